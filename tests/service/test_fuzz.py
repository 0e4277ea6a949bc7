"""Bad input, generated: property-based specs through the whole pipeline, the API fuzzed from
its own OpenAPI document, and oversized requests refused before anything is queued.
"""

from __future__ import annotations

import json
from typing import Any

import pytest
import schemathesis
from hypothesis import HealthCheck, event, given
from hypothesis import settings as hyp_settings
from hypothesis import strategies as st
from pydantic import SecretStr
from schemathesis import GenerationMode
from schemathesis.specs.openapi.checks import negative_data_rejection, positive_data_acceptance
from test_service import PROBLEM_JSON, assert_problem

from fpm.model.spec import FACES
from service.main import create_app
from store import graph

pytestmark = pytest.mark.redis

# --- Property: any spec is either calibrated (or fails with a reason) or refused with a 422 ------


@st.composite
def specs(draw: st.DrawFn) -> dict[str, Any]:
    """Small specs: a valid one (2-4 nodes per axis, selectors and forces on nodes, material
    and settings anywhere in range, edge values included; in one case of three validation
    cases, forces as the load cases'), then in one case of three a single corruption (a value
    out of range, a point off the grid, a missing or unknown field, ...).
    """
    nodes = [draw(st.integers(2, 4)) for _ in range(3)]
    size = [draw(st.sampled_from([0.01, 0.03, 0.1, 1.0])) for _ in range(3)]
    n_nodes = nodes[0] * nodes[1] * nodes[2]

    def grid_point() -> list[float]:
        return [s * draw(st.integers(0, n - 1)) / (n - 1) for s, n in zip(size, nodes, strict=True)]

    def selector() -> dict[str, Any]:
        kind = draw(st.sampled_from(["face", "node", "at", "box"]))
        if kind == "face":
            return {"face": draw(st.sampled_from(FACES))}
        if kind == "node":
            return {"node": draw(st.integers(0, n_nodes - 1))}
        if kind == "at":
            return {"at": grid_point()}
        return {"box": [[0, 0, 0], grid_point()]}

    vectors = st.lists(st.sampled_from([0.0, 0.05, -0.1, 1.0, 1e3, 1e-9]), min_size=3, max_size=3)

    held = draw(st.sampled_from(FACES))  # the solid is held by a face ...
    axis = "xyz".index(held[0])

    def force() -> dict[str, Any]:
        if draw(st.integers(0, 3)) == 0:
            return {"node": draw(st.integers(0, n_nodes - 1)), "vector": draw(vectors)}
        point = grid_point()  # ... and mostly loaded on the opposite face
        point[axis] = size[axis] if held[1] == "-" else 0.0
        return {"at": point, "vector": draw(vectors)}

    spec: dict[str, Any] = {
        "name": draw(st.text(max_size=20)),
        "material": {
            "youngs_modulus": draw(st.sampled_from([1e-3, 1.0, 1e4, 2e5, 1e9, 1e12])),
            "poisson_ratio": draw(
                st.one_of(st.floats(-0.99, 0.49), st.sampled_from([-0.999, 0.0, 0.4999]))
            ),
            "density": draw(st.sampled_from([1e-3, 1.0, 1040.0, 1e5])),
        },
        "geometry": {
            "type": "box",
            "size": size,
            "nodes": nodes,
            "connectivity": draw(st.sampled_from(["axis", "axis+face", "full"])),
        },
        "fixed": [{"face": held}] + [selector() for _ in range(draw(st.integers(0, 1)))],
        "load_cases": [
            {"name": f"case {i}", "forces": [force() for _ in range(draw(st.integers(1, 2)))]}
            for i in range(draw(st.integers(1, 2)))
        ],
        "fpm": {
            "depth": draw(st.one_of(st.integers(0, 4), st.just("auto"))),
            "dt": draw(st.sampled_from([1e-5, 1e-3, 1e-2, 1.0])),
            "max_steps": draw(st.integers(1, 300)),
            "settle_tolerance": draw(st.sampled_from([0.0, 1e-5, 1e-3, 0.5])),
            "stiffness_scale": draw(st.sampled_from([[1, 1, 1], [0.1, 1, 10]])),
        },
        "annealing": {
            "method": draw(st.sampled_from(["two-stage", "paper"])),
            "seed": draw(st.integers(0, 2**31)),
            "chains": draw(st.integers(1, 2)),
            "t_initial": 0.05,
            "t_final": draw(st.sampled_from([0.01, 0.02, 0.04])),
            "beta": draw(st.floats(5.0, 50.0)),  # at most 16 moves per chain
            "c_max": draw(st.sampled_from([0.01, 0.5, 2.0, 1e6])),
        },
    }
    if draw(st.booleans()):  # half of them: the paper's material and settings
        spec["material"] = {"youngs_modulus": 1e4, "poisson_ratio": 0.45, "density": 1040.0}
        spec["fpm"].update(dt=1e-3, max_steps=1000, settle_tolerance=1e-3)
        spec["annealing"]["c_max"] = 2.0
    elif draw(st.booleans()):
        spec["annealing"]["bounds"] = {
            "k": draw(st.sampled_from([[1.0, 1e4], [1e-6, 1e-5], [1e3, 1e9]])),
            "d": draw(st.sampled_from([[1e-9, 2e-9], [0.01, 10.0]])),
        }
    if draw(st.integers(0, 2)) == 0:  # validation cases: loads the fit never sees, any size
        spec["validation_cases"] = [
            {"name": f"unseen {i}", "forces": [force() for _ in range(draw(st.integers(1, 2)))]}
            for i in range(draw(st.integers(1, 2)))
        ]
    if draw(st.integers(0, 2)) == 0:
        draw(st.sampled_from(CORRUPTIONS))(spec, n_nodes)
    return spec


