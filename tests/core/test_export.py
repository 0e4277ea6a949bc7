"""Export of a fitted parameter set with its lattice (fpm/io/export/): json consistent with the
lattice and re-simulated by a plain loop, vtu read back by meshio, the SOFA scene checked
against SOFA's documented component and attribute names, `fpmcal export`, and
GET /v1/parameter-sets/{id}/export on the in-process app and the live stack."""

from __future__ import annotations

import copy
import gzip
import json
import re
import threading
import xml.etree.ElementTree as ET
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import httpx
import meshio
import numpy as np
import pytest
from redis import ConnectionPool, Redis
from rq.job import Job, JobStatus
from rq.serializers import JSONSerializer

import client.sdk as sdk_module
import fpm
from client import Client
from fpm.dynamics.equilibrium import static_equilibrium
from fpm.dynamics.simulation import fpm_model
from fpm.io.export import (
    ExportError,
    Parameters,
    build_lattice,
    engine_parameters,
    export,
    fpm_displacements,
)
from fpm.model.perturbed_list import perturbed_list
from fpmcal.cli import main
from store import graph, keys, records, scratch
from store.hashing import export_hash

ROOT = Path(__file__).resolve().parents[2]
SMALL: dict[str, Any] = json.loads((ROOT / "examples" / "small-box.json").read_text())

# One k per family and a per-axis scale, so that every spring's stiffness is its own.
FAMILIES_SPEC = copy.deepcopy(SMALL)
FAMILIES_SPEC["fpm"].update(stiffness="families", stiffness_scale=[1.0, 1.0, 1.5], max_steps=2000)
RECORD = {"stiffness": {"axis": 40.0, "face": 20.0, "body": 25.0}, "d": 0.15, "depth": 3}

# What SOFA's sources define for each component the scene uses (names checked in
# sofa-framework/sofa: SpringForceField.inl and LinearSpring.h (spring = m1 m2 ks kd initpos),
# DiagonalMass.inl (vertexMass), UniformVelocityDampingForceField.inl (dampingCoefficient,
# implicit), ConstantForceField.inl (indices, forces), FixedProjectiveConstraint (indices),
# MeshTopology (position, hexahedra), EulerImplicitSolver, CGLinearSolver, MechanicalObject).
SOFA_ATTRIBUTES = {
    "Node": {"name", "dt", "gravity"},
    "RequiredPlugin": {"name"},
    "DefaultAnimationLoop": set(),
    "EulerImplicitSolver": {"name", "rayleighStiffness", "rayleighMass"},
    "CGLinearSolver": {"name", "iterations", "tolerance", "threshold"},
    "MechanicalObject": {"name", "template", "position"},
    "MeshTopology": {"name", "position", "hexahedra"},
    "DiagonalMass": {"name", "vertexMass"},
    "SpringForceField": {"name", "spring"},
    "UniformVelocityDampingForceField": {"name", "dampingCoefficient", "implicit"},
    "FixedProjectiveConstraint": {"name", "indices"},
    "ConstantForceField": {"name", "indices", "forces"},
}


@pytest.fixture(scope="module")
def problem() -> Any:
    return fpm.load_problem(FAMILIES_SPEC)


def numbers(text: str) -> np.ndarray:
    return np.array([float(v) for v in text.split()])


def plain_fpm(data: dict[str, Any], case: int) -> tuple[np.ndarray, int]:
    """The FPM step written from the json export alone (docs/howto/export.md, *The step in
    NumPy*): node by node in perturbed-list order, semi-implicit Euler, implicit nodal
    damping; stops once the largest unbalanced force is below the settle tolerance times the
    largest applied force, or once the 2-norm of the unbalanced forces is below the case's
    settle stiffness times the 2-norm of the displacements. Returns the displacements and the
    steps taken."""
    x0 = np.asarray(data["nodes"])
    m = np.asarray(data["masses"])
    p = data["parameters"]
    dt, d = p["dt"], p["d"]
    springs = np.asarray(data["springs"])
    i, j = springs[:, 0].astype(int), springs[:, 1].astype(int)
    ends = np.concatenate([i, j])
    order_by_node = np.argsort(ends, kind="stable")
    other = np.concatenate([j, i])[order_by_node]
    rest = np.concatenate([springs[:, 2], springs[:, 2]])[order_by_node]
    k = np.concatenate([springs[:, 3], springs[:, 3]])[order_by_node]
    start = np.searchsorted(ends[order_by_node], np.arange(len(x0) + 1))
    load = data["load_cases"][case]
    force = np.zeros_like(x0)
    force[load["nodes"]] = load["forces"]
    order = np.concatenate(load["perturbed_layers"]).astype(int)
    settle = p["settle_tolerance"] * np.linalg.norm(force[order], axis=1).max()
    stiffness = load["settle_stiffness"]
    x, v = x0.copy(), np.zeros_like(x0)
    for step in range(1, p["max_steps"] + 1):
        worst = total = 0.0
        for n in order:
            s = slice(start[n], start[n + 1])
            r = x[other[s]] - x[n]
            length = np.linalg.norm(r, axis=1)
            f = force[n] + ((k[s] * (length - rest[s]) / length)[:, None] * r).sum(axis=0)
            worst = max(worst, float(np.linalg.norm(f)))
            total += float(f @ f)
            a = dt / m[n]
            v[n] = (v[n] + a * f) / (1 + a * d)
            x[n] = x[n] + dt * v[n]
        if worst < settle or np.sqrt(total) < stiffness * np.linalg.norm(x[order] - x0[order]):
            return x - x0, step
    return x - x0, p["max_steps"]


