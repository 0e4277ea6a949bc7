"""A reference that says how far it is from converged (``reference.refine``, fpm/fem/refine.py).

Both organs are :func:`bench.tet_organ.organ_spec`: E 5 kPa, nu 0.45, the lower half held (its
plane z = 0 a layer of the mesh's nodes), two fitted cases (a press on top, a lateral pull) and
three validation cases, each force spread over its node's share of the solid.

1. ``refine: "auto"`` on the 5,000-tetrahedron organ (cells (12, 9, 8): 5,184 tetrahedra, h =
   10 mm), in its own process: per level the 10-node mesh's nodes, the change at the lattice
   nodes per case and the seconds; the reference's estimated error; the whole ``solve_fem``
   against :data:`AUTO_GOAL` s, and its peak memory.
2. The few-hundred-tetrahedron organ (cells (5, 4, 4): 480 tetrahedra, as public organ meshes
   come) at h = 5 mm, ``refine: "auto"``: the reported error per case (goal: at most
   :data:`ERROR_GOAL` %), then ``fpm.calibrate`` (families+volume, two-stage) against that
   reference: the validation cases' relative discrepancy (goal: at most :data:`VALIDATION_GOAL`
   % each); beside it the same fit against the mesh as given with point loads (``refine: 0``,
   the reference before this option), judged against its own reference and against the
   refined one. Both lattices (:data:`LATTICES`): the voxels and the conforming lattice, each
   with its own reference (the loads are spread over its own nodes' patches), and each
   lattice's hexahedra as a continuum against its reference (:func:`continuum_gap`: what the
   geometry alone costs).
3. The voxel check: the same organ's lattice with its hexahedra as the reference (no mesh):
   each case's estimated error, the cases a press on a single voxel leaves unresolved.

``python -m bench.bench_refine auto|fit|check`` runs one part.
"""

from __future__ import annotations

import json
import resource
import subprocess
import sys
import time
from typing import Any

AUTO_CELLS = (12, 9, 8)
"""The 5,000-tetrahedron organ (5,184 tetrahedra)."""
FIT_CELLS = (5, 4, 4)
"""The few-hundred-tetrahedron organ (480 tetrahedra)."""
FIT_SPACING = 0.005
"""Its lattice spacing, m (4,409 lattice nodes)."""
AUTO_GOAL = 60.0
"""Seconds for refine 'auto' on the 5,000-tetrahedron organ, end to end, on 2 cores."""
ERROR_GOAL = 2.0
"""The reported reference error of refine 'auto', %, every case."""
VALIDATION_GOAL = 10.0
"""The fit's relative discrepancy on every validation case against the refined reference, %."""
LATTICES = ("voxels", "conforming")
"""The organ's lattices: its voxels (as ``spec from-mesh`` makes it), and the voxels with
their surface nodes moved onto the mesh's surface (:func:`bench.tet_organ.conform`)."""


def fmt(values: list[float] | None) -> str:
    return "-" if values is None else " / ".join(f"{v:.2f}" for v in values)


def run_auto() -> dict[str, Any]:
    """refine 'auto' on the 5,000-tetrahedron organ, in this process."""
    import fpm
    import fpm.fem.refine  # imported before the clock starts
    from bench.tet_organ import organ_spec

    spec = organ_spec(AUTO_CELLS, refine="auto")
    problem = fpm.load_problem(spec)
    t0 = time.perf_counter()
    result = fpm.solve_fem(problem)
    return {
        "tetrahedra": len(spec["reference"]["mesh"]["tetrahedra"]),
        "lattice_nodes": problem.n_nodes,
        "cases": [case.name for case in problem.all_cases],
        "levels": result.levels,
        "estimated_error": result.estimated_error,
        "notes": result.notes,
        "total": time.perf_counter() - t0,
        "peak_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
    }


