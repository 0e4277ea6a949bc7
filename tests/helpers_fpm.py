"""Spec builders for the spec, geometry, perturbed-list and FPM tests.

Each builder returns a plain dict (the JSON a user would write), so a test can break one field
of it and see what :func:`fpm.load_problem` says.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from pydantic import ValidationError

import fpm

MATERIAL: dict[str, Any] = {"youngs_modulus": 1.0e4, "poisson_ratio": 0.45, "density": 1040.0}
PAPER_MODEL: dict[str, Any] = {"stiffness": "single", "dt": 1e-3}
"""The paper's model (one k, springs only) at a 1 ms step: what the spring-lattice tests test;
a builder's ``fpm_settings`` override it."""


def box_spec(
    nodes: tuple[int, int, int],
    spacing: float | tuple[float, float, float] = 0.01,
    *,
    connectivity: str = "full",
    fixed: list[dict[str, Any]] | None = None,
    forces: list[dict[str, Any]] | None = None,
    fpm_settings: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """A box lattice of ``nodes`` nodes per axis, ``spacing`` m apart, origin at 0.

    Default: face z- fixed, one force of 0.01 N along +z on the first node of face z+.
    """
    h = np.broadcast_to(np.asarray(spacing, dtype=float), (3,))
    size = [float(h[a] * (nodes[a] - 1)) for a in range(3)]
    if forces is None:
        forces = [{"at": [0.0, 0.0, size[2]], "vector": [0.0, 0.0, 0.01]}]
    return {
        "name": "test box",
        "material": dict(MATERIAL),
        "geometry": {
            "type": "box",
            "size": size,
            "nodes": list(nodes),
            "connectivity": connectivity,
        },
        "fixed": [{"face": "z-"}] if fixed is None else fixed,
        "load_cases": [{"forces": forces}],
        "fpm": {**PAPER_MODEL, **(fpm_settings or {})},
    }


def network_spec(
    nodes: list[list[float]] | np.ndarray,
    springs: list[tuple[int, int]],
    *,
    masses: float | list[float] = 0.01,
    fixed_nodes: tuple[int, ...] | list[int] = (),
    forces: dict[int, list[float]],
    fpm_settings: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """A mass-spring network; ``forces`` maps node index -> force vector, N."""
    return {
        "name": "test network",
        "material": dict(MATERIAL),
        "geometry": {
            "type": "network",
            "nodes": np.asarray(nodes, dtype=float).tolist(),
            "springs": [list(s) for s in springs],
            "masses": masses,
        },
        "fixed": [{"node": int(i)} for i in fixed_nodes],
        "load_cases": [
            {"forces": [{"node": int(i), "vector": list(v)} for i, v in forces.items()]}
        ],
        "fpm": dict(fpm_settings or {}),
    }


def chain_spec(
    n_springs: int,
    length: float,
    direction: tuple[float, float, float],
    *,
    tip_force: list[float],
    mass: float = 0.01,
    fpm_settings: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """A straight chain of ``n_springs`` springs of rest ``length`` m from node 0 (fixed),
    along ``direction``; node i sits at i * length * direction; the force acts on the tip."""
    e = np.asarray(direction, dtype=float)
    e /= np.linalg.norm(e)
    nodes = np.arange(n_springs + 1)[:, None] * length * e[None, :]
    springs = [(i, i + 1) for i in range(n_springs)]
    return network_spec(
        nodes,
        springs,
        masses=mass,
        fixed_nodes=[0],
        forces={n_springs: tip_force},
        fpm_settings=fpm_settings,
    )


def lattice_index(shape: tuple[int, int, int], i: int, j: int, k: int) -> int:
    """Node index of lattice point (i, j, k) of a box of ``shape`` nodes (x fastest)."""
    nx, ny, _ = shape
    return i + nx * (j + ny * k)


def spec_errors(spec: Any) -> list[tuple[tuple[Any, ...], str]]:
    """The (loc, msg) list of the ValidationError that loading ``spec`` raises."""
    try:
        fpm.load_problem(spec)
    except ValidationError as e:
        return [(tuple(err["loc"]), err["msg"]) for err in e.errors()]
    raise AssertionError("the spec loaded, but it should have been refused")


def spring_forces(
    x: np.ndarray, springs: np.ndarray, rest: np.ndarray, k: float | np.ndarray
) -> np.ndarray:
    """(N, 3) net spring force on each node at positions ``x`` (docs/physics.md, FPM):
    spring (i, j) pulls i by k (|r| - l) r / |r| with r = x_j - x_i, and j by the opposite."""
    r = x[springs[:, 1]] - x[springs[:, 0]]
    length = np.linalg.norm(r, axis=1)
    f = (np.asarray(k) * (length - rest) / length)[:, None] * r
    out = np.zeros_like(x)
    np.add.at(out, springs[:, 0], f)
    np.add.at(out, springs[:, 1], -f)
    return out


def stage_one(problem: fpm.Problem, reference: Any, chain: int = 0) -> tuple[list[float], float]:
    """Stage 1 of a families+volume fit as a calibration makes it: one chain annealing the
    reduced model on the first basis, then the defect-corrected fit from its answer (the
    damping stage's polish). Returns (theta, its normalised static cost)."""
    from fpm.fitting.bounds import fit_depth, stiffness_bounds
    from fpm.fitting.cost import StaticCost
    from fpm.fitting.defect_correction import fit_reduced
    from fpm.fitting.reduced import first_basis
    from fpm.fitting.reference import reference_displacements
    from fpm.fitting.stiffness_stage import run_chain

    annealed = run_chain(problem, reference, chain)
    cost = StaticCost(problem, reference_displacements(reference, problem), fit_depth(problem))
    theta, static, _ = fit_reduced(
        cost, first_basis(problem), annealed.x, stiffness_bounds(problem)
    )
    return theta, static
