"""The native step (fpm/native/fpm_step.c, compiled here with the system's C compiler) and its
numba twin against fpm.runtime's NumPy recipe; the binary export and the C loader's checks."""

import copy
import json
import shutil
import struct
import subprocess
import sys
import zlib
from pathlib import Path

import numpy as np
import pytest
import scipy.sparse.linalg as spla

from fpm import native
from fpm.io.export_binary import HEADER, from_json
from fpm.runtime import Runtime

sys.path.insert(0, str(Path(__file__).parent))
from test_runtime import exported  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]
pytestmark = pytest.mark.skipif(shutil.which("cc") is None, reason="no C compiler")


@pytest.fixture(scope="module", autouse=True)
def fresh_cache(tmp_path_factory):
    """Compiled in this test run, not taken from a cache."""
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("FPM_NATIVE_CACHE", str(tmp_path_factory.mktemp("native")))
        mp.delenv("FPM_CC", raising=False)
        mp.delenv("FPM_RUNTIME_BACKEND", raising=False)
        native._libraries.clear()
        yield
        native._libraries.clear()


@pytest.fixture(scope="module")
def cube():
    spec = json.loads((ROOT / "examples/paper-material-a.json").read_text())
    spec["fpm"] = {"stiffness": "families+volume", "dt": "auto", "settle_tolerance": 1e-12}
    return exported(spec)[3]


@pytest.fixture(scope="module")
def organ():
    """The conforming organ lattice (irregular hexahedra, volume term, fixed nodes) under
    gravity."""
    from live_page import conforming_spec

    spec = conforming_spec(0.012)
    spec["fpm"].update(stiffness="families+volume", settle_tolerance=1e-12, gravity=[0, 0, -9.81])
    return exported(spec)[3]


_recipe: dict[str, tuple] = {}