def _set(path: str, value: Any):
    """A corruption: set the dotted ``path`` of the spec to ``value``."""

    def corrupt(spec: dict[str, Any], n_nodes: int) -> None:
        *parents, last = path.split(".")
        target: Any = spec
        for part in parents:
            target = target[int(part)] if part.isdigit() else target[part]
        target[int(last) if last.isdigit() else last] = value

    corrupt.__name__ = f"{path}={value!r}"
    return corrupt


CORRUPTIONS = [
    _set("material.poisson_ratio", 0.5),
    _set("material.poisson_ratio", -1.0),
    _set("material.youngs_modulus", 0.0),
    _set("material.density", -1.0),
    _set("geometry.nodes", [1, 3, 3]),
    _set("geometry.nodes", [0, 0, 0]),
    _set("geometry.size", [0.0, 0.01, 0.01]),
    _set("geometry.connectivity", "diagonal"),
    _set("geometry.type", "sphere"),
    _set("fixed", []),
    _set("fixed.0", {}),
    _set("fixed.0", {"face": "z-", "node": 0}),
    _set("fixed.0", {"node": 10_000}),
    _set("fixed.0", {"at": [0.123, 0.456, 0.789]}),
    _set("fixed.0", {"box": [[5, 5, 5], [6, 6, 6]]}),
    _set("load_cases", []),
    _set("load_cases.0.forces", []),
    _set("load_cases.0.forces.0", {"vector": [0, 0, 1]}),
    _set("load_cases.0.forces.0", {"node": 0, "at": [0, 0, 0], "vector": [0, 0, 1]}),
    _set("load_cases.0.forces.0", {"node": -1, "vector": [0, 0, 1]}),
    _set("load_cases.0.forces.0", {"node": 10_000, "vector": [0, 0, 1]}),
    _set("load_cases.0.forces.0", {"at": [0.0101, 0, 0], "vector": [0, 0, 1]}),
    _set("load_cases.0.forces.0", {"node": 0, "vector": [0, 0]}),
    _set("fpm.depth", -1),
    _set("fpm.depth", "deep"),
    _set("fpm.dt", 0.0),
    _set("fpm.max_steps", 0),
    _set("fpm.settle_tolerance", -1e-5),
    _set("fpm.stiffness_scale", [0, 1, 1]),
    _set("annealing.chains", 0),
    _set("annealing.chains", 5),
    _set("annealing.t_final", 0.05),
    _set("annealing.beta", 1e-9),
    _set("annealing.c_max", 0.0),
    _set("annealing.seed", -1),
    _set("annealing.bounds", {"k": [10.0, 1.0]}),
    _set("annealing.bounds", {"d": [0.0, 1.0]}),
    _set("validation_cases", [{"forces": []}]),
    _set("validation_cases", [{"forces": [{"node": 10_000, "vector": [0, 0, 1]}]}]),
    _set("validation_cases", [{"forces": [{"node": 0, "vector": [0, 0, 0]}]}]),
    _set("validation_cases", [{"forces": [{"at": [0, 0, 0], "vector": [0, 0, 1e9]}]}]),
    _set("colour", "red"),
    _set("fpm", "fast"),
    _set("material", None),
]


