"""The ``vtu`` export: the lattice and the FPM's and FEM's fields on it, for ParaView.

The hexahedra and the springs (VTK_LINE cells) with, per load case and per validation case,
the FPM's displacements (its static equilibrium at the parameters, where its runs settle:
:func:`fpm_equilibria`) and the FEM's, the error between them and the perturbed list's layer
as point data (written by meshio; ParaView reads it).
"""

from __future__ import annotations

import tempfile
from pathlib import Path
from typing import Any

import numpy as np

from ...model.problem import Problem
from ...model.stiffness import model_stiffness
from .lattice import Lattice, _layers


def fpm_displacements(lattice: Lattice) -> tuple[np.ndarray, list[int], list[bool]]:
    """(L, N, 3) displacements of the FPM run from rest to settling at the parameters, per load
    case, with the steps taken and whether each settled (the result's last dynamic run)."""
    from ...dynamics.simulation import simulate

    p, runs = lattice.params, []
    theta = p.theta(lattice.problem)
    for j in range(len(lattice.problem.load_cases)):
        runs.append(simulate(lattice.problem, k=theta, d=p.d, depth=p.depth, load_case=j, dt=p.dt))
    return (
        np.stack([r.displacements for r in runs]),
        [r.steps for r in runs],
        [r.settled for r in runs],
    )


def fpm_equilibria(lattice: Lattice) -> tuple[np.ndarray, np.ndarray, list[str]]:
    """(L, N, 3) and (V, N, 3) the FPM's static equilibria at the parameters, m, of the load
    cases and of the validation cases: where its runs settle (d and dt decide only how fast;
    a run stops within its settle distance of them), as the fit's figures and its validation
    are taken. The cases are solved on one thread per core, each on a static solver of its own
    (the same bits as one after another). Also a note per case whose equilibrium did not
    converge."""
    import os
    from concurrent.futures import ThreadPoolExecutor

    from ...dynamics.eigen import single_threaded_blas
    from ...dynamics.equilibrium import StaticSolver

    problem, p = lattice.problem, lattice.params
    stiffness = model_stiffness(problem, p.theta(problem))
    checked = problem.validation_problem()
    cases = [(part, j) for part in (problem, checked) for j in range(len(part.load_cases))]

    def one(case: tuple[Problem, int]) -> Any:
        part, j = case
        return StaticSolver(part).solve(j, stiffness, p.depth)

    with single_threaded_blas(), ThreadPoolExecutor(min(len(cases), os.cpu_count() or 1)) as pool:
        solved = list(pool.map(one, cases))
    notes = [
        f"{part.load_cases[j].name}: no static equilibrium ({eq.message})"
        for (part, j), eq in zip(cases, solved, strict=True)
        if not eq.converged
    ]
    every = np.array([eq.displacements for eq in solved]).reshape(-1, problem.n_nodes, 3)
    n = len(problem.load_cases)
    return every[:n], every[n:], notes


def vtu_bytes(
    lattice: Lattice,
    fem: np.ndarray,
    fpm: np.ndarray,
    validation: tuple[np.ndarray, np.ndarray] | None = None,
) -> bytes:
    """The ``vtu`` export: hexahedra and springs with point data per load case (1-based
    suffixes in load case order): ``fpm_displacement_J``, ``fem_displacement_J``, ``error_J``
    (|FPM - FEM|, m) and ``layer_J`` (perturbed-list layer, -1 outside); with ``validation``
    ((V, N, 3) FEM and FPM displacements of the validation cases, m) the same per validation
    case, prefixed ``validation_``; ``mass`` and ``fixed`` per node; ``stiffness``,
    ``rest_length`` and ``family`` per cell (-1 / 0 on the hexahedra); ``volume_stiffness``
    (kappa, Pa) per hexahedron (0 on the springs and without the volume term). Written by
    meshio in its binary (base64, zlib) layout."""
    import meshio

    problem = lattice.problem
    n, hexes, springs = problem.n_nodes, lattice.hexahedra, problem.solid.springs
    point_data: dict[str, np.ndarray] = {
        "mass": problem.solid.masses,
        "fixed": problem.fixed.astype(np.int32),
    }
    parts = [("", lattice.layers, fem, fpm)]
    if validation is not None:
        parts.append(("validation_", _layers(problem.validation_problem(), lattice), *validation))
    for prefix, every, fem_u, fpm_u in parts:
        for j, layers in enumerate(every):
            layer = np.full(n, -1, dtype=np.int32)
            for i, nodes in enumerate(layers):
                layer[nodes] = i
            point_data[f"{prefix}fpm_displacement_{j + 1}"] = fpm_u[j]
            point_data[f"{prefix}fem_displacement_{j + 1}"] = fem_u[j]
            point_data[f"{prefix}error_{j + 1}"] = np.linalg.norm(fpm_u[j] - fem_u[j], axis=1)
            point_data[f"{prefix}layer_{j + 1}"] = layer
    cell_data = {
        "stiffness": [np.zeros(len(hexes)), lattice.stiffness],
        "rest_length": [np.zeros(len(hexes)), problem.rest_lengths],
        "family": [
            np.full(len(hexes), -1, dtype=np.int32),
            problem.solid.families.astype(np.int32),
        ],
        "volume_stiffness": [
            np.zeros(len(hexes)) if lattice.volume is None else lattice.volume,
            np.zeros(len(springs)),
        ],
    }
    mesh = meshio.Mesh(
        problem.nodes,
        [("hexahedron", hexes), ("line", springs.astype(np.int64))],
        point_data=point_data,
        cell_data=cell_data,
    )
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "lattice.vtu"
        meshio.write(path, mesh, file_format="vtu")
        return path.read_bytes()


def vtu_export(lattice: Lattice, fem: np.ndarray | None = None) -> bytes:
    """The ``vtu`` export of ``lattice``: ``fem`` the (L, N, 3) FEM displacements, then (V, N,
    3) those of the validation cases if it holds them (None: solved now); the FPM's are its
    static equilibria (:func:`fpm_equilibria`)."""
    problem = lattice.problem
    if fem is None:
        from ...fem.reference import solve_fem

        fem = solve_fem(problem).displacements
    fem = np.asarray(fem, dtype=float)
    fpm, checked, _ = fpm_equilibria(lattice)
    n, v = len(problem.load_cases), len(problem.validation_cases)
    validation = (fem[n : n + v], checked) if v and len(fem) >= n + v else None
    return vtu_bytes(lattice, fem[:n], fpm, validation)
