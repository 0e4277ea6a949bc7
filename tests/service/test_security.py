"""API keys: every /v1 route refuses a missing or wrong key; keys are compared in constant time
and never logged."""

from __future__ import annotations

import hmac
import logging
import re

import pytest
from fastapi.routing import APIRoute
from fastapi.testclient import TestClient
from test_service import assert_problem

import service.deps
from service.main import create_app

pytestmark = pytest.mark.redis

KEY = "k3y-8f2c41d9e0b7-secret"
OTHER = "second-key-0b5e"


@pytest.fixture
def secured(settings, redis):
    keyed = type(settings)(**{**settings.model_dump(), "api_keys": f"{KEY},{OTHER}"})
    app = create_app(keyed)
    with TestClient(app, raise_server_exceptions=False) as client:
        yield app, client


def v1_requests(app) -> list[tuple[str, str]]:
    """(method, path) of every /v1 route of the app, path parameters filled in."""
    out = []
    for route in api_routes(app.routes):
        if route.path.startswith("/v1"):
            path = re.sub(r"\{[^}]+\}", "x", route.path)
            out += [(method, path) for method in sorted(route.methods)]
    return out


def api_routes(routes) -> list[APIRoute]:
    """The APIRoutes among ``routes``, looking inside included routers (FastAPI >= 0.16x)."""
    found = []
    for route in routes:
        if isinstance(route, APIRoute):
            found.append(route)
        elif hasattr(route, "original_router"):
            found += api_routes(route.original_router.routes)
    return found


def test_every_v1_route_refuses_a_missing_or_wrong_key(secured, small_spec):
    app, client = secured
    requests = v1_requests(app)
    documented = [
        (method.upper(), path)
        for path, operations in app.openapi()["paths"].items()
        if path.startswith("/v1")
        for method in operations
    ]
    assert len(requests) == len(documented) >= 10  # all of them, enumerated from the app
    wrong_keys = [
        None,
        "",
        "wrong",
        KEY[:-1],  # a prefix
        KEY + "x",  # an extension
        KEY.upper(),
        f"{KEY},{OTHER}",  # the configured list itself
        " " + KEY,
    ]
    for method, path in requests:
        body = small_spec if method == "POST" else None
        for key in wrong_keys:
            headers = {} if key is None else {"X-API-Key": key}
            answer = client.request(method, path, json=body, headers=headers)
            assert_problem(answer, 401)
            assert answer.headers["www-authenticate"] == "X-API-Key"
        # The key elsewhere than the header does not count.
        assert_problem(client.request(method, path, json=body, params={"api_key": KEY}), 401)
        client.cookies.set("X-API-Key", KEY)
        assert_problem(client.request(method, path, json=body), 401)
        client.cookies.clear()
        for key in (KEY, OTHER):
            answer = client.request(method, path, json=body, headers={"X-API-Key": key})
            assert answer.status_code != 401, (method, path)
            assert answer.status_code < 500, answer.text


def test_keys_are_compared_with_compare_digest(secured, monkeypatch):
    app, client = secured
    calls = []
    real = hmac.compare_digest

    def spy(a, b):
        calls.append((a, b))
        return real(a, b)

    monkeypatch.setattr(service.deps.hmac, "compare_digest", spy)
    assert client.get("/v1/health", headers={"X-API-Key": "guess"}).status_code == 401
    # The guess was compared with every configured key, by compare_digest, as bytes.
    assert calls == [(b"guess", KEY.encode()), (b"guess", OTHER.encode())]
    calls.clear()
    assert client.get("/v1/health", headers={"X-API-Key": OTHER}).status_code == 200
    assert (OTHER.encode(), OTHER.encode()) in calls
    # And nowhere is a key compared with ==.
    source = open(service.deps.__file__).read()
    assert "compare_digest" in source
    assert not re.search(r"(given|key)\s*(==|!=)|(==|!=)\s*k\.get_secret_value", source)


def test_keys_are_never_logged_or_echoed(secured, caplog, small_spec, settings):
    app, client = secured
    caplog.set_level(logging.DEBUG)  # every logger, every level
    seen = []
    for key in (KEY, "not-" + KEY):
        headers = {"X-API-Key": key}
        seen += [
            client.get("/v1/health", headers=headers),
            client.post("/v1/calibrations", json=small_spec, headers=headers),
            client.post("/v1/calibrations", json={"bad": 1}, headers=headers),
            client.get("/v1/calibrations/nope", headers=headers),
            client.get("/v1/nothing-here", headers=headers),
        ]
    assert {r.status_code for r in seen} >= {200, 202, 401, 404, 422}
    # An unreachable Redis (503, logged as a warning) with a key too.
    down = settings.model_copy(update={"redis_url": "redis://127.0.0.1:1/0"})
    down = type(settings)(**{**down.model_dump(), "api_keys": KEY})
    with TestClient(create_app(down), raise_server_exceptions=False) as other:
        assert other.get("/v1/health", headers={"X-API-Key": KEY}).status_code == 503
    assert caplog.records  # something was logged, and
    for record in caplog.records:  # no key in any of it
        text = record.getMessage() + repr(record.args) + str(record.exc_info or "")
        assert KEY not in text and OTHER not in text
    for response in seen:
        assert KEY not in response.text and OTHER not in response.text
    # Nor in the settings' own repr (what a startup log line or a traceback would show).
    assert KEY not in repr(app.dependency_overrides) and KEY not in str(down)
