"""research.tet_model: its three models' matrices checked against uniform strains on the
bench's organ mesh (curved, no two tetrahedra alike), and :func:`measure` end to end on that
organ meshed with 72 tetrahedra, its figures read back from what it prints."""

from __future__ import annotations

import re

import numpy as np
import pytest

from bench import tet_organ
from fpm.fem.elasticity import constitutive_matrix
from research.tet_model import (
    gradients,
    main,
    relative,
    spring_stiffness,
    tetrahedra_stiffness,
    volume_stiffness,
)

E, NU = 5e3, 0.45


@pytest.fixture(scope="module")
def mesh():
    return tet_organ.organ_mesh((3, 2, 2))


def energy(k, u: np.ndarray) -> float:
    return float(0.5 * u.ravel() @ (k @ u.ravel()))


def test_the_gradients_reproduce_linear_fields_and_the_volume(mesh):
    x, t = mesh
    volume, g = gradients(x, t)
    assert np.all(volume > 0)
    # the organ's volume by the divergence theorem over its boundary faces, oriented outwards
    faces = np.concatenate([t[:, [1, 2, 3]], t[:, [0, 3, 2]], t[:, [0, 1, 3]], t[:, [0, 2, 1]]])
    _, first, count = np.unique(
        np.sort(faces, axis=1), axis=0, return_index=True, return_counts=True
    )
    a, b, c = (x[faces[first[count == 1]]][:, i] for i in range(3))
    assert volume.sum() == pytest.approx(np.einsum("ij,ij->", a, np.cross(b, c)) / 6, rel=1e-12)
    assert np.abs(g.sum(axis=1)).max() < 1e-9 * np.abs(g).max()
    identity = np.einsum("tai,taj->tij", g, x[t])  # sum_a grad(lambda_a) x_a^T
    assert np.abs(identity - np.eye(3)).max() < 1e-9


def test_the_linear_tetrahedra_pass_the_patch_test(mesh):
    x, t = mesh
    c = constitutive_matrix(E, NU)
    k = tetrahedra_stiffness(x, t, c)
    grad = 1e-3 * np.random.default_rng(3).normal(size=(3, 3))
    strain = 0.5 * (grad + grad.T)
    voigt = np.array([*np.diag(strain), 2 * strain[0, 1], 2 * strain[1, 2], 2 * strain[0, 2]])
    volume = gradients(x, t)[0].sum()
    assert energy(k, x @ grad.T) == pytest.approx(0.5 * volume * voigt @ c @ voigt, rel=1e-10)
    spin = np.array([[0, -1, 2], [1, 0, -3], [-2, 3, 0]], float)
    for rigid in (np.ones_like(x) * [1, 2, 3], x @ spin.T):
        assert np.abs(k @ rigid.ravel()).max() < 1e-9 * abs(k).max()


def test_springs_and_volume_term_under_uniform_strains(mesh):
    """A dilation eps stretches every edge by eps l_e: springs of k_e = sum V_t / l_e^2 hold
    0.5 eps^2 sum_e sum_{t holding e} V_t = 3 eps^2 V (six edges a tetrahedron), the volume term
    0.5 (3 eps V_t)^2 / V_t a tetrahedron, 4.5 eps^2 V; a shear keeps every volume, and
    infinitesimal rotations cost neither."""
    x, t = mesh
    volume = gradients(x, t)[0].sum()
    springs, count = spring_stiffness(x, t)
    pairs = [(i, j) for i in range(4) for j in range(i + 1, 4)]
    edges = {(min(tet[i], tet[j]), max(tet[i], tet[j])) for tet in t for i, j in pairs}
    assert count == len(edges)
    vol = volume_stiffness(x, t)
    eps = 1e-3
    assert energy(springs, eps * x) == pytest.approx(3 * eps**2 * volume, rel=1e-10)
    assert energy(vol, eps * x) == pytest.approx(4.5 * eps**2 * volume, rel=1e-10)
    shear = np.array([[1.0, 2.0, 0.0], [0.5, -3.0, 1.0], [0.0, 0.0, 2.0]]) * eps
    assert energy(vol, x @ shear.T) < 1e-12 * energy(vol, eps * x)
    assert energy(springs, x @ shear.T) > 0
    spin = np.array([[0, -1, 2], [1, 0, -3], [-2, 3, 0]], float) * eps
    for k in (springs, vol):
        assert np.abs(k @ (x @ spin.T).ravel()).max() < 1e-9 * abs(k).max() * eps


def test_relative_is_eq2_over_the_kept_nodes():
    truth = np.random.default_rng(5).normal(size=(2, 6, 3))
    keep = np.array([True, True, False, True, True, True])
    u = truth.copy()
    u[:, 2] += 1.0  # a node left out
    assert relative(u, truth, keep) == [0.0, 0.0]
    assert relative(np.zeros_like(truth), truth, keep) == pytest.approx([100.0, 100.0])
    assert relative(-truth, truth, keep) == pytest.approx([200.0, 200.0])


def test_measure_on_a_tiny_organ(monkeypatch, capsys):
    """Two levels of the 72-tetrahedron organ: the refined mesh has a node per corner and per
    edge (a spring each) and 8 tetrahedra per tetrahedron; every figure a percentage; the linear
    tetrahedra converge to the 10-node reference on refinement, case by case; and E and nu fitted do
    no worse on the fitted cases than the given ones (from which Nelder-Mead starts)."""
    made = {**tet_organ.ORGANS["organ"], "mesh": lambda: tet_organ.organ_mesh((3, 2, 2))}
    monkeypatch.setitem(tet_organ.ORGANS, "tiny", made)
    main(["tiny", "0.025", "0", "1"])
    out = capsys.readouterr().out
    levels = re.findall(
        r"(\d) refinement\(s\): ([\d,]+) nodes, ([\d,]+) tetrahedra\n"
        r".*as given: (.*)\n"
        r"\s+([\d,]+) springs .*\(a ([\d.e+-]+), kappa ([\d.e+-]+) E\): "
        r"fitted (.*); validation (.*)\n"
        r".*nu [\d.]+ fitted: fitted (.*); validation (.*)\n",
        out,
    )
    assert [level[0] for level in levels] == ["0", "1"]

    def numbers(text: str) -> list[float]:
        return [float(v) for v in text.split(" / ")]

    (_, n0, t0, plain0, s0, *_), (_, n1, t1, plain1, *_) = levels
    assert int(n1.replace(",", "")) == int(n0) + int(s0) and int(t1) == 8 * int(t0) == 8 * 72
    for _, _, _, plain, _, a, kappa, fit, check, fit_e, check_e in levels:
        assert float(a) > 0 and float(kappa) > 0
        every = [numbers(plain), numbers(fit) + numbers(check), numbers(fit_e) + numbers(check_e)]
        assert all(len(v) == 5 and all(0 < f < 100 for f in v) for v in every)
        assert np.mean(every[2][:2]) <= np.mean(every[0][:2]) + 0.05  # printed to 0.1
    assert all(b < a for a, b in zip(numbers(plain0), numbers(plain1), strict=True))
