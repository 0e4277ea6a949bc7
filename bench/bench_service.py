"""Service load bench: a burst of calibrations on 2 workers, then status polling latency.

1. 20 calibrations of a small problem (4x4x4 box, 2 chains, distinct seeds) submitted at
   once to the API with 2 workers: all must succeed and each must store its parameter set
   (none lost); wall time and throughput.
2. GET /v1/calibrations/{id} at 200 requests/s for 30 s over loopback: p50/p99 latency
   (goal p99 < 25 ms) and failures.

Runs its own redis-server (no persistence), uvicorn and workers on free loopback ports.
"""

from __future__ import annotations

import json
import statistics
import tempfile
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import httpx

from client import Client
from client.table import table
from stack.local import local_stack
from stack.redis_server import RedisServer, free_port

CALIBRATIONS = 20
WORKERS = 2
RATE = 200.0
"""Status requests per second."""
DURATION = 30.0
"""Seconds of status polling."""
POLLERS = 8
"""Threads sharing the polling schedule (each with its own connection)."""

SMALL = {
    **json.loads((Path(__file__).resolve().parents[1] / "examples" / "small-box.json").read_text()),
    "name": "bench box",
}


def burst(url: str) -> list[str]:
    """Submit CALIBRATIONS at once, wait for all; print the table; return their ids."""
    specs = [{**SMALL, "annealing": {**SMALL["annealing"], "seed": s}} for s in range(CALIBRATIONS)]
    started = time.perf_counter()
    with ThreadPoolExecutor(CALIBRATIONS) as pool:
        ids = list(pool.map(lambda spec: Client(url).calibrate(spec)["id"], specs))
    submitted = time.perf_counter() - started
    client = Client(url)
    finals = [client.wait(i, poll=0.2, timeout=600, progress=False) for i in ids]
    wall = time.perf_counter() - started
    succeeded = sum(f["status"] == "succeeded" for f in finals)
    stored = {f["parameter_set_id"] for f in finals if f["parameter_set_id"]}
    listed = {p["id"] for p in client.parameter_sets(name="bench box")}
    lost = CALIBRATIONS - len(stored & listed)
    print(
        table(
            ["calibrations", "workers", "submit s", "wall s", "per min", "succeeded", "lost"],
            [[CALIBRATIONS, WORKERS, submitted, wall, 60 * CALIBRATIONS / wall, succeeded, lost]],
        )
    )
    return ids


def poll(url: str, ids: list[str]) -> None:
    """Open-loop GETs at RATE/s for DURATION s, shared by POLLERS threads; print the table."""
    latencies: list[float] = []
    failures = 0
    lock = threading.Lock()
    start = time.perf_counter() + 0.5

    def run(offset: int) -> None:
        nonlocal failures
        with httpx.Client(base_url=url, timeout=5.0) as http:
            n = 0
            while True:
                due = start + (offset + n * POLLERS) / RATE
                if due - start >= DURATION:
                    return
                time.sleep(max(due - time.perf_counter(), 0))
                sent = time.perf_counter()
                try:
                    ok = http.get(f"/v1/calibrations/{ids[n % len(ids)]}").status_code == 200
                except httpx.HTTPError:
                    ok = False
                elapsed = time.perf_counter() - sent
                with lock:
                    latencies.append(elapsed)
                    failures += not ok
                n += 1

    threads = [threading.Thread(target=run, args=(i,)) for i in range(POLLERS)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    ms = sorted(x * 1000 for x in latencies)
    p99 = ms[int(0.99 * (len(ms) - 1))]
    print(
        table(
            ["requests", "rate /s", "s", "p50 ms", "p99 ms", "max ms", "failures", "p99 < 25 ms"],
            [
                [
                    len(ms),
                    len(ms) / DURATION,
                    DURATION,
                    statistics.median(ms),
                    p99,
                    ms[-1],
                    failures,
                    "yes" if p99 < 25 else "no",
                ]
            ],
        )
    )


def main() -> None:
    logs = Path(tempfile.mkdtemp(prefix="bench-service-"))
    with (
        RedisServer() as redis,
        local_stack(workers=WORKERS, port=free_port(), redis_url=redis.url, log_dir=logs) as url,
    ):
        print(f"\n{CALIBRATIONS} calibrations submitted at once, {WORKERS} workers")
        ids = burst(url)
        print(f"\nstatus polling: {RATE:.0f} requests/s for {DURATION:.0f} s over loopback")
        poll(url, ids)


if __name__ == "__main__":
    main()