FAILURE_REASONS = (
    "annealing chain",
    "damping stage failed",
    "FEM reference failed",
    "reference check failed",
)
"""How a calibration of an accepted spec may fail: the annealer's reason, the damping stage's
(two-stage: no d settles), the FEM's refusal, or a FEM answer no small-strain solid gives."""


@hyp_settings(
    max_examples=300,
    deadline=None,
    database=None,
    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow],
)
@given(spec=specs())
def test_any_spec_calibrates_or_is_refused(api, redis, run_workers, spec):
    redis.flushdb()
    submitted = api.post("/v1/calibrations", json=spec)
    if submitted.status_code == 422:
        event("refused 422")
        problem = assert_problem(submitted, 422)
        assert problem["errors"] and all(e["field"] and e["message"] for e in problem["errors"])
        assert redis.dbsize() == 0  # refused before anything was written or queued
        return
    assert submitted.status_code == 202, submitted.text
    run_workers()  # FEM, chains, damping stage (two-stage) and finalize, in this process
    done = api.get(submitted.headers["location"]).json()
    reason = next((r for r in FAILURE_REASONS if (done["error"] or "").startswith(r)), "")
    event(f"accepted, {done['status']}" + (f" ({reason})" if reason else ""))
    assert done["status"] in ("succeeded", "failed"), done
    for q in graph.queues(redis):
        assert q.count == 0 and q.deferred_job_registry.count == 0  # nothing stuck
    if done["status"] == "succeeded":
        assert done["result"]["k"] > 0 and done["parameter_set_id"]
    else:
        assert done["error"].startswith(FAILURE_REASONS), done["error"]
        assert "Traceback" not in done["error"]
        assert q.failed_job_registry.count == 0 or "FEM" in done["error"]


# --- The API fuzzed from its own OpenAPI document -----------------------------------------------


def operation_labels() -> list[str]:
    """Every operation of the OpenAPI document ('POST /v1/calibrations', ...)."""
    schema = schemathesis.openapi.from_asgi("/openapi.json", create_app())
    return [result.ok().label for result in schema.get_all_operations()]


FUZZ_KEY = "fuzz-key"
FUZZ_EXAMPLES = 30
"""Generated requests per operation and generation mode (valid data, invalid data)."""


@pytest.mark.parametrize("mode", [GenerationMode.POSITIVE, GenerationMode.NEGATIVE])
@pytest.mark.parametrize("label", operation_labels())
def test_api_fuzzed_from_its_openapi(settings, redis, label, mode):
    """No 500s and no response that contradicts the document, for valid and invalid requests."""
    secured = settings.model_copy(update={"api_keys": [SecretStr(FUZZ_KEY)]})
    schema = schemathesis.openapi.from_asgi("/openapi.json", create_app(secured))
    operation = schema.find_operation_by_label(label)
    # A spec can be schema-valid and still not fit its solid (a force `at` no node, a box of
    # one node along an axis): those are 422 by design, so valid data may be refused.
    excluded = [positive_data_acceptance]
    if operation.method == "get":
        excluded.append(negative_data_rejection)  # unknown query parameters are ignored

    @hyp_settings(
        max_examples=FUZZ_EXAMPLES,
        deadline=None,
        database=None,
        suppress_health_check=list(HealthCheck),
    )
    @given(case=operation.as_strategy(generation_mode=mode))
    def fuzz(case):
        response = case.call_and_validate(headers={"X-API-Key": FUZZ_KEY}, excluded_checks=excluded)
        assert response.status_code < 500
        if response.status_code >= 400:
            assert response.headers["content-type"] == [PROBLEM_JSON]

    fuzz()


