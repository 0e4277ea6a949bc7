"""docker-compose.yml and the Dockerfile match the real entry points and settings."""

from __future__ import annotations

import importlib
import re
import shlex
from pathlib import Path

import pytest
import tomllib
import yaml

from service.settings import Settings
from store import keys
from worker.__main__ import parse_args

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def compose() -> dict:
    return yaml.safe_load((ROOT / "docker-compose.yml").read_text())


def setting_names() -> set[str]:
    """Environment variables the service reads."""
    names = {f"FPM_{name.upper()}" for name in Settings.model_fields}
    return names | {"REDIS_URL"}


def test_redis_is_durable_and_healthchecked(compose):
    redis = compose["services"]["redis"]
    command = " ".join(redis["command"])
    for option in ("--appendonly yes", "--appendfsync everysec", "--maxmemory-policy noeviction"):
        assert option in command
    assert "redis-cli" in redis["healthcheck"]["test"]
    assert any(v.split(":")[0] in compose["volumes"] for v in redis["volumes"])


def test_api_runs_the_real_app(compose):
    api = compose["services"]["api"]
    command = api["command"]
    assert command[0] == "uvicorn"
    module, attribute = command[1].split(":")
    assert hasattr(importlib.import_module(module), attribute)
    assert set(api["environment"]) <= setting_names()
    assert api["depends_on"]["redis"]["condition"] == "service_healthy"
    port = command[command.index("--port") + 1]
    assert any(p.endswith(f":{port}") for p in api["ports"])


def test_workers_run_the_real_entry_point(compose):
    worker = compose["services"]["worker"]
    command = worker["command"]
    assert command[:3] == ["python", "-m", "worker"]
    args = parse_args(command[3:])
    assert args.queues == list(keys.QUEUES)  # the priority queue first
    assert args.url == compose["services"]["api"]["environment"]["REDIS_URL"]
    assert args.url.split("//")[1].split(":")[0] in compose["services"]
    assert worker["deploy"]["replicas"] == 2
    assert re.fullmatch(r"\d+s", worker["stop_grace_period"])
    assert worker["depends_on"]["redis"]["condition"] == "service_healthy"


def test_dockerfile_ships_every_package_and_runs_the_api():
    dockerfile = (ROOT / "Dockerfile").read_text()
    pyproject = tomllib.loads((ROOT / "pyproject.toml").read_text())
    packages = [
        p.rstrip("*") for p in pyproject["tool"]["setuptools"]["packages"]["find"]["include"]
    ]
    dev_only = {"bench", "research", "manual"}
    shipped = {p.parent.name for p in ROOT.glob("*/__init__.py")} - dev_only
    assert sorted(packages) == sorted(shipped)
    for package in (*packages, "examples"):
        assert re.search(rf"^COPY {package} {package}$", dockerfile, re.M), package
    cmd = re.search(r"^CMD (.+)$", dockerfile, re.M).group(1)
    compose_api = yaml.safe_load((ROOT / "docker-compose.yml").read_text())["services"]["api"]
    assert shlex.split(cmd.replace('"', "").strip("[]").replace(",", " ")) == compose_api["command"]


def test_limits_are_stated_once(compose):
    """The node limit is the service's default (service/settings.py), not a second number here
    (it once capped specs at 20,000 nodes while the service allowed 100,000)."""
    api = compose["services"]["api"]["environment"]
    assert "FPM_MAX_NODES" not in api
    assert Settings.model_fields["max_nodes"].default == 100_000
    worker = compose["services"]["worker"]["environment"]
    assert set(worker) == {"FPM_WORKER_MEMORY"}
