"""fpm.runtime: the JSON export stepped as an engine steps it (every node at once, springs,
volume term, nodal damping at the exported dt), against the project's own kernels."""

import ast
import json
import sys
from pathlib import Path

import numpy as np
import pytest

from fpm import load_problem, simulate
from fpm.dynamics.equilibrium import static_equilibrium
from fpm.io.export import export
from fpm.model.forces import cells
from fpm.model.hexahedron import NATURAL
from fpm.model.stiffness import continuum_start, stiffness_dict, volume_stiffness
from fpm.model.volume import volume_forces
from fpm.runtime import ExportFormatError, Runtime, hexahedron_volumes

ROOT = Path(__file__).resolve().parents[2]


def exported(spec: dict, theta=None, d_factor: float = 0.5):
    """(problem, theta, d, the parsed JSON export) at the continuum start (or ``theta``)."""
    problem = load_problem(spec)
    theta = continuum_start(problem) if theta is None else theta
    e, h = problem.spec.material.youngs_modulus, problem.h
    d = d_factor * float(np.sqrt(e * h * problem.solid.masses.mean()))
    record = {
        "stiffness": stiffness_dict(problem, theta),
        "volume_stiffness": volume_stiffness(problem, theta),
        "d": d,
        "depth": 30,
    }
    return problem, theta, d, json.loads(export(problem, record, "json"))


@pytest.fixture(scope="module")
def cube():
    """The paper's cube (10^3 nodes, full connectivity) with the default model, settling tight."""
    spec = json.loads((ROOT / "examples/paper-material-a.json").read_text())
    spec["fpm"] = {"stiffness": "families+volume", "dt": "auto", "settle_tolerance": 1e-12}
    return exported(spec)


@pytest.fixture(scope="module")
def conforming():
    """The 480-tetrahedron organ on its conforming lattice (``spec_from_mesh``'s default:
    439 nodes, hexahedra of every shape), families+volume, settling tight."""
    from live_page import conforming_spec

    spec = conforming_spec(0.012)
    spec["fpm"].update(stiffness="families+volume", settle_tolerance=1e-12)
    return exported(spec)


def test_the_runtime_is_standalone(cube, monkeypatch):
    """The recipe an engine ports: NumPy and SciPy only; the one module of ours it names is the
    compiled step, imported only for a backend other than NumPy's, without which it runs."""
    tree = ast.parse((ROOT / "fpm/runtime.py").read_text())
    names = {a.name for n in ast.walk(tree) if isinstance(n, ast.Import) for a in n.names}
    names |= {n.module or "." for n in ast.walk(tree) if isinstance(n, ast.ImportFrom)}
    assert {n.split(".")[0] for n in names} <= {"__future__", "json", "os", "dataclasses",
                                                 "pathlib", "typing", "numpy", "scipy",
                                                 "native"}  # fmt: skip
    monkeypatch.setitem(sys.modules, "fpm.native", None)  # not importable
    rt = Runtime.from_export(cube[3], backend="numpy")
    rt.step(rt.load_case_forces(cube[3], 0))
    with pytest.raises(ImportError):
        Runtime.from_export(cube[3], backend="native")


def test_the_export_order_of_corners_is_the_model_s():
    from fpm.runtime import NATURAL as RUNTIME_NATURAL

    assert np.array_equal(RUNTIME_NATURAL, NATURAL)


def test_forces_are_minus_the_energy_gradient(cube):
    """Central differences of the export's energy (springs, volume term, work of the loads)."""
    _, _, _, doc = cube
    rt = Runtime.from_export(doc)
    rng = np.random.default_rng(3)
    x = rt.rest + 0.05 * doc["h"] * rng.standard_normal(rt.rest.shape)
    forces = rt.load_case_forces(doc, 0)
    total = rt.internal_forces(x) + forces
    eps = 1e-7 * doc["h"]
    for node, axis in [(0, 0), (555, 1), (999, 2), (444, 2)]:
        plus, minus = x.copy(), x.copy()
        plus[node, axis] += eps
        minus[node, axis] -= eps
        numeric = -(rt.energy(plus, forces) - rt.energy(minus, forces)) / (2 * eps)
        assert numeric == pytest.approx(total[node, axis], rel=1e-5, abs=1e-9)


def test_volume_forces_equal_the_model_s(cube):
    problem, theta, _, doc = cube
    rt = Runtime.from_export(doc)
    rng = np.random.default_rng(4)
    u = 0.03 * problem.h * rng.standard_normal(problem.nodes.shape)
    rt.stiffness[:] = 0.0  # springs off: what is left is the volume term
    only_volume = rt.internal_forces(problem.nodes + u)
    kappa = np.asarray(doc["volume_stiffness"])
    expected = volume_forces(cells(problem), kappa, u)
    assert np.abs(only_volume - expected).max() <= 1e-12 * np.abs(expected).max()
    volume, _ = hexahedron_volumes(problem.nodes, rt.hexahedra)
    assert volume == pytest.approx(np.asarray(doc["rest_volumes"]), rel=1e-13)


