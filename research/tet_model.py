"""Models on the organ's own tetrahedra, measured beside the lattice.

``python -m research.tet_model ORGAN H [LEVEL ...]`` (ORGAN a key of
:data:`bench.tet_organ.ORGANS`, H the lattice spacing in m whose loads are used, LEVEL the
uniform 1-to-8 refinements of the organ's mesh to build each model on; default 1 2) prints, per
level, the relative discrepancy (paper Eq. 2's norm, %, per load case: the fitted cases, then
the validation cases) of three small-strain models whose nodes are the refined mesh's corners:

1. **linear tetrahedra** (4-node FEM) with the organ's E and nu: what the tetrahedra themselves
   can do, with nothing fitted;
2. **springs on the tetrahedra's edges and a volume term per tetrahedron**, the candidate
   measured (springs of Van Gelder's form k_e = a E sum_{t holding e} V_t / l_e^2, as Lloyd et
   al. 2007 derive for tetrahedra up to their constant, which the fit absorbs; the volume term
   0.5 kappa (V - V0)^2 / V0 per tetrahedron, as :mod:`fpm.model.volume` per hexahedron), a and
   kappa fitted on the fitted cases (Nelder-Mead on their logarithms, the mean of Eq. 2);
3. linear tetrahedra with E and nu fitted the same way: the best a linear tetrahedral model
   on those nodes does with two parameters.

The loads are the lattice's own (``surface_spec(ORGAN, H)``: every force at a surface point, spread
over its surface cell's lattice nodes, each lattice force over its hat, :mod:`fpm.fem.loads`),
applied to each mesh as the consistent loads of the same samples, so every model carries the very
load the lattice's reference carries. The reference is 10-node tetrahedra on the mesh refined twice
(the organs' reference), read at each model's nodes; held nodes are left out of the sums. Small
strain throughout: a fit of the FPM's nonlinear springs would agree to the loads' geometric
nonlinearity (a few % on the kidney, whose pull moves it 15 mm).

Measured: docs/notes/2026-11-30-organs-candidates.md (*The organ's own tetrahedra*).
"""

from __future__ import annotations

import sys
import time
from collections.abc import Callable
from typing import Any

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla
from scipy.optimize import minimize

EDGE_PAIRS = np.array([[0, 1], [0, 2], [0, 3], [1, 2], [1, 3], [2, 3]])