def auto() -> list[str]:
    print(f"\n1. refine 'auto' on the {AUTO_CELLS} organ, in its own process")
    out = subprocess.run(
        [sys.executable, "-m", "bench.bench_refine", "auto-case"],
        capture_output=True,
        text=True,
        check=True,
    )
    row = json.loads(out.stdout.strip().splitlines()[-1])
    print(
        f"{row['tetrahedra']} tetrahedra, {row['lattice_nodes']} lattice nodes; cases: "
        + ", ".join(row["cases"])
    )
    print(f"{'refinements':>11} {'FEM nodes':>10} {'seconds':>8}   change from the level before, %")
    for level in row["levels"]:
        print(
            f"{level['refinements']:>11} {level['fem_nodes']:>10,} {level['seconds']:>8.1f}   "
            f"{fmt(level['change'])}"
        )
    print(f"estimated error, %: {fmt(row['estimated_error'])}")
    for note in row["notes"]:
        print(f"note: {note}")
    print(
        f"total {row['total']:.1f} s (goal {AUTO_GOAL:.0f} s), peak {row['peak_mb']:.0f} MB",
        flush=True,
    )
    failures = []
    if row["total"] > AUTO_GOAL:
        failures.append(f"refine auto, {row['tetrahedra']} tetrahedra: {row['total']:.1f} s")
    return failures


def fit() -> list[str]:
    import fpm
    from bench.tet_organ import organ_spec

    print(f"\n2. The {FIT_CELLS} organ: refine 'auto', then a calibration against it")
    failures = []
    rows = {}
    for lattice, refine in (("voxels", "auto"), ("voxels", 0), ("conforming", "auto")):
        spec = organ_spec(FIT_CELLS, FIT_SPACING, refine=refine, conforming=lattice != "voxels")
        problem = fpm.load_problem(spec)
        t0 = time.perf_counter()
        reference = fpm.solve_fem(problem)
        t_fem = time.perf_counter() - t0
        t0 = time.perf_counter()
        result = fpm.calibrate(problem, reference=reference)
        rows[lattice, refine] = (reference, result, t_fem, time.perf_counter() - t0)
    print(f"{len(organ_spec(FIT_CELLS)['reference']['mesh']['tetrahedra'])} tetrahedra")
    for lattice in LATTICES:
        reference = rows[lattice, "auto"][0]
        print(
            f"{lattice} lattice: {'refinements':>11} {'FEM nodes':>10} {'seconds':>8}   change, %"
        )
        for level in reference.levels:
            print(
                f"{'':<{len(lattice) + 10}}{level['refinements']:>11} {level['fem_nodes']:>10,} "
                f"{level['seconds']:>8.1f}   {fmt(level['change'])}"
            )
        for note in reference.notes:
            print(f"note: {note}")
    print(
        f"{'lattice':<12}{'fitted against':<18}{'judged against':<16}{'fitted cases %':>16}"
        f"{'validation cases %':>24}{'FEM + fit s':>14}"
    )
    for (lattice, refine), (_, res, tf, tc) in rows.items():
        label = "refine auto" if refine == "auto" else "as given, points"
        print(
            f"{lattice:<12}{label:<18}{'itself':<16}{fmt(res.relative_discrepancy):>16}"
            f"{fmt(res.validation_relative_discrepancy):>24}{tf:>7.1f} + {tc:4.1f}"
        )
    problem = fpm.load_problem(organ_spec(FIT_CELLS, FIT_SPACING, refine=0))
    fitted, validation = judged(problem, rows["voxels", 0][1], rows["voxels", "auto"][0])
    print(f"{'voxels':<12}{'as given, points':<18}{'refine auto':<16}{fmt(fitted):>16}"
          f"{fmt(validation):>24}")  # fmt: skip
    print(
        "The hexahedra of each lattice as a continuum (8-node, refined twice, the loads spread) "
        "against the refined tetrahedra, % per case (the lattice's geometry alone):"
    )
    for lattice in LATTICES:
        print(f"{lattice:<12}{fmt(continuum_gap(lattice, rows[lattice, 'auto'][0]))}", flush=True)
    for lattice in LATTICES:
        result = rows[lattice, "auto"][1]
        print(
            f"{lattice}: reported reference error, %: {fmt(result.reference_error)}; validation "
            f"{fmt(result.validation_reference_error)} (goal <= {ERROR_GOAL:g}%); fitted "
            f"{result.stiffness}, kappa {result.volume_stiffness:.4g} Pa",
            flush=True,
        )
        worst = max(
            [*(result.reference_error or [99.0]), *(result.validation_reference_error or [])]
        )
        if worst > ERROR_GOAL:
            failures.append(f"{lattice}: reported reference error {worst:.2f}% > {ERROR_GOAL:g}%")
        highest = max(result.validation_relative_discrepancy)
        if highest > VALIDATION_GOAL:
            failures.append(f"{lattice}: validation {highest:.1f}% > {VALIDATION_GOAL:g}%")
    return failures


