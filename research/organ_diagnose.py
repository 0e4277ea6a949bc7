"""Where an organ's error is (docs/notes/2026-11-29-organs-what-the-nodes-hold.md).

``python -m research.organ_diagnose ORGAN H REFINE`` (an organ of
:data:`bench.tet_organ.ORGANS`, h in m, REFINE the refinements of its reference): the organ's
row of ``python -m bench.bench_refine organs`` at spacing h against a REFINE-times refined
reference (quicker than 'auto'), and where its error is (:func:`diagnose`), with
:func:`near_field_imposed`: what a lattice refined only near the loads could at best do.
"""

from __future__ import annotations

import sys
from typing import Any

from bench.bench_refine import fmt


def diagnose(organ: str, spacing: float, refine: int) -> None:
    """Where the error of an organ's row (``bench.bench_refine``'s part 4) is, printed:
    ``organ`` at ``spacing`` (m) against a ``refine``-times refined reference (quicker than 'auto'),
    fitted (families+volume, then the per-cell field); per fitted case the share of the relative
    discrepancy from the nodes within 1, 2 and 3 h of the load; and the lattice's own hexahedra as
    an FEM continuum (8-node, B-bar) with the same nodal forces, as they are and refined once,
    against the reference (% per case)."""
    import copy

    import numpy as np

    import fpm
    from bench.tet_organ import surface_spec
    from fpm.fem.levels import relative_change
    from fpm.fitting.cost import StaticCost
    from fpm.fitting.reference import reference_displacements
    from fpm.model.stiffness import fitted_theta

    spec = surface_spec(organ, spacing, refine=refine)
    problem = fpm.load_problem(spec)
    reference = fpm.solve_fem(problem)
    truth = reference_displacements(reference, problem)
    for mode in ("families+volume", "field"):
        spec["fpm"]["stiffness"] = mode
        fitted = fpm.load_problem(spec)
        result = fpm.calibrate(fitted, reference=reference)
        print(
            f"{organ} {1e3 * spacing:g} mm, {fitted.n_nodes} nodes, {mode}: fitted "
            f"{fmt(result.fit.relative_discrepancy)}, validation "
            f"{fmt(result.fit.validation_relative_discrepancy)} %",
            flush=True,
        )
        if mode == "field":
            break
        theta = fitted_theta(fitted, result.parameters)
        near_field_imposed(fitted, theta, reference, spacing)
        static = StaticCost(fitted, truth, None)
        for j, case in enumerate(fitted.load_cases):
            u = static.displacements(theta, j).displacements
            err = np.linalg.norm(u - truth[j], axis=1)
            total = np.linalg.norm(truth[j], axis=1).sum()
            near = np.linalg.norm(
                fitted.nodes[:, None] - fitted.nodes[case.nodes][None], axis=2
            ).min(axis=1)
            shares = [
                f"{int((near <= r * spacing).sum())} nodes within {r:g} h: "
                f"{100 * err[near <= r * spacing].sum() / total:.1f}"
                for r in (1.01, 2.01, 3.01)
            ]
            print(f"  {case.name}: {100 * err.sum() / total:.1f}% of which " + "; ".join(shares))
    # As they are, under the lattice's own nodal loads (the FEM reference on the hexahedra
    # as given would load the forces at their nodes, a deeper dimple than the hat traction
    # the tetrahedra carry: 26-29% at 6.5 mm instead of 9-12%, a bound that was wrong).
    from fpm.fem.elasticity import constitutive_matrix, element_stiffness
    from research import surface_cells

    coords = problem.solid.nodes[problem.solid.elements()]
    material = problem.spec.material
    c = constitutive_matrix(material.youngs_modulus, material.poisson_ratio)
    loads = [case.dense(problem.n_nodes) for case in problem.load_cases]
    gap = surface_cells.judged(
        problem, element_stiffness(coords, c, "selective"), loads, list(truth)
    )
    print(f"  the lattice's hexahedra as a continuum (B-bar, its loads): {fmt(gap)} %")
    hexahedra = copy.deepcopy(spec)
    del hexahedra["reference"]["mesh"]
    hexahedra["reference"]["refine"] = 1  # refined, the reference spreads the loads: the same
    hexahedra["fpm"]["stiffness"] = "families+volume"
    refined = fpm.solve_fem(fpm.load_problem(hexahedra))
    gap = relative_change(reference.displacements, refined.displacements)
    print(f"  the lattice's hexahedra as a continuum, refined once: {fmt(gap)} %")