# ------------------------------------------------------------------ json


def test_json_export_is_the_lattice(problem):
    data = json.loads(export(problem, RECORD, "json"))
    assert data["units"]["stiffness"] == "N/m" and data["units"]["damping"] == "N s/m"
    nodes, springs = np.asarray(data["nodes"]), np.asarray(data["springs"])
    assert len(springs) == len(problem.solid.springs) == 468
    i, j = springs[:, 0].astype(int), springs[:, 1].astype(int)
    e = nodes[j] - nodes[i]
    np.testing.assert_allclose(springs[:, 2], np.linalg.norm(e, axis=1), rtol=1e-12)
    family_k = np.array([40.0, 20.0, 25.0])[data["spring_family"]]
    scale = (e / springs[:, 2:3]) ** 2 @ np.array([1.0, 1.0, 1.5])
    np.testing.assert_allclose(springs[:, 3], family_k * scale, rtol=1e-12)
    rho_v = 1040.0 * 0.03**3
    assert sum(data["masses"]) == pytest.approx(rho_v, rel=1e-12)
    assert data["fixed"] == np.flatnonzero(nodes[:, 2] == 0).tolist()
    p = data["parameters"]
    assert (p["d"], p["dt"], p["depth"]) == (0.15, 0.001, 3)
    assert len(data["hexahedra"]) == 27
    model = fpm_model(problem)
    for c, case in enumerate(data["load_cases"]):
        plist = perturbed_list(model.adjacency, problem.load_cases[c].nodes, problem.fixed, 3)
        layers = [plist.layer(n).tolist() for n in range(len(plist.layer_start) - 1)]
        assert case["perturbed_layers"] == layers and sum(map(len, layers)) == 48
        assert case["nodes"] == problem.load_cases[c].nodes.tolist()


def test_a_plain_loop_on_the_json_export_reproduces_the_fpm(problem):
    data = json.loads(export(problem, RECORD, "json"))
    lattice = build_lattice(problem, Parameters.from_record(problem, RECORD))
    fpm_u, steps, settled = fpm_displacements(lattice)
    assert all(settled)
    for case in range(len(problem.load_cases)):
        u, taken = plain_fpm(data, case)
        assert abs(taken - steps[case]) <= 1
        scale = np.abs(fpm_u[case]).max()
        np.testing.assert_allclose(u, fpm_u[case], atol=1e-6 * scale, rtol=0)


# ------------------------------------------------------------------ vtu


def test_vtu_export_reads_back_with_the_point_data(problem, tmp_path: Path):
    path = tmp_path / "lattice.vtu"
    path.write_bytes(export(problem, RECORD, "vtu"))
    mesh = meshio.read(path)
    np.testing.assert_allclose(mesh.points, problem.nodes)
    cells = {block.type: block.data for block in mesh.cells}
    np.testing.assert_array_equal(cells["hexahedron"], problem.solid.elements())
    np.testing.assert_array_equal(cells["line"], problem.solid.springs)
    fem_u = fpm.solve_fem(problem).displacements
    lattice = build_lattice(problem, Parameters.from_record(problem, RECORD))
    # the FPM's field is where its runs settle: the dynamic runs end within their settle
    # tolerance of it (the static equilibrium, solved to a tenth of that tolerance)
    fpm_u, _, settled = fpm_displacements(lattice)
    assert all(settled)
    for c in range(len(problem.load_cases)):
        exported = mesh.point_data[f"fpm_displacement_{c + 1}"]
        np.testing.assert_allclose(mesh.point_data[f"fem_displacement_{c + 1}"], fem_u[c])
        assert np.abs(exported - fpm_u[c]).max() <= 1e-3 * np.abs(fpm_u[c]).max()
        np.testing.assert_allclose(
            mesh.point_data[f"error_{c + 1}"], np.linalg.norm(exported - fem_u[c], axis=1)
        )
        layer = mesh.point_data[f"layer_{c + 1}"]
        assert layer.max() == len(lattice.layers[c]) - 1 and (layer[problem.fixed] == -1).all()
    np.testing.assert_allclose(mesh.point_data["mass"], problem.solid.masses)
    np.testing.assert_allclose(mesh.cell_data["stiffness"][1], lattice.stiffness)