def continuum_gap(lattice: str, reference: Any) -> list[float]:
    """Relative difference, % per case, of the lattice's own hexahedra as an elastic solid
    (8-node, selective, ``refine: 2``: the loads spread, the second refinement within about
    2% of the first) from the tetrahedral ``reference`` at the lattice nodes: how far the
    lattice's geometry alone (the voxels' staircase) is from the organ's."""
    import fpm
    from bench.tet_organ import organ_spec
    from fpm.fem.refine import relative_change

    spec = organ_spec(FIT_CELLS, FIT_SPACING, refine=2, conforming=lattice != "voxels")
    del spec["reference"]["mesh"]
    hexahedra = fpm.solve_fem(fpm.load_problem(spec))
    return relative_change(reference.displacements, hexahedra.displacements)


def judged(problem: Any, result: Any, reference: Any) -> tuple[list[float], list[float]]:
    """Relative discrepancy, %, of the fit ``result`` of ``problem`` (its static equilibria)
    against another ``reference``: the load cases, the validation cases."""
    import numpy as np

    from fpm.fitting.cost import StaticCost, discrepancies
    from fpm.fitting.validation import reference_displacements, validate
    from fpm.model.stiffness import fitted_theta

    theta = fitted_theta(problem, result)
    truth = reference_displacements(reference, problem)
    static = StaticCost(problem, truth, None)
    solved = np.stack([static.displacements(theta, j).displacements for j in range(len(truth))])
    return (
        discrepancies(problem, solved, truth).relative,
        validate(problem, reference, theta, None).relative,
    )


def check() -> list[str]:
    import fpm
    from bench.tet_organ import organ_spec

    print(f"\n3. The voxel check: the {FIT_CELLS} organ's lattice, its hexahedra the reference")
    spec = organ_spec(FIT_CELLS, FIT_SPACING, refine=None)
    del spec["reference"]
    problem = fpm.load_problem(spec)
    t0 = time.perf_counter()
    result = fpm.solve_fem(problem)
    seconds = time.perf_counter() - t0
    for name, error in zip(
        [c.name for c in problem.all_cases], result.estimated_error or [], strict=False
    ):
        flag = "  (above 5%: not resolved)" if error > 5 else ""
        print(f"{name:<20}{error:>8.2f} %{flag}")
    print(f"{problem.n_nodes} lattice nodes, check on {result.levels[-1]['fem_nodes']:,} nodes, "
          f"{seconds:.1f} s (reference and check)", flush=True)  # fmt: skip
    return []


def main() -> None:
    failures = auto() + fit() + check()
    print("goals: " + ("all met" if not failures else "MISSED " + "; ".join(failures)))


if __name__ == "__main__":
    parts = {"auto": auto, "fit": fit, "check": check}
    if sys.argv[1:] == ["auto-case"]:
        print(json.dumps(run_auto()))
    elif len(sys.argv) == 2 and sys.argv[1] in parts:
        failures = parts[sys.argv[1]]()
        print("goals: " + ("all met" if not failures else "MISSED " + "; ".join(failures)))
    else:
        main()
