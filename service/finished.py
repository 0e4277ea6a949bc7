"""The serialised answers of succeeded calibrations, kept in the API process.

A succeeded calibration's answer (``GET /v1/calibrations/{id}``) never changes: its record is
never written again (:func:`store.records.update_calibration` refuses a finished record), its
jobs have all finished, and a new submission of its spec is answered by it or gets a new id.
Clients poll it all the same (dashboards, scripts waiting on many ids), so the API keeps the
JSON bytes of the last :data:`SIZE` it served and, on the next poll, only reads the record's
stamp (:func:`store.records.calibration_stamp`: its status, times, result and error as stored)
to check that it is still that record: one read and a string comparison instead of the record
and its progress hash read, their JSON decoded and the models built, validated and serialised
again. Redis stays the truth: an answer is served only while Redis holds the same record (a
record gone or replaced is read afresh; with Redis down the poll is a 503 as before).
"""

from __future__ import annotations

import threading
from collections import OrderedDict

from redis import Redis

from store import records

SIZE = 256
"""Answers kept (least recently served dropped first); a paper cube's is about 6 kB."""


class FinishedAnswers:
    """An LRU of (record stamp, JSON bytes) by calibration id, safe across the API's threads."""

    def __init__(self, size: int = SIZE):
        self.size = size
        self._answers: OrderedDict[str, tuple[tuple[str, ...], bytes]] = OrderedDict()
        self._lock = threading.Lock()

    def get(self, redis: Redis, calibration_id: str) -> bytes | None:
        """The kept answer if Redis still holds the record it was made from, else None."""
        with self._lock:
            kept = self._answers.get(calibration_id)
        if kept is None:
            return None
        stamp, body = kept
        if records.calibration_stamp(redis, calibration_id) != stamp:
            with self._lock:
                self._answers.pop(calibration_id, None)
            return None
        with self._lock:
            if calibration_id in self._answers:
                self._answers.move_to_end(calibration_id)
        return body

    def put(self, calibration_id: str, stamp: tuple[str, ...], body: bytes) -> None:
        """Keep ``body``, the answer made from the record of that ``stamp`` (a succeeded one)."""
        with self._lock:
            self._answers[calibration_id] = (stamp, body)
            self._answers.move_to_end(calibration_id)
            while len(self._answers) > self.size:
                self._answers.popitem(last=False)

    def __len__(self) -> int:
        return len(self._answers)