def test_vtu_export_carries_the_validation_cases_and_parses_as_vtk_xml(tmp_path: Path):
    spec = copy.deepcopy(FAMILIES_SPEC)
    spec["validation_cases"] = [
        {"name": "side push", "forces": [{"at": [0.03, 0.01, 0.02], "vector": [-0.02, 0, 0]}]},
        {"name": "corner", "forces": [{"at": [0.0, 0.03, 0.03], "vector": [0, 0.01, -0.02]}]},
    ]
    checked = fpm.load_problem(spec)
    fem_u = fpm.solve_fem(checked).displacements  # the load cases', then the validation cases'
    body = export(checked, RECORD, "vtu", fem=fem_u)
    # the XML as VTK defines it: an UnstructuredGrid piece with a named array per field
    root = ET.fromstring(body)
    assert root.tag == "VTKFile" and root.get("type") == "UnstructuredGrid"
    (piece,) = root.iter("Piece")
    assert int(piece.get("NumberOfPoints")) == checked.n_nodes
    names = {a.get("Name") for a in piece.find("PointData").iter("DataArray")}
    n = len(checked.load_cases)
    for v in (1, 2):
        assert {f"validation_{f}_{v}" for f in ("fpm_displacement", "fem_displacement",
                                                "error", "layer")} <= names  # fmt: skip
    assert "validation_error_3" not in names
    path = tmp_path / "lattice.vtu"
    path.write_bytes(body)
    data = meshio.read(path).point_data
    alone = fpm.load_problem({**spec, "load_cases": spec["validation_cases"]})
    params = Parameters.from_record(checked, RECORD)
    for v in range(2):
        exported = data[f"validation_fpm_displacement_{v + 1}"]
        np.testing.assert_allclose(data[f"validation_fem_displacement_{v + 1}"], fem_u[n + v])
        # the validation case as a load case of its own solid: the same equilibrium
        own = static_equilibrium(alone, k=params.theta(alone), depth=params.depth, load_case=v)
        scale = np.abs(exported).max()
        assert scale > 0
        np.testing.assert_allclose(exported, own.displacements, atol=1e-6 * scale, rtol=0)
        layer = data[f"validation_layer_{v + 1}"]
        assert (layer[checked.validation_cases[v].nodes] == 0).all()
        assert (layer[checked.fixed] == -1).all()


# ------------------------------------------------------------------ sofa


def test_sofa_scene_parses_with_the_right_counts_and_numbers(problem):
    text = export(problem, RECORD, "sofa").decode()
    root = ET.fromstring(text)
    for element in root.iter():
        assert element.tag in SOFA_ATTRIBUTES, element.tag
        assert set(element.attrib) <= SOFA_ATTRIBUTES[element.tag], element.tag
    n, lattice = problem.n_nodes, build_lattice(problem, Parameters.from_record(problem, RECORD))
    engine = engine_parameters(lattice)  # the engine's d and dt, not the kernel's 0.15 and 1 ms
    assert engine is not None and engine["dt"] != 0.001 and engine["d"] != 0.15
    assert root.get("dt") == repr(engine["dt"]) and numbers(root.get("gravity")).tolist() == [0] * 3
    plugins = {e.get("name") for e in root.iter("RequiredPlugin")}
    assert {"Sofa.Component.SolidMechanics.Spring", "Sofa.Component.Mass"} <= plugins

    def one(tag: str) -> ET.Element:
        (element,) = root.iter(tag)
        return element

    np.testing.assert_array_equal(numbers(one("MechanicalObject").get("position")).reshape(n, 3),
                                  problem.nodes)  # fmt: skip
    masses = numbers(one("DiagonalMass").get("vertexMass"))
    np.testing.assert_array_equal(masses, problem.solid.masses)
    assert masses.sum() == pytest.approx(1040.0 * 0.03**3)
    springs = numbers(one("SpringForceField").get("spring")).reshape(-1, 5)
    assert len(springs) == 468
    np.testing.assert_array_equal(springs[:, :2], problem.solid.springs)
    np.testing.assert_array_equal(springs[:, 2], lattice.stiffness)  # ks, N/m
    assert (springs[:, 3] == 0).all()  # kd: the damping is nodal
    np.testing.assert_array_equal(springs[:, 4], problem.rest_lengths)
    damping = one("UniformVelocityDampingForceField")
    assert float(damping.get("dampingCoefficient")) == engine["d"]
    assert damping.get("implicit") == "true"
    (comment,) = [c for c in re.findall(r"<!-- (.*?) -->", text) if "FPM lattice" in c]
    assert "the calibration's d = 0.15 N s/m was fitted at dt = 0.001 s" in comment
    fixed = numbers(one("FixedProjectiveConstraint").get("indices")).astype(int)
    np.testing.assert_array_equal(fixed, np.flatnonzero(problem.fixed))
    topology = one("MeshTopology")
    assert numbers(topology.get("hexahedra")).size == 8 * 27
    assert topology.get("position") == "@dofs.position"
    load = one("ConstantForceField")  # load case 1 active, load case 2 in a comment
    assert load.get("indices") == str(problem.load_cases[0].nodes[0])
    np.testing.assert_array_equal(numbers(load.get("forces")), problem.load_cases[0].forces[0])


# ------------------------------------------------------------------ parameters and the command


