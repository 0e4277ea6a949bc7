"""Where the conforming lattice's springs lose: its own cells as finite elements.

``python -m research.surface_cells ORGAN H [--no-refit]`` (an organ of
:data:`bench.tet_organ.ORGANS`, h in m; about 4-5 minutes at 2,000 nodes, most of it the
reference and the calibration): the organ as ``spec from-mesh`` makes it with the
defaults, its refine-auto reference and its calibration (:func:`bench.bench_refine.run_organ`'s
spec), then the same lattice nodes, fixed nodes and nodal loads (the lattice's own: the hat
shares of ``fpm.loads``) under linear models, each judged like the calibration (relative
discrepancy per case, %, against the reference at the lattice nodes, fitted cases then
validation cases):

- ``springs``: the calibration's four parameters (families+volume; where the calibration
  returns the per-cell field, its four-parameter fit without the field), the tangent at rest
  (the loads are small: at 6.5 mm it reproduces the calibration's figures within 0.2 points);
- ``FEM full``, ``FEM B-bar``, ``FEM QM6``: every cell an 8-node hexahedron of the material's
  E and nu (trilinear with 2x2x2 Gauss points; B-bar with the mean dilatation, as the
  reference's hexahedra; Wilson-Taylor incompatible modes, :func:`qm6_stiffness`): what the
  lattice's nodes can hold under these loads;
- ``surface full`` / ``surface QM6``: the springs and volume term kept in the interior cells
  (the calibrated parameters), the cells with a corner on the surface replaced by that element;
  ``... refitted``: the four parameters refitted (Nelder-Mead on the fitted cases' mean) with
  the surface element in place.

The model solved is the one every row shares: ``K u = f`` on the free nodes, K assembled from
per-cell 24 x 24 blocks (:func:`cell_blocks`).
"""

from __future__ import annotations

import itertools
import sys
from typing import Any

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spl

CORNER_BITS = [
    (0, 0, 0),
    (1, 0, 0),
    (1, 1, 0),
    (0, 1, 0),
    (0, 0, 1),
    (1, 0, 1),
    (1, 1, 1),
    (0, 1, 1),
]
"""A hexahedron's corners (VTK order) as (r, s, t) bits."""
PAIRS = list(itertools.combinations(range(8), 2))
"""The 28 corner pairs of a cell: 12 edges, 12 face diagonals, 4 body diagonals."""
FAMILY = [sum(CORNER_BITS[a][k] != CORNER_BITS[b][k] for k in range(3)) for a, b in PAIRS]
"""Each pair's family: 1 axis (edge), 2 face diagonal, 3 body diagonal."""
SHARE = {1: 0.25, 2: 0.5, 3: 1.0}
"""The share of its family's k a cell gives each of its springs (fpm.model.shares)."""


def qm6_stiffness(coords: np.ndarray, c: np.ndarray) -> np.ndarray:
    """(H, 24, 24) K_e, N/m, of Wilson-Taylor's incompatible-modes hexahedron for ``coords``
    (H, 8, 3), m, and C (6, 6), Pa: the trilinear field plus the bubbles 1 - xi_a^2 per
    component, their gradients taken with the centre's Jacobian scaled by det J0 / det J
    (Taylor's correction, so that uniform strains are reproduced: the patch test), 2x2x2 Gauss
    points, the 9 bubble amplitudes condensed out. Exact for pure bending of a rectangular
    block, and free of volumetric locking as nu nears 1/2, where the trilinear element locks."""
    from fpm.fem.elasticity import GAUSS_POINTS, jacobians, physical_gradients, strain_displacement

    j0 = jacobians(coords, np.zeros(3))
    inverse0, det0 = np.linalg.inv(j0), np.linalg.det(j0)
    kcc = np.zeros((len(coords), 24, 24))
    kci = np.zeros((len(coords), 24, 9))
    kii = np.zeros((len(coords), 9, 9))
    for point in GAUSS_POINTS:
        grad, det = physical_gradients(coords, point)
        bc = strain_displacement(grad)
        bubble = np.diag(-2.0 * np.asarray(point, dtype=float))  # d(1 - xi_a^2)/dxi_b
        gi = np.einsum("ka,hba->hkb", bubble, inverse0) * (det0 / det)[:, None, None]
        bi = strain_displacement(gi)
        w = det[:, None, None]
        kcc += np.einsum("hpa,pq,hqb->hab", bc, c, bc) * w
        kci += np.einsum("hpa,pq,hqb->hab", bc, c, bi) * w
        kii += np.einsum("hpa,pq,hqb->hab", bi, c, bi) * w
    return kcc - kci @ np.linalg.solve(kii, np.transpose(kci, (0, 2, 1)))