def drive(doc, backend, steps, precision="float64"):
    """``steps`` steps under load case 1 scaled by 1 + sin: (runtime, (steps, N, 3) positions
    every 100th step, the unbalanced forces, the settled flags)."""
    rt = Runtime.from_export(doc, backend=backend, precision=precision, damping="kernel")
    assert rt.backend_used == backend
    push = rt.load_case_forces(doc, 0)
    seen, unbalanced, settled = [], [], []
    for n in range(steps):
        x = rt.step(push * (1.0 + 0.5 * np.sin(0.02 * n)) if n < steps // 2 else push)
        unbalanced.append(rt.unbalanced)
        settled.append(rt.settled)
        if n % 100 == 0:
            seen.append(np.array(x, dtype=float))
    return rt, np.stack(seen), np.array(unbalanced), np.array(settled)


@pytest.mark.parametrize("backend", ["native", "numba"])
@pytest.mark.parametrize("lattice", ["cube", "organ"])
def test_the_compiled_step_is_the_numpy_recipe(request, lattice, backend):
    """After thousands of steps with forces that change every step, positions within 1e-12 of
    the largest displacement, the same unbalanced forces and the same settle decisions."""
    doc = request.getfixturevalue(lattice)
    steps = 3000
    if lattice not in _recipe:  # the NumPy run, once per lattice
        _recipe[lattice] = drive(doc, "numpy", steps)
    ref, x_ref, unb_ref, set_ref = _recipe[lattice]
    rt, x, unb, settled = drive(doc, backend, steps)
    scale = np.abs(x_ref - ref.rest).max()
    assert scale > 0
    assert np.abs(x - x_ref).max() <= 1e-12 * scale
    assert np.abs(unb - unb_ref).max() <= 1e-12 * unb_ref.max()  # near rest: rounding
    assert np.array_equal(settled, set_ref)
    assert np.array_equal(rt.x[rt.fixed], rt.rest[rt.fixed])


def test_runs_settle_in_the_same_steps(organ):
    """At the kernel's d, which is overdamped: at the engine's every mode oscillates as it
    decays, the unbalanced force crosses the settle threshold more than once, and a rounding
    difference can pick another crossing (474 against 480 steps on this organ). At a settle
    tolerance of 1e-9, not the fixture's 1e-12: there the threshold (1e-14 N) is the rounding
    floor of the force sums, where their order, not the step, decides the crossing."""
    organ = copy.deepcopy(organ)
    organ["parameters"]["settle_tolerance"] = 1e-9
    counts = {}
    for backend in ("numpy", "native", "numba"):
        rt = Runtime.from_export(organ, backend=backend, damping="kernel")
        counts[backend] = rt.run(rt.load_case_forces(organ, 1), max_steps=20_000)
    assert counts["numpy"] < 20_000
    assert counts["native"] == counts["numba"] == counts["numpy"]


def test_internal_forces_equal_the_recipe(organ):
    rt = Runtime.from_export(organ, backend="native")
    rng = np.random.default_rng(5)
    x = rt.rest + 0.05 * organ["h"] * rng.standard_normal(rt.rest.shape)
    expected = rt.internal_forces(x)  # the NumPy recipe's, whatever the backend
    for step in (rt._engine, Runtime.from_export(organ, backend="numba")._engine):
        got = step.internal_forces(x)
        assert np.abs(got - expected).max() <= 1e-12 * np.abs(expected).max()


def test_float32_keeps_the_equilibrium_within_1e4(cube):
    """float32 state and model: the settled displacement within 1e-4 of float64's."""
    settling = Runtime.from_export(cube, backend="native")
    steps = settling.run(settling.load_case_forces(cube, 0), max_steps=20_000)
    results = {}
    for precision in ("float64", "float32"):
        rt = Runtime.from_export(cube, backend="native", precision=precision)
        assert rt.x.dtype == np.dtype(precision)
        push = rt.load_case_forces(cube, 0)
        for _ in range(steps):
            rt.step(push)
        results[precision] = np.asarray(rt.x - rt.rest, dtype=float)
    u = results["float64"]
    assert np.abs(results["float32"] - u).max() <= 1e-4 * np.abs(u).max()


def test_threads_change_nothing(organ):
    one = Runtime.from_export(organ, backend="native")
    two = Runtime.from_export(organ, backend="native")
    one._engine.threads, two._engine.threads = 1, 2
    push = one.load_case_forces(organ, 0)
    for _ in range(500):
        one.step(push)
        two.step(push)
    assert np.array_equal(one.x, two.x)


# ------------------------------------------------------------------ the binary export


def test_the_cli_writes_the_binary_export_the_c_example_reads(tmp_path):
    """fpmcal export --format binary on the paper's small box, read by the example program
    (examples/native_step.c, compiled here), which settles in the steps fpm.runtime takes."""
    spec = json.loads((ROOT / "examples/small-box.json").read_text())
    spec["fpm"] = {"stiffness": "families+volume", "settle_tolerance": 1e-10}
    from fpm import load_problem
    from fpm.model.stiffness import continuum_start, stiffness_dict, volume_stiffness

    problem = load_problem(spec)
    theta = continuum_start(problem)
    params = {
        "stiffness": stiffness_dict(problem, theta),
        "volume_stiffness": volume_stiffness(problem, theta),
        "d": float(np.sqrt(problem.spec.material.youngs_modulus * problem.h
                           * problem.solid.masses.mean())),
        "depth": None,
    }  # fmt: skip
    (tmp_path / "spec.json").write_text(json.dumps(spec))
    (tmp_path / "params.json").write_text(json.dumps(params))
    from fpmcal.cli import main

    for fmt, out in (("binary", "box.fpmb"), ("json", "box.json")):
        spec_file, params_file = str(tmp_path / "spec.json"), str(tmp_path / "params.json")
        args = ["export", spec_file, params_file, "--format", fmt, "-o", str(tmp_path / out)]
        assert main(args) in (0, None)
    doc = json.loads((tmp_path / "box.json").read_text())
    assert (tmp_path / "box.fpmb").read_bytes() == from_json(doc)
    program = tmp_path / "native_step"
    subprocess.run(
        ["cc", "-O2", f"-I{ROOT / 'fpm/native'}", str(ROOT / "examples/native_step.c"),
         str(ROOT / "fpm/native/fpm_step.c"), "-o", str(program), "-lm"],
        check=True, capture_output=True,
    )  # fmt: skip
    run = subprocess.run([str(program), "box.fpmb"], cwd=tmp_path, capture_output=True, text=True)
    assert run.returncode == 0, run.stderr
    rt = Runtime.from_export(doc, backend="numpy")  # the binary's d and dt: the engine's
    assert doc["parameters"]["engine"] and rt.damping == "engine"
    loaded = rt.run(rt.load_case_forces(doc, 0))
    largest = np.abs(rt.x - rt.rest).max()
    released = rt.run(None)
    assert f"settled in {loaded} steps" in run.stdout
    assert f"at rest again in {released} steps" in run.stdout
    printed = float(run.stdout.split("largest displacement ")[1].split(" m")[0])
    assert printed == pytest.approx(largest, rel=1e-5)


def load(data: bytes):
    return native.NativeStep(data)


def resealed(data: bytearray) -> bytes:
    """``data`` with its checksum made right again (a well-formed file with a bad value)."""
    body = bytes(data[:-4])
    return body + struct.pack("<I", zlib.crc32(body))


def offset_of(doc, field: str) -> int:
    """The byte offset of the array ``field`` in the binary export of ``doc``."""
    n, s, h = len(doc["masses"]), len(doc["springs"]), len(doc["hexahedra"])
    sizes = [
        ("nodes", 24 * n), ("masses", 8 * n), ("fixed", 4 * len(doc["fixed"])),
        ("spring_i", 4 * s), ("spring_j", 4 * s), ("rest_lengths", 8 * s),
        ("stiffness", 8 * s), ("hexahedra", 32 * h), ("volume_stiffness", 8 * h),
    ]  # fmt: skip
    offset = HEADER.size
    for name, size in sizes:
        if name == field:
            return offset
        offset += size
    raise KeyError(field)


def test_bad_files_are_refused_naming_the_field(cube):
    data = from_json(cube)
    assert load(data).n_nodes == len(cube["masses"])
    with pytest.raises(native.NativeError, match="truncated: 50 bytes"):
        load(data[:50])
    with pytest.raises(native.NativeError, match=f"truncated: {len(data) - 7} bytes of"):
        load(data[:-7])
    with pytest.raises(native.NativeError, match="magic"):
        load(b"XXXX" + data[4:])
    flipped = bytearray(data)
    flipped[len(data) // 2] ^= 0x40
    with pytest.raises(native.NativeError, match="crc32.*corrupt"):
        load(bytes(flipped))
    counted = bytearray(data)
    counted[12:16] = struct.pack("<I", len(cube["springs"]) + 1)
    with pytest.raises(native.NativeError, match="total_bytes"):
        load(resealed(counted))
    for field, index, value, message in [
        ("stiffness", 3, float("nan"), r"stiffness\[3\]: nan"),
        ("masses", 7, 0.0, r"masses\[7\]: 0, must be finite and > 0"),
        ("rest_lengths", 2, float("inf"), r"rest_lengths\[2\]: inf"),
        ("volume_stiffness", 5, -1.0, r"volume_stiffness\[5\]: -1"),
    ]:
        bad = bytearray(data)
        at = offset_of(cube, field) + 8 * index
        bad[at : at + 8] = struct.pack("<d", value)
        with pytest.raises(native.NativeError, match=message):
            load(resealed(bad))
    bad = bytearray(data)
    at = offset_of(cube, "spring_j") + 4 * 9
    bad[at : at + 4] = struct.pack("<I", 10**6)
    with pytest.raises(native.NativeError, match=r"spring_j\[9\]: 1000000, must be < 1000"):
        load(resealed(bad))


def test_a_dt_above_the_stability_limit_is_refused(cube):
    step = load(from_json(cube))
    dt = cube["parameters"]["dt"]
    assert dt <= step.stable_dt
    unstable = json.loads(json.dumps(cube))
    unstable["parameters"]["dt"] = 4 * step.stable_dt  # the header's dt: the engine's if any
    if unstable["parameters"].get("engine"):
        unstable["parameters"]["engine"]["dt"] = 4 * step.stable_dt
    with pytest.raises(native.NativeError, match="dt: .* above the lattice's stability limit"):
        load(from_json(unstable))
    with pytest.raises(native.NativeError, match="dt: .* above"):
        step.set_parameters(cube["parameters"]["d"], 4 * step.stable_dt)
    with pytest.raises(native.NativeError, match="d: -1"):
        step.set_parameters(-1.0, dt)


def test_a_dt_that_diverges_is_caught_not_nan(cube):
    """Just above the guaranteed bound the loader lets dt through (the step may be stable);
    where it does diverge the step says so instead of returning NaN."""
    step = load(from_json(cube))
    rt = Runtime.from_export(cube, backend="native")
    for factor in (1.5, 2.0, 2.5, 3.0, 3.5):
        try:
            rt._engine.set_parameters(0.0, factor * step.stable_dt)
        except native.NativeError:
            break  # refused: certainly unstable
        rt.reset()
        push = rt.load_case_forces(cube, 0)
        try:
            for _ in range(3000):
                rt.step(push)
        except native.NativeError as e:
            assert "diverged" in str(e)
            return
        assert np.isfinite(rt.x).all()
    else:
        pytest.fail("no dt up to 3.5 times the bound was refused or diverged")


def test_non_finite_forces_are_refused_and_the_state_kept(cube):
    rt = Runtime.from_export(cube, backend="native")
    push = rt.load_case_forces(cube, 0)
    for _ in range(10):
        rt.step(push)
    x, v = rt.x.copy(), rt.v.copy()
    bad = push.copy()
    bad[17, 1] = np.inf
    with pytest.raises(native.NativeError, match=r"forces\[17\]\.y: not finite"):
        rt.step(bad)
    assert np.array_equal(rt.x, x) and np.array_equal(rt.v, v)


# ------------------------------------------------------------------ choosing the backend


def test_auto_without_a_compiler_is_numba_then_numpy(cube, monkeypatch):
    monkeypatch.setenv("FPM_CC", "none")
    native._libraries.clear()
    assert Runtime.from_export(cube).backend_used == "numba"
    with pytest.raises(native.CompilerUnavailable, match="no C compiler"):
        Runtime.from_export(cube, backend="native")
    monkeypatch.setitem(sys.modules, "fpm.native.numba_step", None)  # numba not installed
    rt = Runtime.from_export(cube)
    assert rt.backend_used == "numpy" and rt._engine is None
    rt.step(rt.load_case_forces(cube, 0))
    monkeypatch.setenv("FPM_CC", "/nonexistent/cc")
    assert Runtime.from_export(cube).backend_used == "numpy"


def test_a_compiler_that_fails_falls_back(cube, monkeypatch, tmp_path):
    failing = tmp_path / "cc"
    failing.write_text("#!/bin/sh\necho 'cc: error: broken' >&2\nexit 1\n")
    failing.chmod(0o755)
    monkeypatch.setenv("FPM_CC", str(failing))
    native._libraries.clear()
    assert Runtime.from_export(cube).backend_used == "numba"
    with pytest.raises(native.CompilerUnavailable, match="broken"):
        Runtime.from_export(cube, backend="native")


def test_the_backend_from_the_environment(cube, monkeypatch):
    monkeypatch.setenv("FPM_RUNTIME_BACKEND", "numpy")
    assert Runtime.from_export(cube).backend_used == "numpy"
    assert Runtime.from_export(cube, backend="native").backend_used == "native"
    with pytest.raises(ValueError, match="backend: 'fast'"):
        Runtime.from_export(cube, backend="fast")
    with pytest.raises(ValueError, match="precision"):
        Runtime.from_export(cube, backend="numba", precision="float32")


# ------------------------------------------------------------------ the engine's damping


def test_the_engine_damping_settles_in_fewer_steps_at_the_same_equilibrium(organ):
    """fpm.dynamics.engine_damping's d and dt: every load case of the organ settles in fewer
    steps than at the export's d and dt, at the same equilibrium."""
    from fpm.dynamics.engine_damping import with_engine_damping

    kernel = Runtime.from_export(organ, backend="native", damping="kernel")
    engine, found = with_engine_damping(kernel)
    assert engine.backend_used == "native" and (engine.d, engine.dt) == (found.d, found.dt)
    assert found.omega_min < found.omega_max and 0 < found.decay < 1
    for case in range(len(organ["load_cases"])):
        push = kernel.load_case_forces(organ, case)
        kernel.reset()
        engine.reset()
        slow = kernel.run(push, max_steps=50_000)
        fast = engine.run(push, max_steps=50_000)
        assert engine.settled and fast < slow
        u = kernel.x - kernel.rest
        assert np.abs(engine.x - kernel.x).max() <= 1e-6 * np.abs(u).max()


# ------------------------------------------------------------------ a probe, live


@pytest.fixture(scope="module")
def organ_plain():
    from live_page import conforming_spec

    spec = conforming_spec(0.012)
    spec["fpm"].update(stiffness="families+volume")
    return exported(spec)[3]


class Probe:
    """A rigid probe pressing one surface node along ``direction`` by a penalty ``stiffness``
    (N/m), one-sided: it pushes, never pulls; its tip at ``depth(t)`` (m) past the node's rest
    position."""

    def __init__(self, rt, node, direction, stiffness, depth):
        self.rt, self.node, self.n, self.k, self.depth = rt, node, direction, stiffness, depth
        self.forces = np.zeros_like(rt.rest)

    def gap(self, t):
        return max(
            0.0, self.depth(t) - float((self.rt.x[self.node] - self.rt.rest[self.node]) @ self.n)
        )

    def force(self, t):
        self.forces[self.node] = self.k * self.gap(t) * self.n
        return self.forces

    def energy(self, t):
        """Kinetic, the model's and the penalty's energy, J."""
        rt = self.rt
        kinetic = 0.5 * float(np.sum(rt.masses[:, None] * rt.v**2))
        return kinetic + rt.energy(rt.x) + 0.5 * self.k * self.gap(t) ** 2


def press(t, depth):
    """In over 0.5 s, held 0.5 s, out over 0.5 s, away 0.5 s."""
    return depth * min(1.0, t / 0.5, max(0.0, (1.5 - t) / 0.5)) if t < 1.5 else 0.0


def test_a_probe_at_1khz_for_two_seconds(organ_plain):
    """A probe pressed into the organ's surface and back, the C step at the engine's damping
    with its dt cut to a whole number of steps a millisecond: during the holds the energy never
    grows (to rounding), the reaction at rest is the static equilibrium's within 2% (solved
    here apart from the dynamics: Newton's iteration on the same forces with the stiffness at
    rest), and after the release the organ comes back to rest."""
    import dataclasses
    import math

    from fpm.dynamics.engine_damping import engine_damping, rest_stiffness

    doc = organ_plain
    base = Runtime.from_export(doc, backend="native")
    found = engine_damping(base)
    substeps = math.ceil(1e-3 / found.dt)
    rt = dataclasses.replace(base, d=found.d, dt=1e-3 / substeps)
    case = doc["load_cases"][0]
    node, push = case["nodes"][0], np.asarray(case["forces"][0], dtype=float)
    stiffness = rest_stiffness(rt)
    k = 4.0 * float(stiffness[3 * node : 3 * node + 3, 3 * node : 3 * node + 3].diagonal().max())
    depth = 0.2 * doc["h"]
    probe = Probe(rt, node, push / np.linalg.norm(push), k, lambda t: press(t, depth))
    energy, reaction = [], []
    for tick in range(2000):
        t = (tick + 1) * 1e-3
        for _ in range(substeps):
            rt.step(probe.force(t))
        energy.append(probe.energy(t))
        reaction.append(k * probe.gap(t))
    energy = np.array(energy)
    peak = energy.max()
    for start, end in ((500, 1000), (1500, 2000)):  # the holds: nothing moves the probe
        assert np.diff(energy[start:end]).max() <= 1e-12 * peak
    assert energy[-1] <= 1e-9 * peak and np.abs(rt.x - rt.rest).max() <= 1e-6 * depth
    # the static equilibrium at full depth, the probe's penalty included
    free = ~rt.fixed
    dofs = np.repeat(free, 3)
    tangent = stiffness.tolil()
    block = slice(3 * node, 3 * node + 3)
    tangent[block, block] += k * np.outer(probe.n, probe.n)
    solve = spla.factorized(tangent.tocsc()[dofs][:, dofs])
    x = rt.rest.copy()
    for _ in range(50):
        gap = depth - float((x[node] - rt.rest[node]) @ probe.n)
        f = rt.internal_forces(x)
        f[node] += k * gap * probe.n
        f[~free] = 0.0
        if np.abs(f).max() < 1e-12 * k * depth:
            break
        x[free] += solve(f[free].ravel()).reshape(-1, 3)
    static = k * (depth - float((x[node] - rt.rest[node]) @ probe.n))
    assert reaction[999] == pytest.approx(static, rel=0.02)
    assert np.abs(f).max() < 1e-12 * k * depth  # Newton converged
