"""FEM reference speed and memory: a cube of n^3 nodes, face z=0 fixed, one point load.

Both linear solvers are timed where the sparse LU is affordable; ``*`` marks the one
:func:`fpm.solve_fem` picks (``method="auto"``). Each case runs in its own subprocess so that
its peak memory (``ru_maxrss``, which includes the ~150 MB of the interpreter and libraries) is
its own. Columns: assembly = element stiffness + block assembly of K; solve = everything else
in the :func:`fpm.solve_fem` call (held check, Dirichlet reduction, factorisation or AMG setup,
solve); total = the whole call. Goals on a 2-core machine: 30^3 nodes in 5 s, 50^3 in 30 s and
4 GB, residual ||K u - f|| / ||f|| <= 1e-8.

The sparse LU runs only up to :data:`DIRECT_UP_TO` nodes a side: its fill-in grows fast on 3-D
meshes (measured once at 30^3: 67 s and 2.5 GB, against 3 s and 0.4 GB for AMG).

Then the neo-Hookean reference (``material.model: "neo-hookean"``, :mod:`fpm.fem.hyperelastic`)
against the linear one on the same :data:`MODEL_SIDE`^3 cube and load, each model in its own
process, :data:`MODEL_REPEATS` times (the fastest run counts): goals at most
:data:`MODEL_GOALS` times the linear solve's time and peak memory. ``python -m bench.bench_fem
models`` runs only this part.

Last, the tetrahedral reference (:mod:`fpm.fem.tet10`) of a 50,000-tetrahedron organ
(:func:`bench.organ.ellipsoid_tetrahedra`), end to end (10-node mesh, assembly, solve, reading at
the lattice nodes), against a goal of :data:`TET10_GOAL` s; ``python -m bench.bench_fem tet10``
runs only this part.
"""

from __future__ import annotations

import json
import resource
import sys
import time

from bench import child_json

SIDES = (10, 20, 30, 40, 50)
DIRECT_UP_TO = 20
"""Largest side (nodes) at which the sparse LU is timed too."""
GOALS = {30: (5.0, None), 50: (30.0, 4096.0)}
"""Nodes a side -> (seconds, MB or None) that the default method must meet."""
MODEL_SIDE = 20
"""Nodes a side of the cube on which the neo-Hookean and linear references are compared."""
MODEL_REPEATS = 2
"""Processes per model in that comparison; the fastest counts."""
MODEL_GOALS = (10.0, 2.0)
"""Neo-Hookean over linear: (time, peak memory) ratios not to exceed."""
LOCKING_RATIOS = (0.3, 0.45, 0.49)
"""Poisson's ratios of the locking table."""
LOCKING_GOAL = 0.07
"""Selective hexahedra at nu = 0.49: relative gap to the triquadratic ones not to exceed."""


def cube_spec(n: int) -> dict:
    """A 0.1 m cube of n^3 nodes (E = 10 kPa, nu = 0.45), z=0 fixed, 1 N on the top face."""
    h = 0.1 / (n - 1)
    middle = (n - 1) // 2 * h
    return {
        "material": {"youngs_modulus": 1e4, "poisson_ratio": 0.45, "density": 1040.0},
        "geometry": {"type": "box", "size": [0.1, 0.1, 0.1], "nodes": [n, n, n]},
        "fixed": [{"face": "z-"}],
        "load_cases": [{"forces": [{"at": [middle, middle, 0.1], "vector": [0, 0, 1.0]}]}],
        "reference": {"refine": 0},  # the solver on the hexahedra as given (no check)
    }


def run_case(n: int, method: str) -> dict:
    """Time one case in this process; returns the table row."""
    import fpm
    from fpm.fem.elasticity import constitutive_matrix
    from fpm.fem.reference import stiffness_matrix

    problem = fpm.load_problem(cube_spec(n))
    hexahedra = problem.solid.elements()
    assert hexahedra is not None
    t0 = time.perf_counter()
    stiffness_matrix(problem.nodes, hexahedra, constitutive_matrix(1e4, 0.45))
    assembly = time.perf_counter() - t0
    t0 = time.perf_counter()
    result = fpm.solve_fem(problem, method=method)
    total = time.perf_counter() - t0
    return {
        "n": n,
        "unknowns": 3 * int((~problem.fixed).sum()),
        "method": result.method,
        "assembly": assembly,
        "solve": total - assembly,
        "total": total,
        "peak_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
        "residual": max(result.residuals),
    }


