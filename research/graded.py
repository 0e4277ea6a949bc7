"""What a lattice graded from the surface inwards could give: a bound, measured.

``python -m research.graded ORGAN H [BANDS]`` (an organ of :data:`bench.tet_organ.ORGANS`, h in
m, BANDS a comma list of node layers, default ``1,2``; about 4 minutes at 2,600 nodes, most of
it the reference and the calibration): the organ as ``spec from-mesh`` makes it with the
defaults at spacing h, its refine-auto reference and its calibration (as
:mod:`research.surface_cells`), then the same lattice solved linearly (the springs' tangent at
rest, the calibration's four parameters, then those refitted) with its interior coarsened to
2h: the nodes within BAND layers of the surface (graph distance through cells) and the nodes of
the 2h grid stay, every other node follows the trilinear field of the 2h cell it lies in
(:func:`coarse_constraint`). That is a lattice of h at the surface and 2h inside, its hanging
nodes constrained (a Galerkin restriction of the fine lattice: conforming, and a little stiffer
inside than 2h cells of springs would be). Each row names its node count (the nodes kept) and
its relative discrepancy per case, %, at the kept nodes, fitted then validation, against the
reference; BAND 99 keeps every node (the fine lattice itself). Two placements of the 2h grid
(parities) per band.

The bound says whether building such a lattice (transition cells or hanging nodes through the
perturbed lists, the export, the runtime, the browser and the SOFA scene) would reach the
goal at its node count; it is not a model the product has.
"""

from __future__ import annotations

import sys
from typing import Any

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spl

from research import surface_cells


def grid_indices(nodes: np.ndarray, hexahedra: np.ndarray, h: float) -> np.ndarray:
    """(N, 3) int each node's index on the voxel grid of spacing ``h`` (m) its lattice came
    from: the interior nodes (unmoved by the conforming) by position, the surface nodes by
    their place in a cell (corner bits of :data:`research.surface_cells.CORNER_BITS`) next to
    a node whose index is known."""
    from fpm.fem.samples import lattice_surface

    bits = np.array(surface_cells.CORNER_BITS)
    inner = ~lattice_surface(hexahedra, len(nodes))
    index = np.zeros((len(nodes), 3), dtype=np.int64)
    origin = nodes[inner][0]
    steps = (nodes[inner] - origin) / h
    index[inner] = np.round(steps).astype(np.int64)
    if np.abs(steps - index[inner]).max() > 1e-6:
        raise ValueError(f"the interior nodes are not on a grid of spacing {h:g} m")
    known = inner.copy()
    while not known.all():
        some = known[hexahedra].any(axis=1) & ~known[hexahedra].all(axis=1)
        if not some.any():
            raise ValueError("a part of the lattice has no interior node")
        for cell in np.flatnonzero(some):
            corners = hexahedra[cell]
            first = int(np.flatnonzero(known[corners])[0])
            base = index[corners[first]] - bits[first]
            index[corners] = base + bits
            known[corners] = True
    if len(np.unique(index, axis=0)) < len(index):
        raise ValueError("two nodes fall on one grid point")
    return index


def surface_depth(hexahedra: np.ndarray, surface: np.ndarray, most: int) -> np.ndarray:
    """(N,) each node's number of cell-neighbour steps from the lattice's surface
    (``surface`` (N,) bool), capped at ``most`` + 1."""
    n = len(surface)
    pairs = np.repeat(hexahedra, 8, axis=1).ravel(), np.tile(hexahedra, (1, 8)).ravel()
    neighbours = sp.csr_matrix((np.ones(len(pairs[0])), pairs), shape=(n, n))
    depth = np.where(surface, 0, most + 1)
    for d in range(1, most + 1):
        reached = (neighbours @ (depth == d - 1).astype(float)) > 0
        depth[(depth == most + 1) & reached] = d
    return depth


def coarse_constraint(
    index: np.ndarray, kept: np.ndarray, fixed: np.ndarray, parity: np.ndarray
) -> sp.csr_matrix:
    """(N, M) T with u = T q: the M kept free nodes (``kept`` & ~``fixed``) are their own
    unknowns, each other free node the trilinear interpolation of the 2h cell it lies in
    (the grid's nodes whose ``index`` (N, 3) has ``parity`` (3,) along every axis), a fixed
    node zero. Raises if such a cell's corner is not kept or not in the lattice."""
    n = len(index)
    free = kept & ~fixed
    column = np.full(n, -1)
    column[free] = np.arange(int(free.sum()))
    lookup = {tuple(row): i for i, row in enumerate(index)}
    rows, cols, values = list(np.flatnonzero(free)), list(column[free]), [1.0] * int(free.sum())
    for i in np.flatnonzero(~kept & ~fixed):
        options = [
            [(index[i, a], 1.0)]
            if (index[i, a] - parity[a]) % 2 == 0
            else [(index[i, a] - 1, 0.5), (index[i, a] + 1, 0.5)]
            for a in range(3)
        ]
        for (ia, wa), (ib, wb), (ic, wc) in (
            (x, y, z) for x in options[0] for y in options[1] for z in options[2]
        ):
            j = lookup[(ia, ib, ic)]
            if not kept[j]:
                raise ValueError(f"node {i}'s 2h corner {j} is not kept")
            if not fixed[j]:
                rows.append(i)
                cols.append(column[j])
                values.append(wa * wb * wc)
    return sp.csr_matrix((values, (rows, cols)), shape=(n, int(free.sum())))


