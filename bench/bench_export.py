"""The VTU export's time at 10^4 nodes (fpm.io.export): the FPM's field of every load and
validation case as its static equilibrium at the parameters (:func:`fpm.io.export.fpm_equilibria`)
against the dynamic runs to rest the export made before (:func:`fpm.io.export.fpm_displacements`,
timed on the load cases only, as it ran them).

The lattice: the soft-tissue box of the volume page (0.1 m, E 10 kPa, nu 0.45, the bottom held),
``NODES`` per side, pressed on top at four nodes and pulled sideways, with two validation cases;
the families+volume model at its continuum start (:func:`fpm.fitting.reduced.chain_start`), d
the critical-damping estimate of its static shapes
(:func:`fpm.fitting.damping.choice.critical_damping`) at dt 'auto'. The FEM reference is solved
first and handed to the export (as the service hands its stored one), so the export's own time is
what is measured.

Run: ``python -m bench export`` (writes bench/results/export.json).
"""

from __future__ import annotations

import copy
import json
import time
from pathlib import Path
from typing import Any

import numpy as np

import fpm
from bench import results
from fpm.dynamics.stability import time_step
from fpm.fitting.damping.choice import critical_damping
from fpm.fitting.reduced import chain_start
from fpm.io.export import Parameters, build_lattice, export, fpm_displacements, fpm_equilibria
from fpm.model.stiffness import model_stiffness, stiffness_dict, volume_stiffness

ROOT = Path(__file__).resolve().parents[1]
NODES = 22
"""Nodes per side: 22^3 = 10,648."""
OLD_PATH_NODES = 12
"""The dynamic runs are timed on this lattice (12^3 = 1,728 nodes): at 10^4 nodes they run for
many minutes."""


def spec(nodes: int) -> dict[str, Any]:
    base = json.loads((ROOT / "examples" / "paper-material-a.json").read_text())
    out = copy.deepcopy(base)
    out["name"] = f"soft box {nodes}^3"
    out["material"]["poisson_ratio"] = 0.45
    out["geometry"]["nodes"] = [nodes] * 3
    out["fpm"] = {"stiffness": "families+volume", "dt": "auto", "max_steps": "auto"}
    out["load_cases"] = [
        {"name": "press", "forces": [{"nearest": [0.05, 0.05, 0.1], "vector": [0, 0, -0.5]}]},
        {"name": "pull", "forces": [{"nearest": [0.1, 0.05, 0.1], "vector": [0.3, 0, 0]}]},
    ]
    out["validation_cases"] = [
        {
            "name": "press off centre",
            "forces": [{"nearest": [0.03, 0.06, 0.1], "vector": [0, 0, -0.4]}],
        },
        {"name": "push y", "forces": [{"nearest": [0.05, 0.0, 0.08], "vector": [0, 0.3, 0]}]},
    ]
    return out


def record_of(problem: Any) -> dict[str, Any]:
    """A parameter record at the continuum start, d the critical-damping estimate."""
    theta = chain_start(problem)
    stiffness = model_stiffness(problem, theta)
    equilibria, _, _ = fpm_equilibria(
        build_lattice(problem, Parameters.from_record(problem, _params(problem, theta, 1.0)))
    )
    d = critical_damping(problem, equilibria)
    return _params(problem, theta, d, time_step(problem, stiffness))


def _params(problem: Any, theta: list[float], d: float, dt: float = 1e-3) -> dict[str, Any]:
    return {
        "stiffness": stiffness_dict(problem, theta),
        "volume_stiffness": volume_stiffness(problem, theta),
        "d": float(d),
        "depth": None,
        "dt": float(dt),
    }


def main() -> None:
    problem = fpm.load_problem(spec(NODES))
    fem = fpm.solve_fem(problem).displacements
    record = record_of(problem)
    t0 = time.perf_counter()
    body = export(problem, record, "vtu", fem=fem)
    seconds = time.perf_counter() - t0
    cases = len(problem.load_cases) + len(problem.validation_cases)
    print(f"vtu at {problem.n_nodes:,} nodes, {cases} cases: {seconds:.2f} s, {len(body):,} bytes")
    results.record("export", "vtu", nodes=problem.n_nodes, cases=cases, seconds=seconds,
                   bytes=len(body), path="static equilibria")  # fmt: skip
    small = fpm.load_problem(spec(OLD_PATH_NODES))
    small_record = record_of(small)
    lattice = build_lattice(small, Parameters.from_record(small, small_record))
    t0 = time.perf_counter()
    fpm_equilibria(lattice)
    static = time.perf_counter() - t0
    t0 = time.perf_counter()
    _, steps, settled = fpm_displacements(lattice)
    dynamic = time.perf_counter() - t0
    print(
        f"at {small.n_nodes:,} nodes: static equilibria (load and validation cases) {static:.2f} s,"
        f" dynamic runs (load cases) {dynamic:.2f} s, {steps} steps, settled {settled}"
    )
    results.record("export", "fpm field", nodes=small.n_nodes, static_seconds=static,
                   dynamic_seconds=dynamic, dynamic_steps=steps,
                   settled=bool(np.all(settled)))  # fmt: skip


if __name__ == "__main__":
    main()
    for path in results.save_all("python -m bench.bench_export"):
        print(f"(results: {path.relative_to(results.ROOT)})")