def run_model(n: int, model: str) -> dict:
    """Time one ``solve_fem`` of the n^3 cube with material ``model`` in this process."""
    import fpm
    import fpm.fem.reference  # imported before the clock starts, as in run_case

    spec = cube_spec(n)
    spec["material"]["model"] = model
    # 2x2x2 hexahedra for both models: the selective neo-Hookean solid does not follow this
    # point load past 75% of it at n = 20 (docs/physics.md, *Large deformation reference*).
    spec["reference"] = {"integration": "full", "refine": 0}
    problem = fpm.load_problem(spec)
    problem.solid.elements()
    t0 = time.perf_counter()
    result = fpm.solve_fem(problem)
    return {
        "model": model,
        "method": result.method,
        "total": time.perf_counter() - t0,
        "peak_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
        "residual": max(result.residuals),
        "steps": result.load_steps,
        "newton": result.newton_iterations,
    }


def compare_models() -> list[str]:
    """The neo-Hookean reference against the linear one (module docstring); returns failures."""
    n = MODEL_SIDE
    print(
        f"\nneo-Hookean against linear reference, {n}^3 nodes, same cube and load, "
        f"best of {MODEL_REPEATS} processes each"
    )
    print(
        f"{'model':>12} {'method':>7} {'total s':>8} {'peak MB':>8} {'residual':>9}  "
        "Newton iterations per load step"
    )
    rows = {}
    for model in ("linear", "neo-hookean"):
        runs = []
        for _ in range(MODEL_REPEATS):
            runs.append(child_json("bench.bench_fem", "model", str(n), model))
        row = min(runs, key=lambda r: r["total"])
        row["peak_mb"] = max(r["peak_mb"] for r in runs)
        rows[model] = row
        newton = ", ".join(str(steps) for steps in row["newton"]) or "-"
        print(
            f"{model:>12} {row['method']:>7} {row['total']:>8.2f} {row['peak_mb']:>8.0f} "
            f"{row['residual']:>9.1e}  {newton}",
            flush=True,
        )
    time_ratio = rows["neo-hookean"]["total"] / rows["linear"]["total"]
    memory_ratio = rows["neo-hookean"]["peak_mb"] / rows["linear"]["peak_mb"]
    failures = []
    if time_ratio > MODEL_GOALS[0]:
        failures.append(f"neo-Hookean {time_ratio:.1f}x the linear time > {MODEL_GOALS[0]:g}x")
    if memory_ratio > MODEL_GOALS[1]:
        failures.append(f"neo-Hookean {memory_ratio:.2f}x the linear memory > {MODEL_GOALS[1]:g}x")
    print(
        f"{'ratio':>12} {'':>7} {time_ratio:>7.1f}x {memory_ratio:>7.2f}x   goals: <= "
        f"{MODEL_GOALS[0]:g}x time, <= {MODEL_GOALS[1]:g}x peak memory: "
        + ("met" if not failures else "MISSED")
    )
    return failures


