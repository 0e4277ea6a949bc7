"""Store dump and restore: the backup and migration path (``fpmcal store dump`` / ``restore``).

A dump is JSON lines: a header ``{"format": "fpm-store-dump", "version": 1, ...}``, then one
object per record, ``{"kind", "id", "data"}``, sorted by kind (FEM references, calibrations,
parameter sets) and id, every object with sorted keys: the same store dumps the same bytes,
and a dump restored into an empty Redis dumps the same lines again.

- ``fem_reference``: a stored FEM reference (``data``: its ``meta`` hash and its ``reference``);
- ``calibration``: a finished calibration's record (succeeded, failed or canceled; ``data``:
  its hash fields, spec and result included). Queued and running ones are left out: their jobs
  live in the queue, not in the record;
- ``parameter_set``: a stored parameter set (``data``: its JSON).

Restore writes only what is missing (a record already there is kept as it is), so restoring
the same file twice changes nothing; a file of a newer format version is refused.
"""

from __future__ import annotations

import json
from collections.abc import Iterable, Iterator
from typing import Any

from redis import Redis

from . import keys, records
from .records import decode_hash, id_list
from .status import CalibrationStatus

FORMAT = "fpm-store-dump"
VERSION = 1
KINDS = ("fem_reference", "calibration", "parameter_set")
FINISHED = {s.value for s in (CalibrationStatus.SUCCEEDED, CalibrationStatus.FAILED,
                              CalibrationStatus.CANCELED)}  # fmt: skip


class DumpError(ValueError):
    """A file that is not a dump this version can restore."""


def _line(obj: dict[str, Any]) -> str:
    return json.dumps(obj, sort_keys=True, separators=(",", ":"))


def dump(redis: Redis) -> Iterator[str]:
    """The store as JSON lines (no newline characters), header first."""
    yield _line({"format": FORMAT, "version": VERSION, "kinds": list(KINDS)})
    fem = sorted(
        key.decode()[len(keys.fem_reference("")) : -len(":meta")]
        for key in redis.scan_iter(match=keys.fem_meta("*"))
    )
    for fem_hash in fem:
        reference = records.get_fem_reference(redis, fem_hash)
        if reference is None:  # failed or still running: nothing to keep
            continue
        meta = decode_hash(redis.hgetall(keys.fem_meta(fem_hash)))
        data = {"meta": meta, "reference": reference}
        yield _line({"kind": "fem_reference", "id": fem_hash, "data": data})
    for calibration_id in sorted(id_list(redis.zrange(keys.calibrations(), 0, -1))):
        fields = decode_hash(redis.hgetall(keys.calibration(calibration_id)))
        if fields.get("status") in FINISHED:
            yield _line({"kind": "calibration", "id": calibration_id, "data": fields})
    for set_id in sorted(id_list(redis.zrange(keys.parameter_sets(), 0, -1))):
        raw = redis.get(keys.parameter_set(set_id))
        if raw is not None:
            yield _line({"kind": "parameter_set", "id": set_id, "data": json.loads(raw)})


def restore(redis: Redis, lines: Iterable[str]) -> dict[str, int]:
    """Write the dump's records that the store lacks; returns {kind: records written}.

    Raises:
        DumpError: not a dump, a newer format version, or a malformed line (nothing after it
            is written; what was written before it stays, and a second restore completes it).
    """
    it = iter(lines)
    try:
        header = json.loads(next(it))
    except (StopIteration, json.JSONDecodeError):
        raise DumpError("not an fpm store dump: the first line is not its JSON header") from None
    if not isinstance(header, dict) or header.get("format") != FORMAT:
        raise DumpError(f"not an fpm store dump (the header's format is not {FORMAT!r})")
    version = header.get("version")
    if not isinstance(version, int) or version > VERSION:
        raise DumpError(
            f"this dump is format version {version}, newer than this version reads "
            f"({VERSION}): restore it with the fpm-calibration release that wrote it, or newer"
        )
    written = dict.fromkeys(KINDS, 0)
    for number, text in enumerate(it, start=2):
        if not text.strip():
            continue
        try:
            record = json.loads(text)
            kind, ident, data = record["kind"], str(record["id"]), record["data"]
        except (json.JSONDecodeError, KeyError, TypeError):
            raise DumpError(f"line {number}: not a dump record") from None
        if kind not in KINDS:
            raise DumpError(f"line {number}: unknown kind {kind!r}")
        if _restore_one(redis, kind, ident, data):
            written[kind] += 1
    return written


def _restore_one(redis: Redis, kind: str, ident: str, data: dict[str, Any]) -> bool:
    """Write one record unless the store has it; True if written."""
    pipe = redis.pipeline()
    if kind == "fem_reference":
        if redis.exists(keys.fem_reference(ident)):
            return False
        layout, arrays = records.pack_reference(data["reference"])
        pipe.set(keys.fem_reference(ident), records.stored_reference(layout, arrays))
        pipe.delete(keys.fem_meta(ident))
        pipe.hset(keys.fem_meta(ident), mapping={str(k): str(v) for k, v in data["meta"].items()})
    elif kind == "calibration":
        if redis.exists(keys.calibration(ident)):
            return False
        pipe.hset(keys.calibration(ident), mapping={str(k): str(v) for k, v in data.items()})
        pipe.zadd(keys.calibrations(), {ident: float(data.get("created", 0.0))})
        if data.get("status") == CalibrationStatus.SUCCEEDED.value and data.get("spec_hash"):
            pipe.set(keys.calibration_by_spec(data["spec_hash"]), ident, nx=True)
    else:
        if redis.exists(keys.parameter_set(ident)):
            return False
        pipe.set(keys.parameter_set(ident), json.dumps(data))
        pipe.zadd(keys.parameter_sets(), {ident: float(data.get("created", 0.0))})
    pipe.execute()
    return True