def test_parameters_that_do_not_fit_the_spec_are_refused(problem):
    other_h = {**RECORD, "h": 0.02}
    with pytest.raises(ExportError, match="fitted on another lattice"):
        export(problem, other_h, "json")
    single = fpm.load_problem(SMALL)
    with pytest.raises(ExportError, match="one k per family but the spec fits one k"):
        export(single, RECORD, "json")
    with pytest.raises(ExportError, match="unknown format"):
        export(problem, RECORD, "obj")
    with pytest.raises(ExportError, match="need stiffness"):
        export(problem, {"d": 1.0}, "json")


def test_fpmcal_export_from_spec_and_result(tmp_path: Path, capsys):
    spec = tmp_path / "spec.json"
    spec.write_text(json.dumps(SMALL))
    result = tmp_path / "result.json"
    problem = fpm.load_problem(SMALL)
    result.write_text(json.dumps({**RECORD, "stiffness": {"axis": 30.0}, "h": problem.h}))
    out = tmp_path / "box.scn"
    assert main(["export", str(spec), str(result), "--format", "sofa", "-o", str(out)]) == 0
    assert ET.parse(out).getroot().tag == "Node"
    assert main(["export", str(spec), str(result)]) == 0
    assert json.loads(capsys.readouterr().out)["parameters"]["stiffness"] == {"axis": 30.0}
    assert main(["export", str(spec)]) == 2
    assert "give the spec and the parameters fitted on it" in capsys.readouterr().err


# ------------------------------------------------------------------ the service


def assert_problem(response: httpx.Response, status: int) -> dict[str, Any]:
    assert response.status_code == status, response.text
    assert response.headers["content-type"].startswith("application/problem+json")
    return response.json()


def calibrated(api, run_workers, spec: dict[str, Any]) -> dict[str, Any]:
    """A finished calibration of ``spec`` on the in-process app (its jobs run here)."""
    calibration = api.post("/v1/calibrations", json=spec).json()
    run_workers()
    done = api.get(f"/v1/calibrations/{calibration['id']}").json()
    assert done["status"] == "succeeded", done["error"]
    return done


def redis_url(redis: Redis) -> str:
    kwargs = redis.connection_pool.connection_kwargs
    return f"redis://{kwargs['host']}:{kwargs['port']}/{kwargs.get('db', 0)}"


def direct_export(redis, done: dict[str, Any], fmt: str) -> bytes:
    """The export computed here with fpm.io.export, from the same stored records."""
    ps = records.get_parameter_set(redis, done["parameter_set_id"])
    fem = None
    if fmt == "vtu":
        fem = records.get_fem_reference(redis, done["fem_reference_id"])["displacements"]
    spec = records.get_calibration(redis, done["id"]).spec
    return export(fpm.load_problem(spec), ps, fmt, fem=fem)


def test_export_endpoint_in_process(api, redis, run_workers, small_spec):
    done = calibrated(api, run_workers, small_spec)
    ps = done["parameter_set_id"]
    path = f"/v1/parameter-sets/{ps}/export"
    first = api.get(path)
    assert first.status_code == 202 and first.json() == {"status": "pending", "retry_after": 1}
    assert first.headers["retry-after"] == "1"
    assert first.headers["location"] == f"{path}?format=json"
    assert api.get(path).status_code == 202  # still pending: no second job
    assert graph.priority_queue(redis).count == 1 and graph.queue(redis).count == 0
    run_workers()
    answer = api.get(path)
    assert answer.status_code == 200 and answer.headers["content-type"] == "application/json"
    assert answer.headers["content-disposition"] == f'attachment; filename="{ps}.json"'
    assert answer.content == direct_export(redis, done, "json")
    assert answer.headers["content-encoding"] == "gzip"  # as cached; httpx unpacks it
    plain = api.get(path, headers={"Accept-Encoding": "identity"})
    assert "content-encoding" not in plain.headers
    assert plain.content == answer.content  # unpacked by the API for such a client
    digest = export_hash(ps, "json")
    cached = redis.get(keys.export(digest))
    assert gzip.decompress(cached) == answer.content and len(cached) < len(answer.content) / 3
    data = answer.json()
    assert data["parameters"]["d"] == done["result"]["d"]
    assert data["parameters"]["stiffness"] == done["result"]["stiffness"]
    assert data["fit"]["relative_discrepancy"] == done["result"]["relative_discrepancy"]
    assert data["fit"]["compliance_ratio"] == done["result"]["compliance_ratio"]
    assert len(data["fit"]["compliance_ratio"]) == len(small_spec["load_cases"])
    assert data["fit"]["verdict"] == done["result"]["verdict"]
    assert data["fit"]["verdict"]["grade"] in ("good", "fair", "poor")
    assert graph.queue(redis).count == graph.priority_queue(redis).count == 0
    digest = export_hash(ps, "json")
    assert 0 < redis.ttl(keys.export(digest)) <= scratch.EXPORT_TTL
    for fmt, media, suffix in (
        ("vtu", "application/xml", "vtu"),
        ("sofa", "application/xml", "scn"),
        ("sofa-python", "text/x-python; charset=utf-8", "py"),
    ):
        assert api.get(path, params={"format": fmt}).status_code == 202
        run_workers()
        answer = api.get(path, params={"format": fmt})
        assert answer.status_code == 200 and answer.headers["content-type"] == media
        assert answer.headers["content-disposition"] == f'attachment; filename="{ps}.{suffix}"'
        assert answer.content == direct_export(redis, done, fmt), fmt
    bad = assert_problem(api.get(f"{path}?format=obj"), 422)
    assert bad["errors"][0]["field"].endswith("format")
    assert_problem(api.get("/v1/parameter-sets/ps-0123456789abcdef/export"), 404)
    redis.delete(keys.calibration(done["id"]))  # the record that holds the spec
    assert api.get(f"{path}?format=sofa").status_code == 200  # made: served from the cache
    redis.delete(keys.export(export_hash(ps, "sofa")))
    gone = assert_problem(api.get(f"{path}?format=sofa"), 410)
    assert "calibrate its spec again" in gone["detail"]