def judged(
    problem: Any, blocks: np.ndarray, t: sp.csr_matrix, kept: np.ndarray, loads: list, truth: list
) -> list[float]:
    """The relative discrepancy, % per load, at the ``kept`` nodes, of K u = f solved for
    u = T q (K from the cells' ``blocks`` (H, 24, 24), T from :func:`coarse_constraint`)."""
    from fpm.fem.levels import relative_change

    hexahedra = problem.solid.elements()
    n = problem.n_nodes
    dofs = (3 * hexahedra[:, :, None] + np.arange(3)).reshape(len(hexahedra), 24)
    rows, cols = np.repeat(dofs, 24, axis=1).ravel(), np.tile(dofs, (1, 24)).ravel()
    k = sp.csr_matrix((blocks.ravel(), (rows, cols)), shape=(3 * n, 3 * n))
    t3 = sp.kron(t, sp.identity(3), format="csr")
    lu = spl.splu((t3.T @ k @ t3).tocsc())
    solved = [(t3 @ lu.solve(t3.T @ f.ravel())).reshape(n, 3)[kept] for f in loads]
    return relative_change(np.stack(solved), np.stack([q[kept] for q in truth]))


def main() -> None:
    from scipy.optimize import minimize

    import fpm
    from bench.tet_organ import surface_spec
    from fpm.fem.samples import lattice_surface

    organ, spacing = sys.argv[1], float(sys.argv[2])
    bands = [int(b) for b in (sys.argv[3] if len(sys.argv) > 3 else "1,2").split(",")]
    problem = fpm.load_problem(surface_spec(organ, spacing))
    result, theta, truth, loads, units = surface_cells.calibrated_linear(
        problem, fpm.solve_fem(problem)
    )
    hexahedra = problem.solid.elements()
    index = grid_indices(problem.solid.nodes, hexahedra, spacing)  # (problem.h: shortest spring)
    surface = lattice_surface(hexahedra, problem.n_nodes)
    depth = surface_depth(hexahedra, surface, max(bands))
    held = index[np.argmin(np.abs(problem.solid.nodes[:, 2])), 2] % 2  # a 2h plane there
    fitted = len(problem.load_cases)
    every = np.ones(len(hexahedra), dtype=bool)

    def text(values: list[float]) -> str:
        """'fitted; validation | worst validation', %."""
        return (
            " / ".join(f"{v:.1f}" for v in values[:fitted])
            + "; "
            + " / ".join(f"{v:.1f}" for v in values[fitted:])
            + f" | {max(values[fitted:]):.1f}"
        )

    calibrated = [*result.fit.relative_discrepancy, *result.fit.validation_relative_discrepancy]
    print(
        f"{organ} at {1e3 * spacing:g} mm, {problem.n_nodes} nodes, calibrated: {text(calibrated)}"
    )
    print("| band | parity | nodes kept | springs, calibrated four | worst | refitted | worst |")
    print("|---|---|---|---|---|---|---|")
    for band in [99, *bands]:
        for parity in ((0, 0, held), (1, 1, held)) if band != 99 else ((0, 0, held),):
            grid = np.all((index - np.array(parity)) % 2 == 0, axis=1)
            kept = (depth <= band) | grid
            t = coarse_constraint(index, kept, problem.fixed, np.array(parity))

            def solved(scale: np.ndarray, t: sp.csr_matrix = t, kept: np.ndarray = kept) -> list:
                blocks = surface_cells.cell_blocks(units, theta * scale, None, every)
                return judged(problem, blocks, t, kept, loads, truth)

            found = minimize(
                lambda y: float(np.mean(solved(np.exp(y))[:fitted])),
                np.zeros(4),
                method="Nelder-Mead",
                options={
                    "initial_simplex": np.vstack([np.zeros(4), 0.3 * np.eye(4)]),
                    "xatol": 0.01,
                    "fatol": 0.01,
                    "maxfev": 60,
                },
            )
            again = solved(np.exp(found.x))
            print(
                f"| {'all' if band == 99 else band} | {parity[:2]} | {int(kept.sum()):,} | "
                f"{text(solved(np.ones(4)))} | {text(again)} |",
                flush=True,
            )


if __name__ == "__main__":
    main()
