"""Status polling under open-loop load: what a dashboard of clients asks of a finished calibration.

The paper's cube (``examples/paper-material-a.json``) is calibrated once through a local stack
of its own (redis-server without persistence, uvicorn, one worker, on free loopback ports);
then requests are sent on a fixed schedule, RATE per second for DURATION seconds, alternately
``GET /v1/calibrations/{id}`` of that calibration and ``GET /v1/health``, over CLIENTS
keep-alive connections (request i on connection i mod CLIENTS). Open loop: a request is due at
its time whether or not the answers before it came back, and its latency is counted from that
time, so a server that falls behind shows it in the tail (and in the throughput) instead of
slowing the load down.

The load generator is plain asyncio on raw sockets (HTTP/1.1, one event loop): at 200 requests
per second it costs this process a few percent of a core, which on 2 cores it shares with the
API, Redis and the worker. Records per route and for both together: requests due, answered
(200 in full), p50/p99/max latency (ms) and throughput (answered per second).
``FPM_BENCH_POLL_SECONDS`` (30) and ``FPM_BENCH_POLL_RATE`` (200) change the load.
"""

from __future__ import annotations

import asyncio
import json
import os
import statistics
import tempfile
import time
from pathlib import Path
from urllib.parse import urlsplit

from bench import results
from client import Client
from client.table import table
from stack.local import local_stack
from stack.redis_server import RedisServer, free_port

RATE = float(os.environ.get("FPM_BENCH_POLL_RATE", "200"))
"""Requests per second, both routes together."""
DURATION = float(os.environ.get("FPM_BENCH_POLL_SECONDS", "30"))
"""Seconds of load."""
CLIENTS = 16
"""Keep-alive connections sharing the schedule."""
GOAL_P99_MS = 25.0
"""The README's goal for a status poll's p99, ms."""
TIMEOUT = 5.0
"""Seconds an answer may take before it counts as not answered."""
SPEC = Path(__file__).resolve().parents[1] / "examples" / "paper-material-a.json"


async def _answer(reader: asyncio.StreamReader) -> tuple[int, bytes]:
    """Read one HTTP/1.1 response: (status code, body). Content-Length or chunked bodies."""
    head = await reader.readuntil(b"\r\n\r\n")
    lines = head.decode("latin-1").split("\r\n")
    code = int(lines[0].split()[1])
    headers = {k.strip().lower(): v.strip() for k, _, v in (x.partition(":") for x in lines[1:])}
    if "content-length" in headers:
        return code, await reader.readexactly(int(headers["content-length"]))
    body = b""
    while size := int((await reader.readuntil(b"\r\n")).strip(), 16):
        body += await reader.readexactly(size)
        await reader.readexactly(2)
    await reader.readexactly(2)
    return code, body


async def _connection(
    host: str, port: int, schedule: list[tuple[float, str]], out: list[tuple[str, float, bool]]
) -> None:
    """Send the requests of ``schedule`` ((due time on the perf_counter clock, path), in order)
    on one keep-alive connection; append (path, latency from the due time in s, answered 200)
    to ``out``. A connection that fails or times out is opened again for the next request."""
    conn: tuple[asyncio.StreamReader, asyncio.StreamWriter] | None = None
    for due, path in schedule:
        await asyncio.sleep(max(due - time.perf_counter(), 0.0))
        ok = False
        try:
            if conn is None:
                conn = await asyncio.open_connection(host, port)
            reader, writer = conn
            writer.write(f"GET {path} HTTP/1.1\r\nHost: {host}:{port}\r\n\r\n".encode())
            code, _ = await asyncio.wait_for(_answer(reader), TIMEOUT)
            ok = code == 200
        except (OSError, asyncio.TimeoutError, asyncio.IncompleteReadError, ValueError):
            if conn is not None:
                conn[1].close()
            conn = None
        out.append((path, time.perf_counter() - due, ok))
    if conn is not None:
        conn[1].close()


async def load(
    url: str, paths: list[str], rate: float, duration: float, clients: int
) -> list[tuple[str, float, bool]]:
    """Open-loop load: request i (path ``paths[i % len(paths)]``) due at i / rate s, sent on
    connection i mod ``clients``; returns (path, latency s, answered) per request."""
    parts = urlsplit(url)
    host, port = parts.hostname or "127.0.0.1", parts.port or 80
    n = int(rate * duration)
    start = time.perf_counter() + 0.5
    schedules: list[list[tuple[float, str]]] = [[] for _ in range(clients)]
    for i in range(n):
        schedules[i % clients].append((start + i / rate, paths[i % len(paths)]))
    out: list[tuple[str, float, bool]] = []
    await asyncio.gather(*(_connection(host, port, s, out) for s in schedules))
    return out


def summary(label: str, rows: list[tuple[str, float, bool]], duration: float) -> dict:
    """Requests, answered, p50/p99/max (ms, of the answered) and throughput of ``rows``."""
    ms = sorted(1000 * t for _, t, ok in rows if ok)
    answered = len(ms)
    return {
        "route": label,
        "requests": len(rows),
        "answered": answered,
        "p50_ms": statistics.median(ms) if ms else None,
        "p99_ms": ms[int(0.99 * (answered - 1))] if ms else None,
        "max_ms": ms[-1] if ms else None,
        "throughput_per_s": answered / duration,
    }


def poll(url: str, calibration_id: str) -> list[dict]:
    """Run the load on ``url``; print and return the summaries (both routes, then each)."""
    status, health = f"/v1/calibrations/{calibration_id}", "/v1/health"
    rows = asyncio.run(load(url, [status, health], RATE, DURATION, CLIENTS))
    out = [summary("both", rows, DURATION)]
    for label, path in (("status", status), ("health", health)):
        out.append(summary(label, [r for r in rows if r[0] == path], DURATION))
    print(
        table(
            ["route", "requests", "answered", "p50 ms", "p99 ms", "max ms", "per s"],
            [
                [
                    s["route"],
                    s["requests"],
                    s["answered"],
                    s["p50_ms"],
                    s["p99_ms"],
                    s["max_ms"],
                    s["throughput_per_s"],
                ]
                for s in out
            ],
        )
    )
    return out


def main() -> None:
    logs = Path(tempfile.mkdtemp(prefix="bench-polling-"))
    with (
        RedisServer() as redis,
        local_stack(workers=1, port=free_port(), redis_url=redis.url, log_dir=logs) as url,
    ):
        spec = json.loads(SPEC.read_text())
        done = Client(url).calibrate(spec, wait=True, progress=False)
        assert done["status"] == "succeeded", done.get("error")
        with Client(url) as client:
            size = len(json.dumps(client.get(done["id"])))
        print(
            f"\nopen-loop polling of a finished paper cube ({size:,} bytes of JSON) and the "
            f"health route: {RATE:.0f} requests/s for {DURATION:.0f} s, {CLIENTS} keep-alive "
            f"clients, load average {os.getloadavg()[0]:.2f} before"
        )
        for s in poll(url, done["id"]):
            results.record(
                "polling",
                "open-loop",
                **s,
                rate_per_s=RATE,
                seconds=DURATION,
                clients=CLIENTS,
                status_bytes=size,
                goal_p99_ms=GOAL_P99_MS,
            )


if __name__ == "__main__":
    main()
    results.save("polling", "python -m bench.bench_polling")