def test_the_service_keeps_the_exporters_media_types():
    from fpm.io.export import MEDIA_TYPES, SUFFIXES
    from service.routers import exports

    assert exports.MEDIA_TYPES == MEDIA_TYPES and exports.SUFFIXES == SUFFIXES


def test_concurrent_first_requests_enqueue_one_job(api, redis, run_workers, small_spec):
    done = calibrated(api, run_workers, small_spec)
    path = f"/v1/parameter-sets/{done['parameter_set_id']}/export"
    with ThreadPoolExecutor(8) as pool:
        answers = list(pool.map(lambda _: api.get(path, params={"format": "sofa"}), range(16)))
    assert [a.status_code for a in answers] == [202] * 16
    queued = graph.priority_queue(redis).get_job_ids() + graph.queue(redis).get_job_ids()
    assert queued == [keys.export_job_id(export_hash(done["parameter_set_id"], "sofa"))]
    run_workers()
    assert api.get(path, params={"format": "sofa"}).status_code == 200
    # The store's own race: 8 threads, each with its own connection, ask at the same instant.
    spec = records.get_calibration(redis, done["id"]).spec
    start = threading.Barrier(8)

    def ask(_: int) -> graph.ExportState:
        own = Redis(connection_pool=ConnectionPool.from_url(redis_url(redis)))
        start.wait()
        return graph.request_export(own, done["parameter_set_id"], "vtu", spec, 60)

    with ThreadPoolExecutor(8) as pool:
        states = list(pool.map(ask, range(8)))
    assert all(s.pending for s in states)
    assert graph.priority_queue(redis).count == 1


def test_each_parameter_set_and_format_has_its_own_export(api, redis, run_workers, small_spec):
    first = calibrated(api, run_workers, small_spec)
    other_spec = copy.deepcopy(small_spec)
    other_spec["load_cases"] = other_spec["load_cases"][:1]
    second = calibrated(api, run_workers, other_spec)
    assert first["parameter_set_id"] != second["parameter_set_id"]
    paths = [f"/v1/parameter-sets/{d['parameter_set_id']}/export" for d in (first, second)]
    assert api.get(paths[0]).status_code == 202
    run_workers()
    assert api.get(paths[0]).status_code == 200
    assert api.get(paths[1]).status_code == 202  # not answered from the first set's cache
    run_workers()
    answers = [api.get(p).content for p in paths]
    assert answers[0] == direct_export(redis, first, "json")
    assert answers[1] == direct_export(redis, second, "json")
    assert (
        len(json.loads(answers[1])["load_cases"]) == 1 != len(json.loads(answers[0])["load_cases"])
    )
    assert api.get(paths[0], params={"format": "sofa"}).status_code == 202  # nor another format's


def test_a_failed_export_job_is_a_problem_not_a_500(api, redis, run_workers, small_spec):
    done = calibrated(api, run_workers, small_spec)
    ps_id = done["parameter_set_id"]
    path = f"/v1/parameter-sets/{ps_id}/export"
    # The parameters stop fitting the lattice (a set written by a buggy finalize, say): 422.
    ps = records.get_parameter_set(redis, ps_id)
    wrong = {**ps, "geometry": {**ps["geometry"], "h": 2 * ps["geometry"]["h"]}}
    redis.set(keys.parameter_set(ps_id), json.dumps(wrong))
    assert api.get(path).status_code == 202
    run_workers()
    invalid = assert_problem(api.get(path), 422)
    assert "fitted on another lattice" in invalid["detail"]
    assert invalid["errors"][0]["field"] == "parameter_set_id"
    assert graph.priority_queue(redis).count == 0  # remembered: not re-run at every poll
    # Any other failure of the job: 503 with Retry-After (the cool-down), then a retry.
    redis.set(keys.parameter_set(ps_id), json.dumps(ps))
    redis.delete(keys.export_failure(export_hash(ps_id, "json")))
    assert api.get(path).status_code == 202
    key = keys.calibration(done["id"])
    spec = redis.hget(key, "spec")
    redis.hset(key, "spec", json.dumps({"broken": True}))  # the job finds a spec it cannot load
    run_workers()
    redis.hset(key, "spec", spec)
    failed = assert_problem(api.get(path), 503)
    retry = int(api.get(path).headers["retry-after"])
    assert 0 < retry <= scratch.EXPORT_FAILED_TTL
    assert re.search(r"it is tried again in \d+ s$", failed["detail"])
    assert "export job" in failed["detail"] and "ValidationError" in failed["detail"]
    redis.delete(keys.export_failure(export_hash(ps_id, "json")))  # the cool-down is over
    assert api.get(path).status_code == 202
    run_workers()
    assert api.get(path).content == direct_export(redis, done, "json")


