"""The measuring tools of ``research/surface_cells.py`` (what the lattice's own nodes can hold, and
where its springs lose), checked against mathematics before their figures are
believed: the incompatible-modes hexahedron passes the patch test on a distorted cell and
bends exactly where the trilinear one locks; the per-cell spring blocks are the product's
springs and volume term (their linear solve is the static equilibrium under a small load)."""

from __future__ import annotations

import numpy as np
import pytest

import fpm
from fpm.dynamics.equilibrium import static_equilibrium
from fpm.fem.elasticity import (
    GAUSS_POINTS,
    constitutive_matrix,
    element_stiffness,
    physical_gradients,
)
from fpm.model.stiffness import continuum_start
from research.surface_cells import cell_blocks, qm6_stiffness, solve, spring_blocks

E, NU = 5e3, 0.45
C = constitutive_matrix(E, NU)
CUBE = np.array(
    [[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0, 0, 1], [1, 0, 1], [1, 1, 1], [0, 1, 1]], float
)


def distorted() -> np.ndarray:
    """(8, 3) a hexahedron far from a parallelepiped (m)."""
    rng = np.random.default_rng(7)
    return 0.01 * (CUBE + 0.2 * rng.uniform(-1, 1, CUBE.shape))


def energy(k: np.ndarray, u: np.ndarray) -> float:
    return float(0.5 * u.ravel() @ k @ u.ravel())


def test_qm6_passes_the_patch_test_and_moves_rigidly_for_free():
    x = distorted()
    k = qm6_stiffness(x[None], C)[0]
    rng = np.random.default_rng(1)
    grad = 1e-3 * rng.normal(size=(3, 3))
    strain = 0.5 * (grad + grad.T)
    voigt = np.array([*np.diag(strain), 2 * strain[0, 1], 2 * strain[1, 2], 2 * strain[2, 0]])
    volume = sum(float(physical_gradients(x[None], p)[1][0]) for p in GAUSS_POINTS)
    assert energy(k, x @ grad.T) == pytest.approx(0.5 * volume * voigt @ C @ voigt, rel=1e-10)
    spin = np.array([[0, -1, 0], [1, 0, 0], [0, 0, 0]], float)
    for rigid in (np.ones_like(x) * [1, 2, 3], x @ spin.T):
        assert np.abs(k @ rigid.ravel()).max() < 1e-9 * np.abs(k).max()


def test_qm6_bends_exactly_where_the_trilinear_hexahedron_locks():
    """Pure bending of a 4:1:1 block, u_x = kz x z, u_y = -nu kz y z, u_z = -kz (x^2 + nu (z^2 -
    y^2)) / 2: stress sigma_xx = E kz z alone, energy E kz^2 / 2 int z^2 dV."""
    a, b, c = 0.04, 0.01, 0.01
    x = CUBE * [a, b, c] - [a / 2, b / 2, c / 2]
    kz = 0.1
    u = np.stack(
        [
            kz * x[:, 0] * x[:, 2],
            -NU * kz * x[:, 1] * x[:, 2],
            -kz * (x[:, 0] ** 2 + NU * (x[:, 2] ** 2 - x[:, 1] ** 2)) / 2,
        ],
        axis=1,
    )
    exact = E * kz**2 / 2 * a * b * c**3 / 12
    assert energy(qm6_stiffness(x[None], C)[0], u) == pytest.approx(exact, rel=1e-9)
    assert energy(element_stiffness(x[None], C, "full")[0], u) > 2 * exact


def test_the_spring_blocks_are_the_products_springs_and_volume_term():
    spec = {
        "name": "block",
        "material": {"youngs_modulus": E, "poisson_ratio": NU, "density": 1000.0},
        "geometry": {"type": "box", "size": [0.03, 0.02, 0.02], "nodes": [4, 3, 3]},
        "fixed": [{"face": "z-"}],
        "load_cases": [
            {"name": "push", "forces": [{"at": [0.03, 0.02, 0.02], "vector": [0, 1e-5, -2e-5]}]}
        ],
        "fpm": {"stiffness": "families+volume"},
    }
    problem = fpm.load_problem(spec)
    theta = np.array(continuum_start(problem)) * [1.3, 0.8, 50.0, 1.1]
    hexahedra = problem.solid.elements()
    units = spring_blocks(problem.solid.nodes[hexahedra])
    linear = solve(
        problem,
        cell_blocks(units, theta, None, np.ones(len(hexahedra), bool)),
        [problem.load_cases[0].dense(problem.n_nodes)],
    )[0]
    static = static_equilibrium(problem, k=theta).displacements
    assert np.abs(linear - static).max() < 1e-3 * np.abs(static).max()