def spring_blocks(coords: np.ndarray) -> np.ndarray:
    """(H, 4, 24, 24) per cell the tangent at rest of its springs, one block per family with
    unit k times the cell's share (N/m per N/m), and of its volume term with unit kappa
    (kappa / V0 g g^T, g = dV/dx: N/m per Pa)."""
    from fpm.fem.elasticity import GAUSS_POINTS, physical_gradients

    out = np.zeros((len(coords), 4, 24, 24))
    for e, (a, b) in enumerate(PAIRS):
        n = coords[:, b] - coords[:, a]
        n /= np.linalg.norm(n, axis=1)[:, None]
        nn = SHARE[FAMILY[e]] * np.einsum("hi,hj->hij", n, n)
        for (i, si), (j, sj) in itertools.product(((a, 1.0), (b, -1.0)), repeat=2):
            out[:, FAMILY[e] - 1, 3 * i : 3 * i + 3, 3 * j : 3 * j + 3] += si * sj * nn
    g = np.zeros((len(coords), 24))
    volume = np.zeros(len(coords))
    for point in GAUSS_POINTS:
        grad, det = physical_gradients(coords, point)
        g += grad.reshape(len(coords), 24) * det[:, None]
        volume += det
    out[:, 3] = np.einsum("ha,hb->hab", g, g) / volume[:, None, None]
    return out


def cell_blocks(
    units: np.ndarray, theta: np.ndarray, element: np.ndarray | None, cells: np.ndarray
) -> np.ndarray:
    """(H, 24, 24) each cell's block: ``element`` (H, 24, 24) where ``cells`` (H,) bool, else
    the springs and volume term at ``theta`` (k_axis, k_face, k_body N/m, kappa Pa), from
    ``units`` (H, 4, 24, 24), the cells' :func:`spring_blocks`."""
    blocks = np.einsum("f,hfab->hab", np.asarray(theta, dtype=float), units)
    if element is not None:
        blocks[cells] = element[cells]
    return blocks


def solve(problem: Any, blocks: np.ndarray, loads: list[np.ndarray]) -> list[np.ndarray]:
    """(N, 3) displacements, m, per load (N, 3) N, of K assembled from ``blocks`` (H, 24, 24)
    on the lattice's cells, its fixed nodes held."""
    hexahedra = problem.solid.elements()
    n = problem.n_nodes
    dofs = (3 * hexahedra[:, :, None] + np.arange(3)).reshape(len(hexahedra), 24)
    rows = np.repeat(dofs, 24, axis=1).ravel()
    cols = np.tile(dofs, (1, 24)).ravel()
    k = sp.csr_matrix((blocks.ravel(), (rows, cols)), shape=(3 * n, 3 * n))
    free = np.repeat(~problem.fixed, 3)
    lu = spl.splu(k[free][:, free].tocsc())
    out = []
    for f in loads:
        u = np.zeros(3 * n)
        u[free] = lu.solve(f.ravel()[free])
        out.append(u.reshape(n, 3))
    return out


def judged(problem: Any, blocks: np.ndarray, loads: list, truth: list) -> list[float]:
    """The relative discrepancy, % per load, of :func:`solve` against ``truth`` (N, 3) per load
    (:func:`fpm.fem.levels.relative_change`: 100 sum_i |u_i - q_i| / sum_i |q_i|)."""
    from fpm.fem.levels import relative_change

    return relative_change(np.stack(solve(problem, blocks, loads)), np.stack(truth))


def refit(
    problem: Any,
    units: np.ndarray,
    theta: np.ndarray,
    element: np.ndarray,
    cells: np.ndarray,
    loads: list,
    truth: list,
) -> np.ndarray:
    """The four parameters refitted with ``element`` in ``cells`` (the other cells' blocks from
    ``units``, :func:`cell_blocks`): Nelder-Mead on log theta, the fitted cases' mean relative
    discrepancy, from ``theta``."""
    from scipy.optimize import minimize

    fitted = len(problem.load_cases)

    def cost(y: np.ndarray) -> float:
        blocks = cell_blocks(units, theta * np.exp(y), element, cells)
        return float(np.mean(judged(problem, blocks, loads[:fitted], truth[:fitted])))

    simplex = np.vstack([np.zeros(4), 0.3 * np.eye(4)])
    found = minimize(
        cost,
        np.zeros(4),
        method="Nelder-Mead",
        options={"initial_simplex": simplex, "xatol": 0.01, "fatol": 0.01, "maxfev": 80},
    )
    return theta * np.exp(found.x)


