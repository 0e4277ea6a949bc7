"""The ``sofa-python`` export: a SofaPython3 scene whose volume term is a Python ForceField.

SOFA is not installable here, so the scene runs against a stand-in ``Sofa.Core`` (a ForceField
base class and a scene node that records what is added): its forces equal the project's kernel
to 1e-12, its addDForce and addKToMatrix equal central differences of its forces, and the scene
carries every spring, mass, fixed node and the load."""

import contextlib
import json
import sys
import types
from pathlib import Path

import numpy as np
import pytest

from fpm import load_problem
from fpm.io.export import export, export_warnings
from fpm.model.forces import cells
from fpm.model.stiffness import continuum_start, stiffness_dict, volume_stiffness
from fpm.model.volume import volume_forces
from fpm.runtime import Runtime

ROOT = Path(__file__).resolve().parents[2]


class Data:
    """A SOFA Data: ``.value`` and ``writeableArray()``."""

    def __init__(self, value):
        self.value = np.array(value, dtype=float)

    @contextlib.contextmanager
    def writeableArray(self):  # noqa: N802 (SofaPython3's name)
        yield self.value


class Node:
    """A scene node that records its objects and children."""

    def __init__(self, name="root"):
        self.name, self.objects, self.children = name, [], []

    def addObject(self, kind, **data):  # noqa: N802
        self.objects.append((kind, data))
        return kind

    def addChild(self, name):  # noqa: N802
        child = Node(name)
        self.children.append(child)
        return child


@pytest.fixture(scope="module", params=["small box", "conforming organ"])
def scene(request):
    """(problem, the parsed JSON export, the scene module run against the stand-in Sofa): the
    small box, and the 480-tetrahedron organ on the conforming lattice a tetrahedral mesh
    gets by default (hexahedra of every shape)."""
    if request.param == "small box":
        spec = json.loads((ROOT / "examples/small-box.json").read_text())
    else:
        from live_page import conforming_spec

        spec = conforming_spec(0.012)
    spec["fpm"] = {"stiffness": "families+volume"}
    return scene_of(spec)


def scene_of(spec):
    """(problem, the parsed JSON export, the scene module) of ``spec`` at the continuum start."""
    problem = load_problem(spec)
    theta = continuum_start(problem)
    record = {
        "stiffness": stiffness_dict(problem, theta),
        "volume_stiffness": volume_stiffness(problem, theta),
        "d": 0.05,
        "depth": 3,
    }
    source = export(problem, record, "sofa-python").decode()
    doc = json.loads(export(problem, record, "json"))

    class ForceField:
        def __init__(self, *args, **kwargs):
            self.name = kwargs.get("name")

    core = types.ModuleType("Sofa.Core")
    core.ForceField = ForceField
    sofa = types.ModuleType("Sofa")
    sofa.Core = core
    saved = {k: sys.modules.get(k) for k in ("Sofa", "Sofa.Core")}
    sys.modules.update({"Sofa": sofa, "Sofa.Core": core})
    try:
        module = types.ModuleType("fpm_scene")
        exec(compile(source, "scene.py", "exec"), module.__dict__)
    finally:
        for k, v in saved.items():
            if v is None:
                sys.modules.pop(k, None)
            else:
                sys.modules[k] = v
    return problem, doc, module


def test_a_push_of_your_own_is_shared_as_the_hat_fit_did():
    """A hat fit's scene carries the load shares: ``applied`` of the forces as given is the
    export's load case (the shared forces the fit judged), and a node-load scene gives a
    force back as it is."""
    from live_page import conforming_spec

    spec = conforming_spec(0.012)
    spec["fpm"] = {"stiffness": "families+volume", "loads": "hat"}
    problem, doc, module = scene_of(spec)
    assert module.MODEL["load_shares"] == doc["load_shares"]
    for j, case in enumerate(problem.load_cases):
        given = case.as_given()
        assert len(case.nodes) > len(given.nodes)
        nodes, forces = module.applied(given.nodes, given.forces)
        spread = np.zeros((problem.n_nodes, 3))
        spread[nodes] = forces
        spread[problem.fixed] = 0.0
        expected = np.zeros_like(spread)
        expected[doc["load_cases"][j]["nodes"]] = doc["load_cases"][j]["forces"]
        np.testing.assert_allclose(spread, expected, rtol=0, atol=1e-15)
    spec["fpm"] = {"stiffness": "families+volume"}
    _, node_doc, node_module = scene_of(spec)
    assert "load_shares" not in node_module.MODEL
    assert node_module.applied([5, 3], [[1, 2, 3], [4, 5, 6]]) == ([3, 5], [[4, 5, 6], [1, 2, 3]])