def compare_locking() -> list[str]:
    """The locking table (module docstring); returns failures."""
    from pathlib import Path

    import numpy as np

    import fpm
    from fpm.fem.elasticity import constitutive_matrix
    from fpm.fem.hex27 import solve_hex27

    root = Path(__file__).resolve().parents[1]
    base = json.loads((root / "examples" / "paper-material-a.json").read_text())
    base["load_cases"] = base["load_cases"][:1]

    def gap(u: np.ndarray, reference: np.ndarray) -> float:
        return float(
            np.linalg.norm(u - reference, axis=-1).sum() / np.linalg.norm(reference, axis=-1).sum()
        )

    print(
        "\nvolumetric locking: paper cube, 0.25 N per pulled node, relative gap (%) to the "
        "triquadratic hexahedron (hex27, 3x3x3 points) on the same grid"
    )
    print(
        f"{'nu':>5} {'full':>7} {'selective':>10} {'NH full':>8} {'NH selective':>13} "
        f"{'hex27 s':>8}   (NH: neo-Hookean at 1e-3 of the load, scaled back)"
    )
    failures = []
    for nu in LOCKING_RATIOS:
        spec = json.loads(json.dumps(base))
        spec["material"]["poisson_ratio"] = nu
        row = {}
        for integration in ("full", "selective"):
            spec["reference"] = {"integration": integration, "refine": 0}
            row[integration] = fpm.solve_fem(fpm.load_problem(spec)).displacements[0]
        for integration in ("full", "selective"):
            small = json.loads(json.dumps(spec))
            small["reference"] = {"integration": integration}
            small["material"]["model"] = "neo-hookean"
            for force in small["load_cases"][0]["forces"]:
                force["vector"] = [1e-3 * v for v in force["vector"]]
            u = fpm.solve_fem(fpm.load_problem(small)).displacements[0]
            row[f"neo-hookean {integration}"] = 1e3 * u
        problem = fpm.load_problem(spec)
        hexahedra = problem.solid.elements()
        assert hexahedra is not None
        forces = problem.load_cases[0].dense(len(problem.nodes))[None]
        t0 = time.perf_counter()
        c = constitutive_matrix(spec["material"]["youngs_modulus"], nu)
        u27 = solve_hex27(problem.nodes, hexahedra, problem.fixed, c, forces)[0]
        seconds = time.perf_counter() - t0
        gaps = {name: 100 * gap(u, u27) for name, u in row.items()}
        print(
            f"{nu:>5} {gaps['full']:>7.2f} {gaps['selective']:>10.2f} "
            f"{gaps['neo-hookean full']:>8.2f} {gaps['neo-hookean selective']:>13.2f} "
            f"{seconds:>8.1f}",
            flush=True,
        )
        if nu == 0.49 and gaps["selective"] > 100 * LOCKING_GOAL:
            failures.append(f"selective at nu 0.49: {gaps['selective']:.1f}% > 7%")
    print(
        f"goal: selective within {100 * LOCKING_GOAL:g}% of hex27 at nu 0.49: "
        + ("met" if not failures else "MISSED")
    )
    return failures


TET10_H = 0.0039
"""Node spacing of the tetrahedral organ (:func:`bench.organ.ellipsoid_tetrahedra`): about
51,000 tetrahedra (71,000 nodes of the 10-node mesh)."""
TET10_LATTICE = 0.005
"""Lattice spacing of the organ's spec (about 4,600 lattice nodes)."""
TET10_GOAL = 60.0
"""Seconds for the 50,000-tetrahedron reference, end to end, on 2 cores."""


def run_tet10() -> dict:
    """Time the tet10 reference of the tetrahedral organ in this process: the spec as
    ``spec_from_mesh`` makes it (probe force on top, own weight, bottom centimetre fixed), then
    one ``solve_fem``: 10-node mesh, assembly, solve, reading at the lattice nodes."""
    import meshio

    import fpm
    import fpm.fem.tet10  # imported before the clock starts
    from bench.organ import ellipsoid_tetrahedra
    from fpm.io.meshes import spec_from_mesh

    nodes, tets = ellipsoid_tetrahedra(TET10_H)
    bottom = nodes[:, 2].min()
    spec, _ = spec_from_mesh(
        meshio.Mesh(nodes, [("tetra", tets)]),
        fix=[f"box:-1,-1,-1:1,1,{bottom + 0.01}"],
        forces=["nearest:0,0,0.04:0,0,-0.02"],
        youngs_modulus=5e3,
        poisson_ratio=0.45,
        density=1040.0,
        spacing=TET10_LATTICE,
        lattice="voxels",  # the figure this bench records (a conforming lattice: the same FEM)
    )
    spec["fpm"]["gravity"] = [0.0, 0.0, -9.81]
    spec["reference"]["refine"] = 0  # the 10-node solve on the mesh as given (bench_refine: auto)
    problem = fpm.load_problem(spec)
    t0 = time.perf_counter()
    result = fpm.solve_fem(problem)
    total = time.perf_counter() - t0
    return {
        "tetrahedra": len(tets),
        "lattice_nodes": problem.n_nodes,
        "method": result.method,
        "total": total,
        "peak_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
        "residual": max(result.residuals),
    }