def test_an_export_job_that_died_is_a_503_until_its_cool_down_ends(
    api, redis, run_workers, small_spec
):
    done = calibrated(api, run_workers, small_spec)
    path = f"/v1/parameter-sets/{done['parameter_set_id']}/export"
    assert api.get(path).status_code == 202
    job_id = keys.export_job_id(export_hash(done["parameter_set_id"], "json"))
    job = Job.fetch(job_id, connection=redis, serializer=JSONSerializer)
    job.set_status(JobStatus.FAILED)  # as RQ leaves the job of a worker killed mid-export
    redis.expire(job.key, 120)
    graph.priority_queue(redis).remove(job_id)
    died = assert_problem(api.get(path), 503)
    assert "stopped before it finished" in died["detail"]
    assert 100 < int(api.get(path).headers["retry-after"]) <= 120
    claim = keys.export_claim(export_hash(done["parameter_set_id"], "json"))
    redis.delete(job.key, claim)  # the cool-down over, RQ forgets the job; the claim expired
    assert api.get(path).status_code == 202
    run_workers()
    assert api.get(path).status_code == 200


def test_the_sdk_waits_for_the_export(api, sdk, run_workers, redis, small_spec, monkeypatch):
    done = calibrated(api, run_workers, small_spec)
    ps = done["parameter_set_id"]
    polls: list[str] = []

    def worker_between_polls(seconds: float) -> None:  # instead of sleeping: a worker runs
        polls.append(f"slept {seconds}")
        run_workers()

    monkeypatch.setattr(sdk_module.time, "sleep", worker_between_polls)
    body = sdk.export_bytes(ps, "sofa", progress=False)
    assert body == direct_export(redis, done, "sofa")
    assert polls == ["slept 1.0"]  # one 202, the Retry-After honoured, then 200
    assert sdk.export(ps, "json", progress=False) == json.loads(direct_export(redis, done, "json"))
    monkeypatch.setattr(sdk_module.time, "sleep", lambda s: None)  # no worker: it never ends
    with pytest.raises(TimeoutError, match="still being made"):
        sdk.export_bytes(ps, "vtu", timeout=0, progress=False)


def test_export_endpoint_on_the_live_stack(live_api, small_spec, tmp_path: Path, capsys):
    small_spec["name"] = "export over http"
    with Client(live_api) as client:
        done = client.calibrate(small_spec, wait=True, progress=False)
        assert done["status"] == "succeeded", done["error"]
        ps = done["parameter_set_id"]
        out = tmp_path / "from-service.json"
        argv = ["export", "--parameter-set", ps, "--url", live_api, "-o", str(out)]
        capsys.readouterr()
        assert main(argv) == 0  # the first request: waits for the worker, says so on stderr
        waited = capsys.readouterr().err
        assert f"{ps} json: the service makes the export ..." in waited
        assert "ready after" in waited and f"wrote {out}" in waited
        data = client.export(ps, "json")
        assert data["format"] == "fpm-lattice" and len(data["nodes"]) == 64
        assert data["parameters"]["d"] == done["result"]["d"]
        scene = client.export(ps, "sofa")
        assert len(list(ET.fromstring(scene).iter("SpringForceField"))) == 1
        vtu = client.export(ps, "vtu", path=tmp_path / "lattice.vtu")
    mesh = meshio.read(vtu)
    assert mesh.points.shape == (64, 3)
    for c in (1, 2):
        assert {f"fpm_displacement_{c}", f"fem_displacement_{c}", f"error_{c}"} <= set(
            mesh.point_data
        )
    fem = httpx.get(f"{live_api}/v1/fem-references/{done['fem_reference_id']}").json()
    np.testing.assert_allclose(mesh.point_data["fem_displacement_2"], fem["displacements"][1])
    answer = httpx.get(f"{live_api}/v1/parameter-sets/{ps}/export", params={"format": "sofa"})
    assert answer.headers["content-type"].startswith("application/xml")
    assert f'filename="{ps}.scn"' in answer.headers["content-disposition"]
    assert json.loads(out.read_text()) == data
    assert main(["export", "--parameter-set", "ps-0123456789abcdef", "--url", live_api]) == 1
    assert "404 Not found" in capsys.readouterr().err


# --- the volume term: the JSON alone rebuilds the model ----------------------------------------

CORNERS = np.array(
    [[-1, -1, -1], [1, -1, -1], [1, 1, -1], [-1, 1, -1],
     [-1, -1, 1], [1, -1, 1], [1, 1, 1], [-1, 1, 1]], dtype=float,
)  # fmt: skip