def volume_field(scene):
    _, doc, module = scene
    root = module.createScene(Node())
    (body,) = root.children
    fields = [kind for kind, _ in body.objects if isinstance(kind, module.VolumeForceField)]
    assert len(fields) == 1
    return fields[0]


def test_the_scene_carries_the_whole_model(scene):
    problem, doc, module = scene
    root = module.createScene(Node())
    engine = doc["parameters"]["engine"]  # the engine's d and dt, not the kernel's 0.05
    assert root.dt == engine["dt"] != doc["parameters"]["dt"]
    assert module.MODEL["parameters"]["engine"] == engine
    (body,) = root.children
    objects = {
        kind if isinstance(kind, str) else "VolumeForceField": data for kind, data in body.objects
    }
    springs = np.array(objects["SpringForceField"]["spring"])
    assert springs.shape == (len(doc["springs"]), 5)
    expected = np.array(doc["springs"])
    assert np.array_equal(springs[:, [0, 1, 4, 2]], expected)  # i j ks kd L against i j L k
    assert np.all(springs[:, 3] == 0)
    assert objects["DiagonalMass"]["vertexMass"] == doc["masses"]
    assert objects["MeshTopology"]["hexahedra"] == doc["hexahedra"]
    assert objects["FixedProjectiveConstraint"]["indices"] == doc["fixed"]
    assert objects["ConstantForceField"]["forces"] == doc["load_cases"][0]["forces"]
    assert objects["UniformVelocityDampingForceField"]["dampingCoefficient"] == engine["d"]
    assert "VolumeForceField" in objects


def test_add_force_equals_the_kernel(scene):
    problem, doc, module = scene
    field = volume_field(scene)
    rng = np.random.default_rng(5)
    u = 0.05 * problem.h * rng.standard_normal(problem.nodes.shape)
    forces = Data(np.zeros_like(u))
    field.addForce({}, forces, Data(problem.nodes + u), Data(np.zeros_like(u)))
    expected = volume_forces(cells(problem), np.asarray(doc["volume_stiffness"]), u)
    assert np.abs(forces.value - expected).max() <= 1e-12 * np.abs(expected).max()
    # with the springs (SOFA's own component, from the same numbers) the runtime's whole force
    runtime = Runtime.from_export(doc)
    runtime.stiffness[:] = 0.0
    assert np.abs(runtime.internal_forces(problem.nodes + u) - forces.value).max() <= (
        1e-12 * np.abs(expected).max()
    )


def test_tangent_against_central_differences(scene):
    problem, _, module = scene
    field = volume_field(scene)
    rng = np.random.default_rng(6)
    x = problem.nodes + 0.05 * problem.h * rng.standard_normal(problem.nodes.shape)
    dx = problem.h * rng.standard_normal(x.shape)
    eps = 1e-6
    numeric = (field.forces(x + eps * dx) - field.forces(x - eps * dx)) / (2 * eps)
    field.forces(x)
    dforce = Data(np.zeros_like(x))
    field.addDForce({"kFactor": 1.0}, dforce, Data(dx))
    scale = np.abs(numeric).max()
    assert np.abs(dforce.value - numeric).max() <= 1e-7 * scale
    # addKToMatrix: the same K as triplets, scaled by kFactor
    triplets = field.addKToMatrix({"kFactor": 2.0, "bFactor": 0.0}, len(x), 3)
    k = np.zeros((x.size, x.size))
    np.add.at(k, (triplets[:, 0].astype(int), triplets[:, 1].astype(int)), triplets[:, 2])
    assert np.abs(k @ dx.ravel() - 2.0 * dforce.value.ravel()).max() <= 1e-10 * scale
    assert np.abs(k - k.T).max() <= 1e-10 * np.abs(k).max()  # a potential's Hessian


def test_the_xml_scene_points_to_sofa_python():
    spec = json.loads((ROOT / "examples/small-box.json").read_text())
    problem = load_problem({**spec, "fpm": {"stiffness": "families+volume"}})
    assert "sofa-python" in export_warnings(problem, "sofa")[0]
    assert export_warnings(problem, "sofa-python") == []
