"""fpm.dynamics.engine_damping: the stiffness at rest it assembles, its two eigensolves (exact by
shift-invert on small lattices, LOBPCG with a multigrid preconditioner above), and that the
d and dt it gives settle the all-at-once step in fewer steps than the kernel's on the paper's
cube (the organ: tests/core/test_native.py)."""

import json
import sys
from pathlib import Path

import numpy as np
import pytest

from fpm.dynamics import engine_damping as ed
from fpm.runtime import Runtime

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(Path(__file__).parent))
from test_runtime import exported  # noqa: E402


@pytest.fixture(scope="module")
def cube():
    """The paper's cube's export at the continuum start (its d half the critical scale)."""
    spec = json.loads((ROOT / "examples/paper-material-a.json").read_text())
    spec["fpm"] = {"stiffness": "families+volume", "dt": "auto"}
    return exported(spec)[3]


def test_the_stiffness_at_rest_is_the_tangent_of_the_forces(cube):
    """K dx = -(F(x0 + e dx) - F(x0 - e dx)) / 2e, springs and volume term, to 1e-6."""
    rt = Runtime.from_export(cube, backend="numpy", damping="kernel")
    k = ed.rest_stiffness(rt)
    rng = np.random.default_rng(1)
    dx = rng.standard_normal(rt.rest.shape)
    eps = 1e-7 * cube["h"]
    central = -(rt.internal_forces(rt.rest + eps * dx) - rt.internal_forces(rt.rest - eps * dx))
    central /= 2 * eps
    kdx = (k @ dx.ravel()).reshape(dx.shape)
    assert np.abs(kdx - central).max() <= 1e-6 * np.abs(central).max()
    assert abs(k - k.T).max() <= 1e-12 * abs(k).max()


def test_the_multigrid_eigensolve_agrees_with_shift_invert(monkeypatch):
    """Above DIRECT_UP_TO unknowns w_min comes from LOBPCG (an upper bound): on a 13^3 box
    within 0.5% of shift-invert's, d within 1%, the same w_max, dt within 1e-4; the same bits
    twice."""
    from bench.bench_native import box_runtime

    rt, _ = box_runtime(13, "numpy")
    assert 3 * int((~rt.fixed).sum()) > ed.DIRECT_UP_TO
    fast = ed.engine_damping(rt)
    assert fast == ed.engine_damping(rt)  # deterministic: an export is the same file twice
    monkeypatch.setattr(ed, "DIRECT_UP_TO", 10**9)
    exact = ed.engine_damping(rt)
    assert exact.omega_min <= fast.omega_min <= 1.005 * exact.omega_min
    assert fast.d == pytest.approx(exact.d, rel=0.01)
    assert fast.dt == pytest.approx(exact.dt, rel=1e-4)  # through w_min only
    assert fast.omega_max == pytest.approx(exact.omega_max, rel=1e-6)


def test_the_export_block(cube):
    """EngineDamping.as_export: the fields docs/reference/json-export.md lists, consistent with
    one another (dt = 2 / (w_max - w_min), d = (q^2 - 1) m / dt, the decay 1 / q)."""
    found = ed.engine_damping(Runtime.from_export(cube, backend="numpy", damping="kernel"))
    block = found.as_export()
    assert list(block) == [
        "d", "dt", "decay_per_step", "omega_min", "omega_max", "mode_mass", "margin",
    ]  # fmt: skip
    w0, w1 = block["omega_min"], block["omega_max"]
    q = (w1 + w0) / (w1 - w0)
    assert block["dt"] == pytest.approx(2 / (w1 - w0), rel=1e-12)
    assert block["decay_per_step"] == pytest.approx(1 / q, rel=1e-12)
    assert block["d"] == pytest.approx((q * q - 1) * block["mode_mass"] / block["dt"], rel=1e-12)
    masses = np.asarray(cube["masses"])
    assert masses.min() <= block["mode_mass"] <= masses.max() and block["margin"] == ed.MARGIN


def test_the_engine_damping_settles_the_cube_in_fewer_steps(cube):
    """Each load case of the cube from rest: fewer steps at the engine's d and dt than at the
    export's (the kernel's), to the same equilibrium (within the settle criterion's 1%)."""
    kernel = Runtime.from_export(cube, damping="kernel")
    engine, found = ed.with_engine_damping(kernel)
    assert (engine.damping, engine.d, engine.dt) == ("engine", found.d, found.dt)
    for case in range(len(cube["load_cases"])):
        push = kernel.load_case_forces(cube, case)
        kernel.reset()
        engine.reset()
        slow, fast = kernel.run(push, 50_000), engine.run(push, 50_000)
        assert kernel.settled and engine.settled and fast < slow
        u = np.abs(kernel.x - kernel.rest).max()
        assert np.abs(engine.x - kernel.x).max() <= 0.02 * u
