"""A task of the damping stage (:mod:`worker.spread`): its digest and span name, its runs as
stored, the static equilibria its runs settle towards, and its run under a held claim."""

from __future__ import annotations

import hashlib
import json
import threading
import time
from collections.abc import Callable
from dataclasses import asdict
from typing import Any

import numpy as np
from redis import Redis

from fpm.fitting.damping.lockstep import (
    CaseRun,
    Request,
    Verdict,
    lockstep_cpu,
)
from fpm.fitting.damping.validation import Validation
from store import scratch


def task_digest(spec: dict[str, Any]) -> str:
    """The digest of a task's spec (floats by their exact hexadecimal form; ``after``, the
    span it waits for, left out)."""

    def exact(x: Any) -> Any:
        if isinstance(x, float):
            return x.hex()
        if isinstance(x, dict):
            return {k: exact(v) for k, v in x.items() if k != "after"}
        return [exact(v) for v in x] if isinstance(x, list | tuple) else x

    return hashlib.sha256(json.dumps(exact(spec), sort_keys=True).encode()).hexdigest()[:32]


VALIDATION_SPAN = "damping: validation cases"


def task_name(spec: dict[str, Any]) -> str:
    """A task's span name (:mod:`store.timeline`)."""
    if "validation" in spec:
        return VALIDATION_SPAN
    if "request" in spec:
        r = spec["request"]
        within = "" if r["budget"] is None else f" within {r['budget']}"
        within += " within the margin's caps" if r.get("caps_later") else ""
        return f"damping: d {r['d']:.6g}{within}, all load cases"
    return f"damping: d {spec['d']:.6g}, load case {spec['load_case']}"


def to_stored(runs: list[CaseRun], verdict: Verdict | None) -> tuple[dict[str, Any], bytes]:
    """A task's runs (and a request's verdict) as stored: (JSON dict, the runs' float64
    displacements one after the other)."""
    data: dict[str, Any] = {"runs": [], "verdict": None if verdict is None else asdict(verdict)}
    for run in runs:
        entry = {k: v for k, v in asdict(run).items() if k != "displacements"}
        data["runs"].append({**entry, "shape": list(run.displacements.shape)})
    raw = b"".join(np.ascontiguousarray(r.displacements, dtype=np.float64).tobytes() for r in runs)
    return data, raw


def from_stored(data: dict[str, Any], raw: bytes) -> tuple[list[CaseRun], Verdict | None]:
    """The stored runs and verdict back (:func:`to_stored`)."""
    runs, offset = [], 0
    for entry in data["runs"]:
        shape = tuple(entry["shape"])
        size = int(np.prod(shape)) * 8
        displacements = np.frombuffer(raw[offset : offset + size], dtype=np.float64)
        offset += size
        runs.append(
            CaseRun(
                steps=int(entry["steps"]),
                state=int(entry["state"]),
                settle_force=float(entry["settle_force"]),
                history=[(int(n), float(r)) for n, r in entry["history"]],
                displacements=displacements.reshape(shape).copy(),
            )
        )
    v = data["verdict"]
    verdict = None if v is None else Verdict(v["outcome"], v["total"], tuple(v["predicted"]))
    return runs, verdict


def validation_stored(found: Validation) -> tuple[dict[str, Any], bytes]:
    """A validation task's answer as stored (JSON; no arrays)."""
    return {"validation": asdict(found)}, b""


def save_targets(redis: Redis, calibration_id: str, targets: np.ndarray) -> None:
    """The static equilibria (L, N, 3) m the d search's runs settle towards, for its tasks."""
    data = np.ascontiguousarray(targets, dtype=np.float64)
    scratch.save_damping_targets(redis, calibration_id, list(data.shape), data.tobytes())


def targets_of(redis: Redis, calibration_id: str, spec: dict[str, Any]) -> np.ndarray | None:
    """A task's static equilibria (L, N, 3) m (None: its runs do not settle towards them).

    Raises:
        LookupError: the plan names them but they are gone."""
    if spec.get("distance") is None:
        return None
    found = scratch.get_damping_targets(redis, calibration_id)
    if found is None:
        raise LookupError("the damping stage's static equilibria are gone")
    shape, raw = found
    return np.frombuffer(raw, dtype=np.float64).reshape(shape).copy()


def request_of(spec: dict[str, Any]) -> Request:
    """A request task's :class:`Request` (JSON lists back to tuples)."""
    r = spec["request"]
    return Request(**{**r, "caps": tuple(r["caps"])})


class Holding:
    """Holds a task's claim while its run goes on: renewed every third of its expiry on a
    thread of its own (a holder killed with its process stops renewing)."""

    def __init__(self, redis: Redis, calibration_id: str, task: str, holder: str):
        self.args = (redis, calibration_id, task, holder)
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._renew, daemon=True)

    def _renew(self) -> None:
        while not self.stop.wait(scratch.CLAIM_TTL / 3):
            scratch.renew_claim(*self.args)

    def __enter__(self) -> Holding:
        self.thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop.set()
        self.thread.join()


def run_task(
    redis: Redis,
    calibration_id: str,
    task: str,
    spec: dict[str, Any],
    holder: str,
    worker: str,
    run: Callable[[], Any],
    clock: Callable[[], float] = time.process_time,
    stored: Callable[[Any], tuple[dict[str, Any], bytes]] = lambda found: to_stored(*found),
) -> float:
    """Run a claimed task (``run``: its runs and a request's verdict, or what ``stored``
    turns into its stored form), store them and its span, its CPU seconds by ``clock`` (a
    case job's horse: its process; the damping job's thread that ran it: :func:`task_clock`);
    return those CPU seconds. On an error give the claim up (another may take the task) and
    raise."""
    start, cpu = time.time(), clock()
    try:
        with Holding(redis, calibration_id, task, holder):
            found = run()
    except BaseException:
        scratch.release_claim(redis, calibration_id, task)
        raise
    scratch.save_case_run(redis, calibration_id, task, *stored(found))
    cpu = clock() - cpu
    span = {
        "name": task_name(spec),
        "worker": worker,
        "start": start,
        "end": time.time(),
        "cpu": cpu,
        "after": [spec["after"]],
        "task": task,
    }
    scratch.add_span(redis, calibration_id, span)
    return cpu


def task_clock() -> float:
    """A task run on one of the damping job's threads: that thread's CPU seconds and those
    its lockstep runs spent on the pool's threads
    (:func:`fpm.fitting.damping.lockstep.lockstep_cpu`)."""
    return time.thread_time() + lockstep_cpu()