NEAR = 3.01
"""What :func:`near_field_imposed` calls near a load: lattice nodes within this many h of a
loaded node."""


def near_field_imposed(problem: Any, theta: Any, reference: Any, spacing: float) -> None:
    """Whether a lattice refined only near the loads could do: per case (fitted, then
    validation), the relative discrepancy (% of the case's whole displacement sum) of the
    lattice nodes further than NEAR h from a loaded node, as the fitted lattice solves the
    case, and with the reference's displacements imposed on the nodes within (a perfect near
    field: what any refinement there could at best give), then with the parameters refitted
    for that far field (Nelder-Mead on their logarithms). Linear: the lattice's tangent at rest
    (:class:`fpm.dynamics.spring_system.SpringSystem`), the loads being small."""
    import numpy as np
    import scipy.sparse.linalg as spla
    from scipy.optimize import minimize

    from fpm.dynamics.spring_system import SpringSystem
    from fpm.model.stiffness import model_stiffness

    truth = np.asarray(reference.displacements)
    forces = np.stack([case.dense(problem.n_nodes) for case in problem.all_cases])
    free = np.flatnonzero(~problem.fixed)
    system = SpringSystem(problem, free)
    rest = np.zeros((len(free), 3))
    local = np.full(problem.n_nodes, -1)
    local[free] = np.arange(len(free))

    def dofs(nodes: np.ndarray) -> np.ndarray:
        return (3 * local[nodes][:, None] + np.arange(3)).ravel()

    def far_field(log_theta: np.ndarray, imposed: bool) -> list[float]:
        stiffness = model_stiffness(problem, list(np.exp(log_theta)))
        k = system.tangent(rest, system.parameters(stiffness)).tocsr()
        out = []
        for j, f in enumerate(forces):
            loaded = problem.nodes[np.any(f != 0, axis=1)]
            gap = np.linalg.norm(problem.nodes[:, None] - loaded[None], axis=2).min(axis=1)
            near = gap <= NEAR * spacing
            far = np.flatnonzero(~near & ~problem.fixed)
            if imposed:
                held = np.flatnonzero(near & ~problem.fixed)
                rhs = f[far].ravel() - k[dofs(far)][:, dofs(held)] @ truth[j, held].ravel()
                u = spla.spsolve(k[dofs(far)][:, dofs(far)].tocsc(), rhs).reshape(-1, 3)
            else:
                u = spla.spsolve(k.tocsc(), f[free].ravel()).reshape(-1, 3)[local[far]]
            error = np.linalg.norm(u - truth[j, far], axis=1).sum()
            out.append(100 * error / np.linalg.norm(truth[j], axis=1).sum())
        return out

    start = np.log(np.asarray(theta, dtype=float))
    fitted = len(problem.load_cases)
    best = minimize(
        lambda p: float(np.mean(far_field(p, True)[:fitted])), start, method="Nelder-Mead",
        options={"maxiter": 200, "xatol": 1e-3, "fatol": 1e-3},
    )  # fmt: skip
    print(f"  beyond {NEAR:.0f} h of the loads, % of each case (fitted, then validation):")
    print(f"    as the lattice solves it:          {fmt(far_field(start, False))}")
    print(f"    the reference imposed within:      {fmt(far_field(start, True))}")
    print(f"    ... and the parameters refitted:   {fmt(far_field(best.x, True))}", flush=True)


if __name__ == "__main__":
    if len(sys.argv) != 4:
        raise SystemExit("usage: python -m research.organ_diagnose ORGAN H REFINE")
    diagnose(sys.argv[1], float(sys.argv[2]), int(sys.argv[3]))
