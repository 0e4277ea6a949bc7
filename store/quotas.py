"""Per-key quotas: how many calibrations, and how many lattice nodes, one API key has in flight.

An owner is a short hash of the API key (the key itself is never stored or shown; without keys
every request is the one owner ``"anonymous"``). Each owner has a sorted set of its
calibrations scored by their node count (:func:`store.keys.owner_calibrations`). Usage is read
from the calibrations' own status, never from a counter a dead worker could leave behind: a
calibration that finished, failed or was canceled leaves the set on the next read.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass
from typing import Any

from redis import Redis

from . import keys
from .status import CalibrationStatus

ACTIVE_VALUES = (CalibrationStatus.QUEUED.value, CalibrationStatus.RUNNING.value)
ANONYMOUS = "anonymous"


def owner_of(api_key: str | None) -> str:
    """The owner id of an API key: the first 16 hex digits of its SHA-256 (or "anonymous")."""
    if not api_key:
        return ANONYMOUS
    return hashlib.sha256(api_key.encode()).hexdigest()[:16]


@dataclass(frozen=True)
class Usage:
    """An owner's calibrations queued or running, and their lattice nodes in all."""

    active: int
    nodes: int


def usage(redis: Redis, owner: str) -> Usage:
    """The owner's usage now (finished calibrations are dropped from its set)."""
    key = keys.owner_calibrations(owner)
    return usages(redis, {owner: redis.zrange(key, 0, -1, withscores=True)})[owner]  # type: ignore[dict-item]


def usages(redis: Redis, members: dict[str, list[tuple[Any, float]]]) -> dict[str, Usage]:
    """Each owner's usage from its set's (calibration id, nodes) ``members`` as read: the
    calibrations' statuses in one round trip (not the whole records), and the finished ones
    dropped from the sets in another (only when there are some)."""
    pipe = redis.pipeline(transaction=False)
    for entries in members.values():
        for raw, _ in entries:
            pipe.hget(keys.calibration(_str(raw)), "status")
    statuses = iter(pipe.execute() if any(members.values()) else [])
    out = {}
    for owner, entries in members.items():
        active, nodes, done = 0, 0, []
        for raw, score in entries:
            status = next(statuses)
            if status is not None and _str(status) in ACTIVE_VALUES:
                active += 1
                nodes += int(score)
            else:
                done.append(_str(raw))
        if done:
            pipe.zrem(keys.owner_calibrations(owner), *done)
        out[owner] = Usage(active, nodes)
    if len(pipe):
        pipe.execute()
    return out


def add(redis: Redis, owner: str, calibration_id: str, nodes: int) -> None:
    """Count a new calibration of ``nodes`` lattice nodes against ``owner``."""
    pipe = redis.pipeline()
    pipe.zadd(keys.owner_calibrations(owner), {calibration_id: nodes})
    pipe.sadd(keys.owners(), owner)
    pipe.execute()


def all_usage(redis: Redis) -> dict[str, Usage]:
    """Every owner's usage (for /metrics and the web view: owner ids, never keys)."""
    owners = sorted(
        o.decode() if isinstance(o, bytes) else str(o) for o in redis.smembers(keys.owners())
    )
    return {owner: usage(redis, owner) for owner in owners}


def _str(value: Any) -> str:
    return value.decode() if isinstance(value, bytes) else str(value)
