"""The local stack: Redis, the API (uvicorn) and N workers, as child processes.

Redis is ``$REDIS_URL``'s server if that is set; otherwise an embedded redis-server
(:mod:`service.redis_server`) with its data in ``./data/redis`` (append-only file on), so
stored parameter sets and FEM references survive a restart. Ctrl-C stops everything: workers
first (a job cut short is re-queued and resumes from its checkpoint on the next start), then
the API, then Redis.
"""

from __future__ import annotations

import argparse
import os
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from contextlib import ExitStack, contextmanager
from pathlib import Path

import httpx

from .redis_server import RedisServer

DATA_DIR = Path("data")
STARTUP_TIMEOUT = 30.0
"""Seconds the API may take to answer its health route."""


def _spawn(args: list[str], env: dict[str, str], log: Path | None) -> subprocess.Popen[bytes]:
    """A child in a new session (the terminal's Ctrl-C reaches only us; we stop the children
    in order), its output appended to ``log`` if given."""
    out = None if log is None else log.open("ab")
    try:
        return subprocess.Popen(args, env=env, stdout=out, stderr=out, start_new_session=True)
    finally:
        if out is not None:
            out.close()


def _stop(processes: list[subprocess.Popen[bytes]], grace: float) -> None:
    """SIGTERM to each process group (a worker's work horse too), then SIGKILL after ``grace``.

    A job whose horse is stopped this way is re-queued by its worker (it has retries) and
    resumes from its checkpoint.
    """
    for p in processes:
        _signal_group(p, signal.SIGTERM)
    deadline = time.monotonic() + grace
    for p in processes:
        try:
            p.wait(max(deadline - time.monotonic(), 0.1))
        except subprocess.TimeoutExpired:
            _signal_group(p, signal.SIGKILL)
            p.wait()


def _signal_group(p: subprocess.Popen[bytes], sig: signal.Signals) -> None:
    if p.poll() is None:
        try:
            os.killpg(p.pid, sig)
        except ProcessLookupError:
            pass


def _wait_until_up(url: str, api: subprocess.Popen[bytes]) -> None:
    deadline = time.monotonic() + STARTUP_TIMEOUT
    while time.monotonic() < deadline:
        if api.poll() is not None:
            raise RuntimeError(f"the API exited with code {api.returncode}")
        try:
            # 401 (API keys set) also means it is up.
            if httpx.get(f"{url}/v1/health", timeout=1.0).status_code in (200, 401):
                return
        except httpx.HTTPError:
            pass
        time.sleep(0.1)
    raise RuntimeError(f"the API did not answer on {url} within {STARTUP_TIMEOUT} s")


@contextmanager
def local_stack(
    workers: int = 2,
    port: int = 8000,
    host: str = "127.0.0.1",
    data_dir: Path = DATA_DIR,
    redis_url: str | None = None,
    log_dir: Path | None = None,
) -> Iterator[str]:
    """Start Redis, the API and ``workers`` workers; yield the API's URL.

    Redis: ``redis_url``'s server, else $REDIS_URL's, else an embedded one in ``data_dir``.
    The API's and workers' logs go to the terminal, or to files in ``log_dir`` if given.
    """
    if log_dir is not None:
        log_dir.mkdir(parents=True, exist_ok=True)

    def log(name: str) -> Path | None:
        return None if log_dir is None else log_dir / f"{name}.log"

    with ExitStack() as stack:
        redis_url = redis_url or os.environ.get("REDIS_URL")
        if not redis_url:
            redis_url = stack.enter_context(RedisServer(data_dir=data_dir / "redis")).url
        env = {**os.environ, "REDIS_URL": redis_url}
        uvicorn = ["-m", "uvicorn", "service.main:app", "--host", host, "--port", str(port)]
        api = _spawn([sys.executable, *uvicorn], env, log("api"))
        stack.callback(_stop, [api], 5.0)
        worker = [sys.executable, "-m", "worker", "--url", redis_url]
        pool = [_spawn(worker, env, log(f"worker-{i}")) for i in range(workers)]
        stack.callback(_stop, pool, 10.0)
        url = f"http://{host}:{port}"
        _wait_until_up(url, api)
        yield url


def run_stack(workers: int = 2, host: str = "127.0.0.1", port: int = 8000) -> None:
    """Run the local stack until Ctrl-C (or SIGTERM)."""
    signal.signal(signal.SIGTERM, signal.default_int_handler)
    try:
        with local_stack(workers=workers, port=port, host=host) as url:
            print(f"API on {url} (docs: {url}/docs), {workers} workers. Ctrl-C stops.", flush=True)
            while True:
                time.sleep(3600)
    except KeyboardInterrupt:
        print("stopped.", file=sys.stderr)


def main(argv: list[str] | None = None) -> None:
    """``fpmcal up`` / ``python -m service.stack``: [--workers N] [--port P] [--host H]."""
    parser = argparse.ArgumentParser(prog="fpmcal up", description="run the local stack")
    parser.add_argument("--workers", type=int, default=2, help="worker processes (default 2)")
    parser.add_argument("--port", type=int, default=8000, help="API port (default 8000)")
    parser.add_argument("--host", default="127.0.0.1", help="API address (default 127.0.0.1)")
    args = parser.parse_args(argv)
    run_stack(workers=args.workers, host=args.host, port=args.port)


if __name__ == "__main__":
    main()
