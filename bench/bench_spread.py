"""One calibration over 1, 2 and 3 workers: wall time, critical path and
the timeline of the organ at h = 3 mm (``python -m bench spread``; ``spread 5`` for h = 5 mm;
``spread 1.75`` for the 93,705-node organ on 2 workers, against the goals of 180 s wall, 120 s
critical path and 3 GB per worker).

Each run starts its own redis-server and ``python -m worker`` processes, submits the organ
(families+volume, the bench's spec) through the job graph and reads the result's jobs and
critical path (worker.spread, store.timeline), while a thread samples each worker's memory
(the PSS of its process and of its work horse, from /proc, every SAMPLE seconds: a peak between
two looks is missed). The fitted parameters must be identical to the bit whatever the number of
workers.
"""

from __future__ import annotations

import os
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

from bench.bench_calibration import load, verdict
from bench.organ_calibration import organ_settings

ROOT = Path(__file__).resolve().parents[1]
WORKERS = (1, 2, 3)
LARGE_WALL_GOAL, LARGE_PATH_GOAL = 180.0, 120.0
"""The goals of ``spread 1.75`` (the 93,705-node organ): wall with 2 workers, critical path, s."""
MEMORY_GOAL = 3e9
"""The goal: bytes per worker (its process and its work horse together, PSS)."""
SAMPLE = 0.5
"""Seconds between the memory sampler's looks."""


def pss(pid: int) -> int:
    """Proportional set size of process ``pid``, bytes (0 once it has gone): shared pages
    split between the processes sharing them, so a worker's and its forked horse's add up."""
    try:
        with open(f"/proc/{pid}/smaps_rollup") as f:
            return next(int(line.split()[1]) * 1024 for line in f if line.startswith("Pss:"))
    except (OSError, StopIteration, ValueError):
        return 0


def children(pid: int) -> list[int]:
    """Processes whose parent is ``pid`` (a worker's work horse)."""
    found = []
    for entry in os.listdir("/proc"):
        if entry.isdigit():
            try:
                with open(f"/proc/{entry}/stat") as f:
                    parent = int(f.read().rsplit(")", 1)[1].split()[1])
            except (OSError, IndexError, ValueError):
                continue
            if parent == pid:
                found.append(int(entry))
    return found


class PeakMemory:
    """Samples every SAMPLE seconds, on a thread, each worker process's PSS plus its
    children's, and keeps each worker's peak (bytes) and when it came (Unix s); Linux /proc
    only (0 elsewhere)."""

    def __init__(self, pids: list[int]):
        self.peaks = dict.fromkeys(pids, 0)
        self.when = dict.fromkeys(pids, 0.0)
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._run, daemon=True)

    def _run(self) -> None:
        while not self.stop.wait(SAMPLE):
            for pid in self.peaks:
                now = pss(pid) + sum(pss(child) for child in children(pid))
                if now > self.peaks[pid]:
                    self.peaks[pid], self.when[pid] = now, time.time()

    def __enter__(self) -> PeakMemory:
        self.thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop.set()
        self.thread.join()


FITTED = ("k", "stiffness", "volume_stiffness", "d", "d_min", "depth", "settle_steps",
          "relative_discrepancy")  # fmt: skip


def calibrate_on(
    redis_url: str, spec: dict[str, Any], workers: int
) -> tuple[float, dict, list[tuple[int, float]]]:
    """(wall s from submission to the end, the result, each worker's peak PSS in bytes with
    its work horse and when, Unix s) of one calibration on ``workers`` fresh worker processes
    (stopped afterwards)."""
    from redis import Redis
    from rq import Worker

    from store import graph, records

    redis = Redis.from_url(redis_url)
    redis.flushdb()
    command = [sys.executable, "-m", "worker", "--url", redis_url]
    started = [
        subprocess.Popen(command, cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                         start_new_session=True)
        for _ in range(workers)
    ]  # fmt: skip
    try:
        while len(Worker.all(connection=redis)) < workers:
            time.sleep(0.2)
        t0 = time.time()
        with PeakMemory([p.pid for p in started]) as memory:
            record, _ = graph.submit_calibration(redis, spec, graph.JobOptions(retries=1))
            while True:
                done = records.get_calibration(redis, record.id)
                assert done is not None
                if done.status.terminal:
                    break
                time.sleep(0.5)
            wall = time.time() - t0
    finally:
        for process in started:
            os.killpg(process.pid, 15)
            process.wait()
    if done.result is None:
        raise RuntimeError(f"the calibration {done.status}: {done.error}")
    return wall, done.result, [(memory.peaks[p], memory.when[p]) for p in memory.peaks]