def test_the_static_equilibrium_is_at_rest_in_the_runtime(cube):
    """The static solver's answer leaves no unbalanced force in the runtime's model."""
    problem, theta, _, doc = cube
    rt = Runtime.from_export(doc)
    eq = static_equilibrium(problem, k=theta, depth=None, load_case=1, tolerance=1e-12)
    forces = rt.load_case_forces(doc, 1)
    residual = rt.internal_forces(problem.nodes + eq.displacements) + forces
    residual[rt.fixed] = 0.0
    assert np.abs(residual).max() <= 1e-9 * np.abs(forces).max()


def test_a_conforming_lattice_is_at_rest_at_its_static_equilibrium_in_the_runtime(conforming):
    """The lattice a tetrahedral organ gets by default: the export's volume term is the
    model's on its irregular hexahedra, and the static solver's answer leaves no unbalanced
    force in the runtime."""
    problem, theta, _, doc = conforming
    rt = Runtime.from_export(doc)
    volume, _ = hexahedron_volumes(problem.nodes, rt.hexahedra)
    assert volume == pytest.approx(np.asarray(doc["rest_volumes"]), rel=1e-13)
    assert np.ptp(volume) > 0.5 * volume.mean()  # not a regular lattice
    eq = static_equilibrium(problem, k=theta, depth=None, load_case=0, tolerance=1e-12)
    forces = rt.load_case_forces(doc, 0)
    residual = rt.internal_forces(problem.nodes + eq.displacements) + forces
    residual[rt.fixed] = 0.0
    assert np.abs(residual).max() <= 1e-9 * np.abs(forces).max()


def test_the_runtime_settles_where_simulate_settles(cube):
    """Every node at once vs the kernel's list order: the same settled state to 1e-9."""
    problem, theta, d, doc = cube
    rt = Runtime.from_export(doc)
    forces = rt.load_case_forces(doc, 0)
    steps = rt.run(forces, max_steps=20_000)
    assert rt.settled and steps < 20_000
    run = simulate(problem, k=theta, d=d, depth=None, load_case=0, dt=rt.dt, max_steps=40_000)
    assert run.settled
    u = run.displacements
    assert np.abs((rt.x - rt.rest) - u).max() <= 1e-9 * np.abs(u).max()


def test_forces_may_change_every_step(cube):
    """A push that comes and goes: the model returns to rest; fixed nodes never move."""
    _, _, _, doc = cube
    rt = Runtime.from_export(doc)
    push = rt.load_case_forces(doc, 2)
    for n in range(400):
        x = rt.step(push * np.sin(np.pi * n / 400))
        assert np.array_equal(x[rt.fixed], rt.rest[rt.fixed])
    moved = np.abs(rt.x - rt.rest).max()
    assert moved > 0
    rt.run(None, max_steps=20_000)
    assert np.abs(rt.x - rt.rest).max() < 1e-6 * moved


def test_a_spring_only_export_and_a_file(tmp_path):
    spec = json.loads((ROOT / "examples/small-box.json").read_text())
    spec["fpm"] = {"stiffness": "single", "settle_tolerance": 1e-12}
    problem = load_problem(spec)
    k = problem.spec.material.youngs_modulus * problem.h / 3
    problem, theta, d, doc = exported(spec, theta=[k])
    assert doc["volume_stiffness"] is None
    path = tmp_path / "lattice.json"
    path.write_text(json.dumps(doc))
    rt = Runtime.from_export(path)
    assert len(rt.hexahedra) == 0
    rt.run(rt.load_case_forces(doc, 0), max_steps=50_000)
    eq = static_equilibrium(problem, k=theta, depth=None, load_case=0, tolerance=1e-12)
    assert np.abs(rt.x - rt.rest - eq.displacements).max() <= 1e-8 * np.abs(eq.displacements).max()


def test_not_an_export():
    with pytest.raises(ExportFormatError, match="fpm-lattice"):
        Runtime.from_export({"format": "something else"})


def readme_step() -> str:
    """The manual's "The step in NumPy" code block (docs/howto/export.md)."""
    page = (ROOT / "docs" / "howto" / "export.md").read_text()
    section = page.split("\n## The step in NumPy\n", 1)[1]
    return section.split("```python\n", 1)[1].split("```", 1)[0]