def compare_tet10() -> list[str]:
    """The tet10 reference of a 50,000-tetrahedron organ, in its own process: one row, time
    against :data:`TET10_GOAL`."""
    row = child_json("bench.bench_fem", "tet10-case")
    print(
        f"{'tetrahedra':>10} {'lattice':>8} {'method':>7} {'total s':>8} {'goal s':>7} "
        f"{'ratio':>6} {'peak MB':>8} {'residual':>9}"
    )
    print(
        f"{row['tetrahedra']:>10} {row['lattice_nodes']:>8} {row['method']:>7} "
        f"{row['total']:>8.1f} {TET10_GOAL:>7.0f} {row['total'] / TET10_GOAL:>6.2f} "
        f"{row['peak_mb']:>8.0f} {row['residual']:>9.1e}",
        flush=True,
    )
    failures = []
    if row["total"] > TET10_GOAL:
        failures.append(f"tet10 organ: {row['total']:.1f} s > {TET10_GOAL} s")
    if row["residual"] > 1e-8:
        failures.append(f"tet10 organ: residual {row['residual']:.1e} > 1e-8")
    return failures


def main() -> None:
    from fpm.fem.linear_solver import choose_method

    print(
        f"{'nodes':>7} {'unknowns':>9} {'method':>8} {'assembly s':>11} {'solve s':>8} "
        f"{'total s':>8} {'peak MB':>8} {'residual':>9}"
    )
    failures = []
    for n in SIDES:
        for method in ("direct", "amg") if n <= DIRECT_UP_TO else ("amg",):
            row = child_json("bench.bench_fem", str(n), method)
            chosen = choose_method(row["unknowns"]) == method
            label = method + ("*" if chosen else "")
            print(
                f"{n:>4}^3 {row['unknowns']:>9} {label:>8} {row['assembly']:>11.2f} "
                f"{row['solve']:>8.2f} {row['total']:>8.2f} {row['peak_mb']:>8.0f} "
                f"{row['residual']:>9.1e}",
                flush=True,
            )
            seconds, megabytes = GOALS.get(n, (None, None)) if chosen else (None, None)
            if row["residual"] > 1e-8:
                failures.append(f"{n}^3 {row['method']}: residual {row['residual']:.1e} > 1e-8")
            if seconds is not None and row["total"] > seconds:
                failures.append(f"{n}^3: {row['total']:.1f} s > {seconds} s")
            if megabytes is not None and row["peak_mb"] > megabytes:
                failures.append(f"{n}^3: {row['peak_mb']:.0f} MB > {megabytes} MB")
    print("* = the method solve_fem picks at that size")
    failures += compare_models()
    failures += compare_locking()
    failures += compare_tet10()
    print("goals: " + ("all met" if not failures else "MISSED " + "; ".join(failures)))


if __name__ == "__main__":
    if len(sys.argv) == 4 and sys.argv[1] == "model":
        print(json.dumps(run_model(int(sys.argv[2]), sys.argv[3])))
    elif len(sys.argv) == 3:
        print(json.dumps(run_case(int(sys.argv[1]), sys.argv[2])))
    elif sys.argv[1:] == ["models"]:
        failures = compare_models()
        print("goals: " + ("all met" if not failures else "MISSED " + "; ".join(failures)))
    elif sys.argv[1:] == ["tet10-case"]:
        print(json.dumps(run_tet10()))
    elif sys.argv[1:] == ["tet10"]:
        failures = compare_tet10()
        print("goals: " + ("all met" if not failures else "MISSED " + "; ".join(failures)))
    elif sys.argv[1:] == ["locking"]:
        failures = compare_locking()
        print("goals: " + ("all met" if not failures else "MISSED " + "; ".join(failures)))
    else:
        main()