def timeline(result: dict[str, Any]) -> None:
    t0 = result["jobs"][0]["start"]
    for s in result["jobs"]:
        print(
            f"     {s['name']:<38}{s['worker'][:8]:>9}{s['start'] - t0:8.1f}{s['end'] - t0:8.1f}"
            f"{s['end'] - s['start']:8.1f}{s['cpu']:8.1f}"
        )
        for p in s.get("phases", []):  # what the damping job did alone, and on how many cores
            print(
                f"       {p['phase']:<36}{'':>9}{'':>8}{'':>8}{p['seconds']:8.1f}{p['cpu']:8.1f}"
                f"  ({p['cpu'] / max(p['seconds'], 1e-9):.2f} cores)"
            )
    print(f"     critical path: {' -> '.join(result['critical_path'])}")


def main() -> None:
    import fpm
    from bench import results
    from service.limits import dump_spec
    from stack.redis_server import RedisServer

    args = sys.argv[2:]
    h = 0.005 if "5" in args else 0.00175 if "1.75" in args else 0.003
    counts = tuple(int(a.split("=")[1]) for a in args if a.startswith("workers="))
    # the 10^5-node organ: 2 workers unless named (workers=1 workers=2 workers=3)
    workers = counts or ((2,) if h == 0.00175 else WORKERS)
    problem = fpm.load_problem(organ_settings(h, "families+volume")[0])
    spec = dump_spec(problem.spec)
    print(f"\nThe organ at h = {1e3 * h:g} mm over {workers} workers ({load()})")
    fitted: dict[int, dict[str, Any]] = {}
    with RedisServer() as server:
        for n in workers:
            wall, result, peaks = calibrate_on(server.url, spec, n)
            fitted[n] = {name: result[name] for name in FITTED}
            jobs = result["jobs"]
            damping = [s for s in jobs if s["name"].startswith("damping")]
            stage = max(s["end"] for s in damping) - min(s["start"] for s in damping)
            print(
                f"\n  {n} worker(s): wall {wall:.1f} s, critical path "
                f"{result['critical_path_seconds']:.1f} s, damping stage {stage:.1f} s, "
                f"CPU {sum(s['cpu'] for s in jobs):.0f} s ({load()})"
            )
            print(f"     {'job':<38}{'worker':>9}{'start':>8}{'end':>8}{'s':>8}{'cpu s':>8}")
            timeline(result)
            t0 = result["jobs"][0]["start"]
            mib = " / ".join(
                f"{p / 2**20:,.0f} MiB at {at - t0:.0f} s" for p, at in sorted(peaks, reverse=True)
            )
            print(f"     peak PSS per worker (its process and work horse, every {SAMPLE} s): {mib}")
            results.record(
                "spread", f"h{1e3 * h:g}mm-{n}w", h=h, workers=n, nodes=problem.n_nodes,
                wall_s=wall, critical_path_s=result["critical_path_seconds"],
                damping_stage_s=stage, cpu_s=sum(s["cpu"] for s in jobs),
                peak_pss_gb=max(p for p, _ in peaks) / 1e9,
                settled_over_static_cost=result["cost"] / result["static_cost"],
                settle_steps=result["settle_steps"], settle_distance=result["settle_distance"],
                settle_distance_measured=result["settle_distance_measured"],
                relative_discrepancy=result["relative_discrepancy"],
                validation_relative_discrepancy=result["validation_relative_discrepancy"],
                d=result["d"], d_min=result["d_min"], warnings=result["warnings"],
            )  # fmt: skip
            if h == 0.00175:
                path, most = result["critical_path_seconds"], max(p for p, _ in peaks)
                print(
                    f"  [{verdict(wall <= LARGE_WALL_GOAL)}] wall <= {LARGE_WALL_GOAL:.0f} s "
                    f"with {n} workers (the goal is for 2): {wall:.0f} s; "
                    f"[{verdict(path <= LARGE_PATH_GOAL)}] "
                    f"critical path <= {LARGE_PATH_GOAL:.0f} s: {path:.0f} s; "
                    f"[{verdict(0 < most <= MEMORY_GOAL)}] <= 3 GB per worker: "
                    f"{most / 1e9:.2f} GB"
                )
    same = all(fitted[n] == fitted[workers[0]] for n in workers)
    print(f"\nsummary: identical parameters with {workers} workers: {verdict(same)}")
    results.record("spread", f"h{1e3 * h:g}mm-same", h=h, workers=list(workers), identical=same)


if __name__ == "__main__":
    main()
