"""research.organ_diagnose, on the smallest inputs that run it: :func:`near_field_imposed` on a
column of cells, where the far field is known exactly, and :func:`diagnose` end to end on the
bench's organ meshed with 72 tetrahedra at a 25 mm lattice (45 nodes), its figures read back
from what it prints."""

from __future__ import annotations

import re
from types import SimpleNamespace

import numpy as np
import pytest
import scipy.sparse.linalg as spla

import fpm
from bench import tet_organ
from fpm.dynamics.spring_system import SpringSystem
from fpm.model.stiffness import continuum_start, model_stiffness
from research.organ_diagnose import NEAR, diagnose, near_field_imposed
from tests.helpers_fpm import box_spec

H = 0.01


def figures(line: str) -> list[float]:
    """The ' / '-separated figures after the line's last colon."""
    return [float(v) for v in line.rsplit(":", 1)[1].split(" / ")]


def test_a_uniformly_stiffer_truth_is_exact_beyond_the_imposed_near_field(capsys):
    """The truth is the lattice at twice its parameters (half its displacements: the tangent is
    linear in them). Solved as it is, the lattice's far-field error is then the far field's share
    of the truth; with the truth imposed within NEAR h of the loads, every load lies inside and
    the far field's equations K_ff u_f = -K_fh u_h are those of the stiffer lattice too: exact,
    whatever the scale, and the refit (started there) keeps it exact."""
    top = (3 - 1) * H, (3 - 1) * H, (10 - 1) * H
    spec = box_spec(
        (3, 3, 10), H, forces=[{"at": list(top), "vector": [0.002, 0.0, -0.01]}],
        fpm_settings={"stiffness": "families+volume"},
    )  # fmt: skip
    spec["validation_cases"] = [
        {"name": "side", "forces": [{"at": [0.0, 0.0, 7 * H], "vector": [0.0, 0.01, 0.0]}]}
    ]
    problem = fpm.load_problem(spec)
    theta = continuum_start(problem)
    free = np.flatnonzero(~problem.fixed)
    system = SpringSystem(problem, free)
    k = system.tangent(np.zeros((len(free), 3)), system.parameters(model_stiffness(problem, theta)))
    truth = np.zeros((len(problem.all_cases), problem.n_nodes, 3))
    for j, case in enumerate(problem.all_cases):
        f = case.dense(problem.n_nodes)[free].ravel()
        truth[j, free] = 0.5 * spla.spsolve(k.tocsc(), f).reshape(-1, 3)

    shares = []
    for j, case in enumerate(problem.all_cases):
        loaded = problem.nodes[case.nodes]
        gap = np.linalg.norm(problem.nodes[:, None] - loaded[None], axis=2).min(axis=1)
        far = (gap > NEAR * H) & ~problem.fixed
        size = np.linalg.norm(truth[j], axis=1)
        assert 10 < far.sum() < (~problem.fixed).sum() - 10  # both fields have nodes
        shares.append(100 * size[far].sum() / size.sum())

    near_field_imposed(problem, theta, SimpleNamespace(displacements=truth), H)
    lines = capsys.readouterr().out.splitlines()
    assert figures(lines[1]) == pytest.approx(shares, abs=0.006)  # printed to 0.01
    assert 0 < min(shares) and max(shares) < 100
    assert figures(lines[2]) == [0.0, 0.0]
    assert figures(lines[3]) == [0.0, 0.0]


@pytest.fixture
def tiny_organ(monkeypatch):
    """The bench's organ (its held half and its five cases) meshed with 3 x 2 x 2 cells."""
    made = {**tet_organ.ORGANS["organ"], "mesh": lambda: tet_organ.organ_mesh((3, 2, 2))}
    monkeypatch.setitem(tet_organ.ORGANS, "tiny", made)
    return "tiny"


def test_diagnose_on_a_tiny_organ(tiny_organ, capsys):
    """Every figure a percentage; per fitted case the shares of the error grow with the radius
    (as do the counts of nodes within it) and reach the case's whole error once every node is
    within: the same Eq. 2 as the calibration's (its settled run, so to a few tenths)."""
    diagnose(tiny_organ, 0.025, 1)
    out = capsys.readouterr().out
    head = re.search(r"(\d+) nodes, families\+volume: fitted (.*), validation (.*) %", out)
    assert head is not None
    n_nodes = int(head[1])
    fitted = [float(v) for v in head[2].split(" / ")]
    assert len(fitted) == 2 and len(head[3].split(" / ")) == 3
    field = re.search(r"field: fitted (.*), validation (.*) %", out)
    assert field is not None
    cases = {m[1]: m for m in re.finditer(r"  (press top|lateral): ([\d.]+)% of which (.*)", out)}
    assert list(cases) == ["press top", "lateral"]
    for calibrated, m in zip(fitted, cases.values(), strict=True):
        total = float(m[2])
        assert total == pytest.approx(calibrated, abs=1.0)
        within = re.findall(r"(\d+) nodes within [\d.]+ h: ([\d.]+)", m[3])
        counts = [int(c) for c, _ in within]
        shares = [float(s) for _, s in within]
        assert counts == sorted(counts) and shares == sorted(shares) and shares[-1] <= total
        assert counts[-1] == n_nodes and shares[-1] == pytest.approx(total, abs=0.051)
        assert 0 < shares[0] < total
    far = [line for line in out.splitlines() if line.startswith("    ")]
    assert len(far) == 3 and all(figures(line) == [0.0] * 5 for line in far)  # no node is far
    bbar = re.search(r"B-bar, its loads\): (.*) %", out)
    once = re.search(r"refined once: (.*) %", out)
    assert bbar is not None and once is not None
    every = [
        *fitted, *map(float, head[3].split(" / ")),
        *(float(v) for g in (field[1], field[2], bbar[1], once[1]) for v in g.split(" / ")),
    ]  # fmt: skip
    assert len(every) == 2 + 3 + 2 + 3 + 2 + 5
    assert all(0 < v < 100 for v in every)