def quadrature_volume(x: np.ndarray) -> float:
    """Volume of the trilinear hexahedron with corners x (8, 3), by 2x2x2 Gauss quadrature of
    det J, written here from scratch (not fpm's)."""
    total = 0.0
    g = 1 / np.sqrt(3)
    for r in (-g, g):
        for s in (-g, g):
            for t in (-g, g):
                dn = np.empty((8, 3))
                for n, (a, b, c) in enumerate(CORNERS):
                    dn[n] = [a * (1 + s * b) * (1 + t * c), (1 + r * a) * b * (1 + t * c),
                             (1 + r * a) * (1 + s * b) * c]  # fmt: skip
                total += np.linalg.det(dn.T @ x / 8)
    return total


def independent_linear_solve(model: dict[str, Any], load_case: int) -> np.ndarray:
    """(N, 3) displacements of the exported model linearised at rest under a load case's forces,
    from the JSON alone: springs k e e^T, cells (kappa / V0) g g^T with g = dV/dx by central
    differences of :func:`quadrature_volume`, fixed nodes held."""
    x = np.asarray(model["nodes"])
    n = len(x)
    k = np.zeros((3 * n, 3 * n))
    for i, j, _, ks in model["springs"]:
        e = x[int(j)] - x[int(i)]
        e /= np.linalg.norm(e)
        block = ks * np.outer(e, e)
        for a, b, sign in ((i, i, 1), (j, j, 1), (i, j, -1), (j, i, -1)):
            k[3 * int(a) : 3 * int(a) + 3, 3 * int(b) : 3 * int(b) + 3] += sign * block
    if model["volume_stiffness"] is not None:
        for hexa, kappa, v0 in zip(
            model["hexahedra"], model["volume_stiffness"], model["rest_volumes"], strict=True
        ):
            corners = x[hexa]
            step = 1e-6 * np.ptp(corners, axis=0).max()
            grad = np.zeros(24)
            for q in range(24):
                up, down = corners.copy(), corners.copy()
                up.flat[q] += step
                down.flat[q] -= step
                grad[q] = (quadrature_volume(up) - quadrature_volume(down)) / (2 * step)
            dofs = np.ravel([[3 * c, 3 * c + 1, 3 * c + 2] for c in hexa])
            k[np.ix_(dofs, dofs)] += kappa / v0 * np.outer(grad, grad)
    forces = np.zeros((n, 3))
    case = model["load_cases"][load_case]
    forces[case["nodes"]] = case["forces"]
    free = np.ones(n, dtype=bool)
    free[model["fixed"]] = False
    dofs = np.repeat(free, 3)
    u = np.zeros(3 * n)
    u[dofs] = np.linalg.solve(k[np.ix_(dofs, dofs)], forces.ravel()[dofs])
    return u.reshape(-1, 3)


def soft_block_spec() -> dict[str, Any]:
    return {
        "name": "soft block",
        "material": {"youngs_modulus": 5000.0, "poisson_ratio": 0.45, "density": 1040.0},
        "geometry": {"type": "box", "size": [0.03, 0.03, 0.04], "nodes": [4, 4, 5]},
        "fixed": [{"face": "z-"}],
        "load_cases": [
            {"name": "press", "forces": [{"at": [0.01, 0.01, 0.04], "vector": [0, 0, -0.002]}]},
            {"name": "shear", "forces": [{"at": [0.02, 0.01, 0.04], "vector": [0.002, 0, 0]}]},
        ],
        "annealing": {"chains": 1},
    }


def test_the_json_export_alone_rebuilds_the_volume_model():
    """An independent linear solve of the exported families+volume model (its own volume and
    gradient, its own assembly) equals the project's static equilibrium at a small load."""
    spec = soft_block_spec()
    for case in spec["load_cases"]:  # 1e-5 of the forces: the linear limit
        case["forces"][0]["vector"] = [1e-5 * v for v in case["forces"][0]["vector"]]
    problem = fpm.load_problem(spec)
    assert problem.spec.fpm.stiffness == "families+volume"
    record = {"stiffness": {"axis": 30.0, "face": 20.0, "body": 4.0}, "volume_stiffness": 2e4,
              "d": 0.05, "depth": 10, "dt": 1e-4}  # fmt: skip
    model = json.loads(export(problem, record, "json"))
    assert len(model["volume_stiffness"]) == len(model["hexahedra"]) == len(model["rest_volumes"])
    assert "kappa" in model["energy"] and model["parameters"]["volume_stiffness"] == 2e4
    interior = [ks for _, _, length, ks in model["springs"] if length < 0.0101]
    assert max(interior) == pytest.approx(30.0) and min(interior) == pytest.approx(7.5)
    theta = [30.0, 20.0, 4.0, 2e4]
    for j in range(2):
        ours = static_equilibrium(problem, k=theta, load_case=j, tolerance=1e-10).displacements
        theirs = independent_linear_solve(model, j)
        assert np.abs(ours - theirs).max() < 1e-5 * np.abs(ours).max()


