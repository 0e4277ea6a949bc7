"""The local stack: Redis, the API (uvicorn) and N workers, as child processes.

Redis is ``$REDIS_URL``'s server if that is set; otherwise an embedded redis-server
(:mod:`stack.redis_server`) with its data in ``./data/redis`` (append-only file on), so
stored parameter sets and FEM references survive a restart. The stack supervises its
children (:class:`LocalStack`): a worker, the API or the embedded Redis that dies is started
again within a second (Redis on the same port and data directory; one that keeps dying, with a
growing delay). Ctrl-C stops everything: workers first (a job cut short is re-queued and
resumes from its checkpoint on the next start), then the API, then Redis.
"""

from __future__ import annotations

import argparse
import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import ExitStack, contextmanager
from functools import partial
from pathlib import Path

import httpx

from .redis_server import RedisServer

DATA_DIR = Path("data")
STARTUP_TIMEOUT = 30.0
"""Seconds the API may take to answer its health route."""
POLL = 0.2
"""Seconds between two looks of the supervisor at its children."""
STABLE = 10.0
"""A child that dies sooner after its start is restarted with a delay: RESTART_DELAY, doubled
for each such death in a row, at most MAX_RESTART_DELAY seconds."""
RESTART_DELAY = 0.5
MAX_RESTART_DELAY = 30.0


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


class Child:
    """A supervised child process: how to start it, the running one, and its restarts."""

    def __init__(
        self,
        name: str,
        start: Callable[[], subprocess.Popen[bytes]],
        process: subprocess.Popen[bytes] | None = None,
    ):
        self.name = name
        self._start = start
        self.process = process if process is not None else start()
        self.started = time.monotonic()
        self.quick_deaths = 0
        self.restart_at: float | None = None

    def restart(self) -> None:
        self.process = self._start()
        self.started = time.monotonic()
        self.restart_at = None


class LocalStack:
    """Redis, the API and ``workers`` workers as supervised children (a context manager).

    Redis: ``redis_url``'s server, else $REDIS_URL's, else an embedded one in ``data_dir``
    (:attr:`redis`; restarted on its port and data directory if it dies). The API's and
    workers' logs go to the terminal, or to files in ``log_dir`` if given. A thread looks at
    the children every :data:`POLL` seconds and starts again any that died (:attr:`restarts`
    counts them by name: ``redis``, ``api``, ``worker-0``, ...).
    """

    def __init__(
        self,
        workers: int = 2,
        port: int = 8000,
        host: str = "127.0.0.1",
        data_dir: Path = DATA_DIR,
        redis_url: str | None = None,
        log_dir: Path | None = None,
    ):
        self.n_workers = workers
        self.host, self.port = host, port
        self.data_dir, self.log_dir = data_dir, log_dir
        self.redis_url = redis_url or os.environ.get("REDIS_URL") or ""
        self.url = f"http://{host}:{port}"
        self.redis: RedisServer | None = None
        self.children: list[Child] = []
        self.restarts: dict[str, int] = {}
        self._stopping = threading.Event()
        self._supervisor: threading.Thread | None = None
        self._exit = ExitStack()

    @property
    def api(self) -> Child:
        return next(c for c in self.children if c.name == "api")

    @property
    def workers(self) -> list[Child]:
        return [c for c in self.children if c.name.startswith("worker-")]

    def _log(self, name: str) -> Path | None:
        return None if self.log_dir is None else self.log_dir / f"{name}.log"

    def __enter__(self) -> LocalStack:
        if self.log_dir is not None:
            self.log_dir.mkdir(parents=True, exist_ok=True)
        with ExitStack() as stack:
            if not self.redis_url:
                redis = RedisServer(data_dir=self.data_dir / "redis")
                self.redis = stack.enter_context(redis)
                self.redis_url = redis.url

                def start_redis() -> subprocess.Popen[bytes]:
                    """The same port and data directory: it replays its append-only file."""
                    process = redis.start().process
                    assert process is not None
                    return process

                self.children.append(Child("redis", start_redis, redis.process))
            env = {**os.environ, "REDIS_URL": self.redis_url}
            uvicorn = ["-m", "uvicorn", "service.main:app", "--host", self.host]
            api = [sys.executable, *uvicorn, "--port", str(self.port)]
            self.children.append(Child("api", lambda: _spawn(api, env, self._log("api"))))
            stack.callback(lambda: _stop([self.api.process], 5.0))
            worker = [sys.executable, "-m", "worker", "--url", self.redis_url]
            for i in range(self.n_workers):
                name = f"worker-{i}"
                self.children.append(Child(name, partial(_spawn, worker, env, self._log(name))))
            stack.callback(lambda: _stop([c.process for c in self.workers], 10.0))
            _wait_until_up(self.url, self.api.process)
            self._supervisor = threading.Thread(
                target=self._supervise, name="stack-supervisor", daemon=True
            )
            self._supervisor.start()
            stack.callback(self._stop_supervising)
            self._exit = stack.pop_all()
        return self

    def __exit__(self, *exc: object) -> None:
        self._exit.close()

    def _stop_supervising(self) -> None:
        self._stopping.set()
        if self._supervisor is not None:
            self._supervisor.join()

    def _supervise(self) -> None:
        while not self._stopping.wait(POLL):
            for child in self.children:
                if self._stopping.is_set():
                    return
                self._look_after(child)

    def _look_after(self, child: Child) -> None:
        """Start ``child`` again if it died (after a delay if it keeps dying)."""
        code = child.process.poll()
        if code is None:
            return
        now = time.monotonic()
        if child.restart_at is None:
            quick = now - child.started < STABLE
            child.quick_deaths = child.quick_deaths + 1 if quick else 0
            delay = 0.0
            if child.quick_deaths > 1:
                delay = min(RESTART_DELAY * 2 ** (child.quick_deaths - 2), MAX_RESTART_DELAY)
            child.restart_at = now + delay
            later = f" in {delay:.1f} s" if delay else ""
            print(f"{child.name} exited (code {code}); restarting{later}", file=sys.stderr)
        if now < child.restart_at:
            return
        try:
            child.restart()
        except (OSError, RuntimeError) as e:  # e.g. Redis's port taken meanwhile
            child.restart_at = now + MAX_RESTART_DELAY
            print(f"{child.name} did not start ({e}); trying again later", file=sys.stderr)
            return
        self.restarts[child.name] = self.restarts.get(child.name, 0) + 1


@contextmanager
def local_stack(
    workers: int = 2,
    port: int = 8000,
    host: str = "127.0.0.1",
    data_dir: Path = DATA_DIR,
    redis_url: str | None = None,
    log_dir: Path | None = None,
) -> Iterator[str]:
    """Start the supervised stack (:class:`LocalStack`); yield the API's URL."""
    with LocalStack(workers, port, host, data_dir, redis_url, log_dir) as stack:
        yield stack.url


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
    """``fpmcal up`` / ``python -m stack.local``: [--workers N] [--port P] [--host H]."""
    parser = argparse.ArgumentParser(prog="fpmcal up", description="run the local stack")
    parser.add_argument("--workers", type=int, default=2, help="worker processes (default 2)")
    parser.add_argument("--port", type=int, default=8000, help="API port (default 8000)")
    parser.add_argument("--host", default="127.0.0.1", help="API address (default 127.0.0.1)")
    args = parser.parse_args(argv)
    run_stack(workers=args.workers, host=args.host, port=args.port)


if __name__ == "__main__":
    main()
