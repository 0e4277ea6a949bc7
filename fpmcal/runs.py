"""``fpmcal simulate``, ``equilibrium`` and ``fem``: one FPM run, one static equilibrium, the FEM
reference."""

from __future__ import annotations

import argparse
import sys

from .inputs import _emit, _load, _warn
from .progress import _fem_levels


def cmd_simulate(args: argparse.Namespace) -> None:
    from fpm.dynamics.simulation import simulate
    from fpm.dynamics.stability import auto_time_step, stable_time_step
    from fpm.model.stiffness import model_stiffness

    problem = _load(args.spec)
    k = args.k[0] if len(args.k) == 1 else args.k
    stiffness = model_stiffness(problem, k)
    dt = args.dt if args.dt is not None else problem.spec.fpm.dt
    dt = auto_time_step(problem, stiffness) if dt == "auto" else float(dt)
    limit = stable_time_step(problem, stiffness)
    given = " ".join(f"{v:g}" for v in args.k)
    advice = f"the lattice's stability estimate for k = {given} is dt <= {limit:.3g} s"
    if dt > limit:
        _warn([f"dt = {dt:.3g} s: {advice}; the run may diverge (lower --dt)"])
    result = simulate(
        problem,
        k=k,
        d=args.d,
        depth=args.depth,
        load_case=args.load_case,
        dt=dt,
        max_steps=args.max_steps,
    )
    if result.diverged:
        _warn(
            [
                result.message
                + f" (dt = {dt:.3g} s: {advice}, and the node-by-node step needs some damping: "
                "lower --dt or raise --d)"
            ]
        )
    _emit(result.to_dict(), args.output)


def cmd_equilibrium(args: argparse.Namespace) -> None:
    from dataclasses import asdict

    from fpm.dynamics.equilibrium import static_equilibrium

    k = args.k[0] if len(args.k) == 1 else args.k
    result = static_equilibrium(
        _load(args.spec), k=k, depth=args.depth, load_case=args.load_case
    ).check()
    data = asdict(result)
    data["displacements"] = result.displacements.tolist()
    _emit(data, args.output)


def cmd_fem(args: argparse.Namespace) -> None:
    from fpm.fem.reference import solve_fem
    from fpm.fitting.diagnosis import UnitsError, check_reference
    from fpm.fitting.reference import resolution_notes

    problem = _load(args.spec)
    result = solve_fem(problem, progress=_fem_levels)
    if result.element == "tet10":
        mesh = problem.spec.reference.mesh
        size = f" ({len(mesh.tetrahedra)} tetrahedra)" if mesh is not None else ""
        print(
            f"{problem.spec.name}: the reference solved on reference.mesh{size} with 10-node "
            f"tetrahedra, read at the {problem.n_nodes} lattice nodes (what the fit compares)",
            file=sys.stderr,
        )
    try:
        _warn(check_reference(problem, result.displacements))
    except UnitsError as e:
        _warn([str(e)])
    if result.estimated_error is not None:
        names = [case.name for case in problem.all_cases]
        print(
            f"{problem.spec.name}: the reference's estimated error per case, % ("
            + (
                f"change from its last refinement, {result.refinements} in all"
                if result.refinements
                else "its change under one refinement with the forces spread"
            )
            + "): "
            + ", ".join(f"{n} {e:.2f}" for n, e in zip(names, result.estimated_error, strict=True)),
            file=sys.stderr,
        )
    _warn(resolution_notes(problem, result))
    _emit(result.to_dict(), args.output)