def test_the_fit_figures_agree_with_an_independent_solve_of_the_export():
    """The export's check: the relative discrepancy the calibration reports agrees within 2
    points with one computed from the exported JSON alone (independent solve) against the FEM."""
    problem = fpm.load_problem(soft_block_spec())
    reference = fpm.solve_fem(problem)
    result = fpm.calibrate(problem, reference=reference)
    model = json.loads(export(problem, result.to_dict(), "json"))
    for j in range(2):
        theirs = independent_linear_solve(model, j)
        fem = reference.displacements[j]
        relative = 100 * np.linalg.norm(theirs - fem, axis=1).sum()
        relative /= np.linalg.norm(fem, axis=1).sum()
        assert relative == pytest.approx(result.fit.relative_discrepancy[j], abs=2.0)


def test_the_validation_figures_agree_with_an_independent_solve_of_the_export():
    """The export's check on loads the fit never saw: the relative discrepancy the calibration
    reports for each load case and each validation case agrees within 1.5 points with one
    computed from the exported JSON alone (the model; the validation forces from the spec, as a
    user applies them) against the FEM."""
    spec = soft_block_spec()
    off_centre = {"at": [0.02, 0.02, 0.04], "vector": [0, 0, -0.002]}
    sideways = {"at": [0.01, 0.02, 0.04], "vector": [0, 0.002, 0]}
    spec["validation_cases"] = [
        {"name": "press off centre", "forces": [off_centre]},
        {"name": "sideways", "forces": [sideways]},
    ]
    problem = fpm.load_problem(spec)
    reference = fpm.solve_fem(problem)
    result = fpm.calibrate(problem, reference=reference)
    model = json.loads(export(problem, result.to_dict(), "json"))
    assert (
        result.parameters.depth == result.parameters.full_depth
        and model["parameters"]["depth"] is None
    )
    fitted = len(problem.load_cases)
    for case in problem.validation_cases:
        model["load_cases"].append(
            {"nodes": case.nodes.tolist(), "forces": case.forces.tolist()}
        )  # the user's own load, applied to the exported lattice
    reported = result.fit.relative_discrepancy + result.fit.validation_relative_discrepancy
    ratios = model["fit"]["compliance_ratio"] + model["fit"]["validation_compliance_ratio"]
    assert ratios == result.fit.compliance_ratio + result.fit.validation_compliance_ratio
    assert model["fit"]["verdict"] == result.fit.verdict.model_dump()
    for j, (expected, ratio) in enumerate(zip(reported, ratios, strict=True)):
        theirs = independent_linear_solve(model, j)
        fem = np.asarray(reference.displacements[j])
        relative = 100 * np.linalg.norm(theirs - fem, axis=1).sum()
        relative /= np.linalg.norm(fem, axis=1).sum()
        assert relative == pytest.approx(expected, abs=1.5), (j, j >= fitted)
        # the load compliance ratio from the export alone: the work of its forces
        nodes, forces = (np.asarray(model["load_cases"][j][k]) for k in ("nodes", "forces"))
        work = np.einsum("ij,ij->", forces, theirs[nodes])
        assert work / np.einsum("ij,ij->", forces, fem[nodes]) == pytest.approx(ratio, abs=0.015), j


def test_a_sofa_scene_of_the_volume_model_says_it_lacks_the_volume_term(capsys):
    from fpm.io.export import export_warnings

    problem = fpm.load_problem(soft_block_spec())
    record = {"stiffness": {"axis": 30.0, "face": 20.0, "body": 4.0}, "volume_stiffness": 2e4,
              "d": 0.05, "depth": 10, "dt": 1e-4}  # fmt: skip
    scene = export(problem, record, "sofa").decode()
    assert "no XML component for this model's volume term" in scene and "sofa-python" in scene
    assert export_warnings(problem, "sofa") and not export_warnings(problem, "json")
    vtu = meshio.read(_write(export(problem, record, "vtu"), ".vtu"))
    kappa = vtu.cell_data["volume_stiffness"]
    assert np.all(kappa[0] == 2e4) and np.all(kappa[1] == 0)


def _write(body: bytes, suffix: str) -> Path:
    import tempfile

    path = Path(tempfile.mkdtemp()) / f"export{suffix}"
    path.write_bytes(body)
    return path


def test_a_fit_at_its_full_depth_exports_every_layer(problem):
    """A depth at the fit's full depth means every layer (the validation cases were judged so:
    a load elsewhere needs more layers than the fitted ones' lists): the export says null, and
    its perturbed lists reach every free node; a shorter depth stays as it is."""
    model = fpm_model(problem)
    deepest = perturbed_list(model.adjacency, problem.load_cases[0].nodes, problem.fixed, None)
    full = {**RECORD, "depth": deepest.layers, "full_depth": deepest.layers}
    data = json.loads(export(problem, full, "json"))
    assert data["parameters"]["depth"] is None
    reached = np.concatenate(
        [np.asarray(layer) for layer in data["load_cases"][0]["perturbed_layers"]]
    )
    assert len(reached) == problem.n_nodes - problem.fixed.sum()
    short = json.loads(export(problem, {**full, "depth": deepest.layers - 1}, "json"))
    assert short["parameters"]["depth"] == deepest.layers - 1