def gradients(x: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(T,) volumes, m^3, and (T, 4, 3) gradients of the barycentric coordinates, 1/m, of
    tetrahedra ``t`` (T, 4) on nodes ``x`` (N, 3)."""
    c = x[t]
    jac = np.transpose(c[:, 1:] - c[:, :1], (0, 2, 1))
    inverse = np.linalg.inv(jac)
    grads = np.concatenate([-inverse.sum(axis=1, keepdims=True), inverse], axis=1)
    return np.linalg.det(jac) / 6, grads


def assemble(t: np.ndarray, blocks: np.ndarray, n: int) -> sp.csr_matrix:
    """(3n, 3n) matrix of element ``blocks`` (T, 12, 12) on tetrahedra ``t`` (T, 4)."""
    dofs = (3 * t[:, :, None] + np.arange(3)).reshape(len(t), 12)
    rows = np.repeat(dofs, 12, axis=1).ravel()
    cols = np.tile(dofs, (1, 12)).ravel()
    return sp.csr_matrix((blocks.ravel(), (rows, cols)), shape=(3 * n, 3 * n))


def tetrahedra_stiffness(x: np.ndarray, t: np.ndarray, c: np.ndarray) -> sp.csr_matrix:
    """Linear 4-node tetrahedra with the (6, 6) elasticity matrix ``c``, Pa (Voigt order
    xx, yy, zz, xy, yz, xz as :func:`fpm.fem.elasticity.strain_displacement`)."""
    volume, g = gradients(x, t)
    b = np.zeros((len(t), 6, 12))
    for a in range(4):
        gx, gy, gz = g[:, a, 0], g[:, a, 1], g[:, a, 2]
        b[:, 0, 3 * a], b[:, 1, 3 * a + 1], b[:, 2, 3 * a + 2] = gx, gy, gz
        b[:, 3, 3 * a], b[:, 3, 3 * a + 1] = gy, gx
        b[:, 4, 3 * a + 1], b[:, 4, 3 * a + 2] = gz, gy
        b[:, 5, 3 * a], b[:, 5, 3 * a + 2] = gz, gx
    blocks = np.einsum("tik,ij,tjl->tkl", b, c, b) * volume[:, None, None]
    return assemble(t, blocks, len(x))


def volume_stiffness(x: np.ndarray, t: np.ndarray) -> sp.csr_matrix:
    """The volume term at kappa = 1 Pa, linearised at rest: 0.5 (V - V0)^2 / V0 per
    tetrahedron, so g g^T / V0 with g = dV/dx = V0 grad(lambda)."""
    volume, g = gradients(x, t)
    dv = (volume[:, None, None] * g).reshape(len(t), 12)
    return assemble(t, dv[:, :, None] * dv[:, None, :] / volume[:, None, None], len(x))


def spring_stiffness(x: np.ndarray, t: np.ndarray) -> tuple[sp.csr_matrix, int]:
    """Edge springs at E = 1 Pa, linearised at rest: k_e = sum_{t holding e} V_t / l_e^2,
    N/m per Pa; and the number of springs."""
    volume, _ = gradients(x, t)
    n = len(x)
    ends = np.sort(t[:, EDGE_PAIRS].reshape(-1, 2), axis=1)
    keys, inverse = np.unique(ends[:, 0] * n + ends[:, 1], return_inverse=True)
    a, b = keys // n, keys % n
    d = x[b] - x[a]
    length2 = (d * d).sum(axis=1)
    k = np.bincount(inverse, np.repeat(volume, 6)) / length2
    nn = d[:, :, None] * d[:, None, :] * (k / length2)[:, None, None]
    blocks = np.block([[nn, -nn], [-nn, nn]])
    dofs = np.concatenate([3 * a[:, None] + np.arange(3), 3 * b[:, None] + np.arange(3)], axis=1)
    rows, cols = np.repeat(dofs, 6, axis=1).ravel(), np.tile(dofs, (1, 6)).ravel()
    return sp.csr_matrix((blocks.ravel(), (rows, cols)), shape=(3 * n, 3 * n)), len(a)


def relative(u: np.ndarray, truth: np.ndarray, keep: np.ndarray) -> list[float]:
    """Eq. 2's relative discrepancy, % per case, of ``u`` against ``truth`` (L, N, 3) over
    the nodes ``keep``."""
    error = np.linalg.norm(u[:, keep] - truth[:, keep], axis=2).sum(axis=1)
    return (100 * error / np.linalg.norm(truth[:, keep], axis=2).sum(axis=1)).tolist()


def fmt(values: list[float]) -> str:
    return " / ".join(f"{v:.1f}" for v in values)


def measure(organ: str, spacing: float, levels: list[int]) -> None:
    import fpm
    from bench.tet_organ import surface_spec
    from fpm.fem.elasticity import constitutive_matrix
    from fpm.fem.loads import spread, tetrahedron_nodal_loads
    from fpm.fem.samples import (
        Samples,
        lattice_spacing,
        lattice_surface,
        tetrahedron_surface_samples,
        tetrahedron_volume_samples,
    )
    from fpm.fem.tet10 import (
        fixed_nodes,
        interpolate,
        quadratic_mesh,
        solve_p_multigrid,
        stiffness_matrix,
    )
    from fpm.model.tetrahedra import TetMesh

    spec = surface_spec(organ, spacing, refine=2)
    problem = fpm.load_problem(spec)
    material = problem.spec.material
    e, nu = material.youngs_modulus, material.poisson_ratio
    x0 = np.asarray(spec["reference"]["mesh"]["nodes"], dtype=float)
    t0 = np.asarray(spec["reference"]["mesh"]["tetrahedra"], dtype=np.int64)
    cases = problem.all_cases
    fitted = len(problem.load_cases)
    forces = np.stack([case.dense(problem.n_nodes) for case in cases])
    hexahedra = problem.solid.elements()
    assert hexahedra is not None  # the organ's lattice
    lattice, surface = problem.nodes, lattice_surface(hexahedra, problem.n_nodes)
    h_axes = lattice_spacing(lattice, hexahedra)

    def samples(x: np.ndarray, t: np.ndarray) -> Any:
        """The lattice's loads spread over the hats, sampled on the mesh (x, t)."""
        loaded = lattice[np.any(forces != 0, axis=(0, 2))]
        tet = TetMesh(x, t)
        where = tet.locate(lattice)
        return spread(
            lattice, surface, h_axes, forces,
            tetrahedron_surface_samples(tet, loaded, float(h_axes.max())),
            lambda: tetrahedron_volume_samples(tet, loaded, float(h_axes.max())),
            Samples(lattice, np.ones(len(lattice)), where.element, where.lam),
        )  # fmt: skip

    def refined(levels: int) -> tuple[np.ndarray, np.ndarray]:
        x, t = x0, t0
        for _ in range(levels):
            x, t = TetMesh(x, t).refine()[:2]
        return x, t

    start = time.perf_counter()
    mesh = quadratic_mesh(*refined(2))
    spread_loads = samples(mesh.nodes[: mesh.n_corners], mesh.corners)
    loads = tetrahedron_nodal_loads(
        mesh.elements, len(mesh.nodes), spread_loads.samples, spread_loads.forces
    )
    held = fixed_nodes(problem, mesh)
    used = np.zeros(len(mesh.nodes), dtype=bool)
    used[mesh.elements] = True
    c = constitutive_matrix(e, nu)
    u_ref, _, _ = solve_p_multigrid(
        stiffness_matrix(mesh, c), loads.reshape(len(cases), -1),
        np.repeat(~held & used, 3), mesh, "amg",
    )  # fmt: skip
    u_ref = u_ref.reshape(len(cases), -1, 3)
    print(
        f"{organ}, the loads of h = {1e3 * spacing:g} mm: reference 10-node tetrahedra on the "
        f"mesh refined twice, {len(mesh.nodes):,} nodes ({time.perf_counter() - start:.0f} s); "
        f"cases {' / '.join(c.name for c in cases)}",
        flush=True,
    )

    def one(level: int) -> None:
        """The three models on the mesh refined ``level`` times, printed."""
        x, t = refined(level)
        n = len(x)
        truth = interpolate(
            mesh, u_ref, TetMesh(mesh.nodes[: mesh.n_corners], mesh.corners).locate(x)
        )
        keep = ~fixed_nodes(problem, quadratic_mesh(x, t))[:n]
        free = np.repeat(keep, 3)
        on_mesh = samples(x, t)
        nodes = t[on_mesh.samples.element].ravel()
        f = np.zeros((len(cases), n, 3))
        for j in range(len(cases)):
            for i in range(3):
                weighted = on_mesh.forces[j, :, i, None] * on_mesh.samples.local
                f[j, :, i] = np.bincount(nodes, weighted.ravel(), n)

        def solve(k: sp.csr_matrix) -> np.ndarray:
            lu = spla.splu(k[free][:, free].tocsc())
            u = np.zeros((len(cases), 3 * n))
            for j in range(len(cases)):
                u[j, free] = lu.solve(f[j].ravel()[free])
            return u.reshape(len(cases), n, 3)

        def fit(model: Callable[[np.ndarray], sp.csr_matrix], p0: list[float]) -> Any:
            best = minimize(
                lambda p: float(np.mean(relative(solve(model(p)), truth, keep)[:fitted])),
                p0, method="Nelder-Mead", options={"xatol": 1e-3, "fatol": 1e-3, "maxiter": 120},
            )  # fmt: skip
            return best.x, relative(solve(model(best.x)), truth, keep)

        print(f"  {level} refinement(s): {n:,} nodes, {len(t):,} tetrahedra", flush=True)
        plain = relative(solve(tetrahedra_stiffness(x, t, c)), truth, keep)
        print(f"    linear tetrahedra, E and nu as given: {fmt(plain)}", flush=True)
        springs, count = spring_stiffness(x, t)
        volume = volume_stiffness(x, t)
        p, found = fit(lambda p: e * (np.exp(p[0]) * springs + np.exp(p[1]) * volume), [0.0, 0.0])
        print(
            f"    {count:,} springs + a volume term per tetrahedron (a {np.exp(p[0]):.3g}, "
            f"kappa {np.exp(p[1]):.3g} E): fitted {fmt(found[:fitted])}; validation "
            f"{fmt(found[fitted:])}",
            flush=True,
        )

        def poisson(q: float) -> float:
            return 0.5 / (1 + np.exp(-q))

        p, found = fit(
            lambda p: tetrahedra_stiffness(
                x, t, constitutive_matrix(e * np.exp(p[0]), poisson(p[1]))
            ),
            [0.0, float(np.log(nu / (0.5 - nu)))],
        )
        print(
            f"    linear tetrahedra, E x {np.exp(p[0]):.3g} and nu {poisson(p[1]):.3f} fitted: "
            f"fitted {fmt(found[:fitted])}; validation {fmt(found[fitted:])}",
            flush=True,
        )

    for level in levels:
        one(level)


def main(argv: list[str] | None = None) -> None:
    args = sys.argv[1:] if argv is None else argv
    if len(args) < 2:
        raise SystemExit("usage: python -m research.tet_model ORGAN H [LEVEL ...]")
    measure(args[0], float(args[1]), [int(a) for a in args[2:]] or [1, 2])


if __name__ == "__main__":
    main()