def calibrated_linear(
    problem: Any, reference: Any
) -> tuple[Any, np.ndarray, list, list, np.ndarray]:
    """The calibration of ``problem`` against ``reference`` and what the linear models need:
    (result, theta (4,) its four parameters, the reference (N, 3) per fitted then validation
    case, the nodal loads (N, 3) N of those cases, the lattice's cells' :func:`spring_blocks`
    (H, 4, 24, 24), which :func:`cell_blocks` takes)."""
    import fpm
    from fpm.fitting.reference import reference_displacements, validation_reference

    result = fpm.calibrate(problem, reference=reference)
    theta = np.array([*result.parameters.stiffness.values(), result.parameters.volume_stiffness])
    truth = [
        *reference_displacements(reference, problem),
        *validation_reference(reference, problem),
    ]
    cases = [*problem.load_cases, *problem.validation_problem().load_cases]
    loads = [case.dense(problem.n_nodes) for case in cases]
    units = spring_blocks(problem.solid.nodes[problem.solid.elements()])
    return result, theta, truth, loads, units


def rows(problem: Any, reference: Any, refitted: bool = True) -> list[tuple[str, list[float]]]:
    """The table's rows for ``problem`` and its FEM ``reference``, as (model, % per case);
    ``refitted`` False leaves out the refitted rows (each refit solves the lattice up to 80
    times: minutes at 15,000 nodes)."""
    from fpm.fem.elasticity import constitutive_matrix, element_stiffness
    from fpm.fem.samples import lattice_surface

    result, theta, truth, loads, units = calibrated_linear(problem, reference)
    hexahedra = problem.solid.elements()
    coords = problem.solid.nodes[hexahedra]
    material = problem.spec.material
    c = constitutive_matrix(material.youngs_modulus, material.poisson_ratio)
    every = np.ones(len(hexahedra), dtype=bool)
    surface = lattice_surface(hexahedra, problem.n_nodes)[hexahedra].any(axis=1)
    full = element_stiffness(coords, c, "full")
    qm6 = qm6_stiffness(coords, c)

    def judged_all(blocks: np.ndarray) -> list[float]:
        return judged(problem, blocks, loads, truth)

    out = [
        (
            "calibrated (nonlinear, as reported)",
            [*result.fit.relative_discrepancy, *result.fit.validation_relative_discrepancy],
        ),
        (
            "springs, the four parameters (linear)",
            judged_all(cell_blocks(units, theta, None, every)),
        ),
        ("FEM full", judged_all(full)),
        ("FEM B-bar", judged_all(element_stiffness(coords, c, "selective"))),
        ("FEM QM6", judged_all(qm6)),
    ]
    for name, element in (("full", full), ("QM6", qm6)):
        out.append((f"surface {name}", judged_all(cell_blocks(units, theta, element, surface))))
        if not refitted:
            continue
        again = refit(problem, units, theta, element, surface, loads, truth)
        out.append(
            (f"surface {name} refitted", judged_all(cell_blocks(units, again, element, surface)))
        )
    errors = [*(result.reference.error or []), *(result.reference.validation_error or [])]
    field = result.parameters.field
    print(
        f"{problem.n_nodes} nodes, {len(hexahedra)} cells, {int(surface.sum())} with a corner "
        f"on the surface; reference error {' / '.join(f'{e:.1f}' for e in errors)} %; "
        f"per-cell field returned: {bool(field and field.returned)}"
    )
    return out


def main() -> None:
    import fpm
    from bench.tet_organ import surface_spec

    organ, spacing = sys.argv[1], float(sys.argv[2])
    refitted = "--no-refit" not in sys.argv[3:]
    problem = fpm.load_problem(surface_spec(organ, spacing))
    print(f"{organ} at {1e3 * spacing:g} mm:", end=" ")
    table = rows(problem, fpm.solve_fem(problem), refitted)
    print("| model | fitted, % | validation, % | worst validation |")
    print("|---|---|---|---|")
    fitted = len(problem.load_cases)
    for name, values in table:
        print(
            f"| {name} | {' / '.join(f'{v:.1f}' for v in values[:fitted])} | "
            f"{' / '.join(f'{v:.1f}' for v in values[fitted:])} | {max(values[fitted:]):.1f} |"
        )


if __name__ == "__main__":
    main()