# --- Too big: refused before any work is queued --------------------------------------------------


def nothing_queued(redis) -> None:
    for q in graph.queues(redis):
        assert q.count == 0 and q.deferred_job_registry.count == 0
    assert redis.dbsize() == 0


def test_streamed_oversized_body_is_413(api, redis, settings, small_spec):
    """A body with no Content-Length (chunked) is cut off once it passes the limit."""
    chunk = json.dumps(small_spec).encode()

    def body():
        yield b'{"name": "'
        sent = 0
        while sent <= settings.max_body_bytes:
            yield b"x" * 65536
            sent += 65536
        yield b'", ' + chunk[1:]

    answer = api.post(
        "/v1/calibrations", content=body(), headers={"content-type": "application/json"}
    )
    assert_problem(answer, 413)
    nothing_queued(redis)


@pytest.mark.parametrize(
    "geometry",
    [
        pytest.param({"type": "box", "size": [1, 1, 1], "nodes": [46, 46, 46]}, id="box"),
        pytest.param(  # 2^21 x 2^21 x 2^22 = 2^64 nodes: np.prod wrapped this to 0
            {"type": "box", "size": [1, 1, 1], "nodes": [2**21, 2**21, 2**22]}, id="box-2^64"
        ),
        pytest.param(
            {"type": "box", "size": [1, 1, 1], "nodes": [10**7, 10**7, 10**7]}, id="box-1e21"
        ),
        pytest.param(
            {"type": "voxels", "occupancy": [[[True] * 15] * 15] * 15, "spacing": [0.01] * 3},
            id="voxels",
        ),
        pytest.param(
            {
                "type": "mesh",
                "nodes": [[i * 0.01, 0, 0] for i in range(2001)],
                "hexahedra": [[0, 1, 2, 3, 4, 5, 6, 7]],
            },
            id="mesh",
        ),
    ],
)
@pytest.mark.parametrize("route", ["/v1/calibrations", "/v1/fem-references"])
def test_geometry_over_the_node_limit_is_refused_before_queueing(
    api, redis, small_spec, geometry, route
):
    small_spec["geometry"] = geometry
    problem = assert_problem(api.post(route, json=small_spec), 422, "geometry")
    assert "over the limit of 2000" in problem["detail"]
    nothing_queued(redis)


def test_listing_offset_past_64_bits_is_422_not_500(api):
    """Found by the fuzzer: Redis refused the range (not an integer), answered 500."""
    assert_problem(api.get("/v1/calibrations", params={"offset": 2**63 - 49}), 422, "offset")
    assert api.get("/v1/calibrations", params={"offset": 10**9}).status_code == 200


def test_springs_too_soft_for_their_volume_term_fail_as_the_chains_say(api, redis, run_workers):
    """Found by the fuzz test above: E 1 GPa at nu 0.4999 with k bounded to 1e-5 N/m puts the
    chains' start at springs 1e-17 of the volume term, whose linearised lattice is singular in
    double precision. The reduced-basis job leaves it to the chains, which fail the calibration
    with the reason and what to change, never a raw solver error."""
    redis.flushdb()
    spec = {
        "name": "stiff",
        "material": {"youngs_modulus": 1e9, "poisson_ratio": 0.4999, "density": 0.001},
        "geometry": {"type": "box", "size": [0.01, 0.1, 1.0], "nodes": [2, 2, 3],
                     "connectivity": "axis+face"},
        "fixed": [{"face": "y-"}],
        "load_cases": [{"name": "a", "forces": [{"at": [0.01, 0.1, 0.5],
                                                 "vector": [1e3, 1e3, 0]}]}],
        "annealing": {"method": "two-stage", "chains": 1, "bounds": {"k": [1e-6, 1e-5]}},
    }  # fmt: skip
    submitted = api.post("/v1/calibrations", json=spec)
    assert submitted.status_code == 202, submitted.text
    run_workers()
    done = api.get(submitted.headers["location"]).json()
    assert done["status"] == "failed"
    assert done["error"].startswith("annealing chain 0 failed: the lattice linearised")
    assert "widen annealing.bounds.k" in done["error"] and "Traceback" not in done["error"]