@pytest.mark.parametrize("mode", ["families+volume", "single"])
def test_the_readme_numpy_step_is_the_runtime(tmp_path, monkeypatch, mode):
    """The recipe in the manual, run as printed on an export of the small box, settles where
    the runtime does (the same arithmetic) and at the static solver's equilibrium."""
    spec = json.loads((ROOT / "examples/small-box.json").read_text())
    spec["fpm"] = {"stiffness": mode, "settle_tolerance": 1e-10}
    problem = load_problem(spec)
    theta = continuum_start(problem) if mode != "single" else [problem.h * 3000.0]
    problem, theta, _, doc = exported(spec, theta=theta)
    (tmp_path / "box-lattice.json").write_text(json.dumps(doc))
    monkeypatch.chdir(tmp_path)
    scope: dict = {}
    exec(compile(readme_step(), "docs/howto/export.md", "exec"), scope)
    displacement = scope["displacement"]
    rt = Runtime.from_export(doc)
    steps = rt.run(rt.load_case_forces(doc, 0), max_steps=doc["parameters"]["max_steps"])
    assert scope["step"] == steps < doc["parameters"]["max_steps"]
    scale = np.abs(displacement).max()
    assert np.abs(rt.x - rt.rest - displacement).max() <= 1e-10 * scale
    eq = static_equilibrium(problem, k=theta, depth=None, load_case=0, tolerance=1e-12)
    assert np.abs(eq.displacements - displacement).max() <= 1e-6 * scale


def test_an_engine_applies_a_force_as_the_hat_fit_did():
    """With ``fpm.loads: "hat"`` the export carries the shares of every surface node: a force
    at a node passed through :meth:`Runtime.applied` is the export's load case (its spread
    forces), so an engine loading a node gets the model the fit judged."""
    from live_page import conforming_spec

    spec = conforming_spec(0.012)
    spec["fpm"].update(stiffness="families+volume", loads="hat")
    problem, _, _, doc = exported(spec)
    assert doc["parameters"]["loads"] == "hat" and "4/9" in doc["loads"]
    rt = Runtime.from_export(doc)
    for j, case in enumerate(problem.load_cases):
        given = case.as_given().dense(problem.n_nodes)
        assert len(case.nodes) > len(case.as_given().nodes)
        spread = rt.applied(given)
        spread[rt.fixed] = 0.0
        np.testing.assert_allclose(spread, rt.load_case_forces(doc, j), rtol=0, atol=1e-15)
    node = exported({**spec, "fpm": {"stiffness": "families+volume"}})[3]
    assert "load_shares" not in node
    np.testing.assert_array_equal(Runtime.from_export(node).applied(given), given)


@pytest.mark.parametrize("depth", [2, 5])
def test_a_region_rests_where_the_kernel_rests_at_its_depth(cube, depth):
    """The paper's tunable speed: the runtime of one load's perturbed list up to ``depth``
    layers holds only the list and the ring beyond it, and the kernel's static equilibrium at
    that depth leaves no unbalanced force on the list's nodes (the nodes beyond it at rest in
    both); stepped from rest, the region settles there."""
    problem, theta, _, doc = cube
    rt = Runtime.from_export(doc, backend="numpy")
    forces = rt.load_case_forces(doc, 1)
    loaded = np.flatnonzero(np.abs(forces).sum(axis=1))
    region = rt.region(loaded, depth)
    sub = region.runtime
    assert region.layers == depth
    assert len(region.nodes) < rt.n_nodes and len(sub.springs) < len(rt.springs)
    eq = static_equilibrium(problem, k=theta, depth=depth, load_case=1, tolerance=1e-12)
    moved = np.flatnonzero(np.abs(eq.displacements).sum(axis=1))
    assert set(moved) <= set(region.nodes[~sub.fixed])
    x = problem.nodes[region.nodes] + eq.displacements[region.nodes]
    residual = sub.internal_forces(x) + region.forces(forces)
    residual[sub.fixed] = 0.0
    assert np.abs(residual).max() <= 1e-9 * np.abs(forces).max()
    sub.settle_tolerance = 1e-10
    sub.run(region.forces(forces), max_steps=20_000)
    assert sub.settled
    settled = region.positions(problem.nodes) - problem.nodes
    scale = np.abs(eq.displacements).max()
    assert np.abs(settled - eq.displacements).max() <= 1e-6 * scale


def test_a_region_defaults_to_the_export_s_depth(cube):
    """``parameters.depth`` of the export (here 30 layers, beyond the cube's 9: every layer) is
    the region's unless told; a depth that is no number is refused."""
    _, _, _, doc = cube
    rt = Runtime.from_export(doc, backend="numpy")
    assert rt.depth == 30
    forces = rt.load_case_forces(doc, 0)
    loaded = np.flatnonzero(np.abs(forces).sum(axis=1))
    every = rt.region(loaded, None)
    assert rt.region(loaded).layers == every.layers
    assert len(every.nodes) == rt.n_nodes
    assert len(rt.region(loaded, 1).nodes) < len(every.nodes)
    with pytest.raises(ValueError, match="depth"):
        rt.region(loaded, "auto")
