"""The ``json`` export: every number an engine needs, with units.

Nodes, springs ``[i, j, rest length, stiffness]`` (each spring's assembled stiffness; a field
fit's per-cell factors included, ``fpm.stiffness: "field"``), the hexahedra with their volume
stiffness kappa and rest volume (the volume term; null in the spring-only models), lumped
masses, fixed nodes, the model's energy in words, d, dt, depth (null: every layer), and per
load case the nodal forces and the perturbed list's layers (the paper's lookup table),
``parameters.engine``: the d and dt at which an engine's all-at-once step settles fastest
(:func:`engine_parameters`; d and dt beside it are the calibration kernel's), and ``fit``: the
figures per load and validation case (relative discrepancy, load compliance ratio) and the
verdict on the fit (good, fair or poor, and why): from it alone another program rebuilds the
model's static equilibrium (tests/core/test_export.py does, with its own linear solve).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from ...model.hexahedron import FAMILIES
from ...model.problem import Problem
from ...model.stiffness import model_stiffness
from .lattice import Lattice

UNITS = {
    "length": "m",
    "mass": "kg",
    "time": "s",
    "force": "N",
    "stiffness": "N/m",
    "damping": "N s/m",
}

STEP = (
    "node by node in perturbed-list order (layer 0 = the loaded nodes, then layer by layer; "
    "nodes outside the list do not move): F_s = sum_j k_ij (|r_ij| - L_ij) r_ij / |r_ij| "
    "with r_ij = x_j - x_i, plus the volume forces (computed once per step, from the "
    "positions at its start); v_i <- (v_i + dt (F_i + F_s) / m_i) / (1 + dt d / m_i); "
    "x_i <- x_i + dt v_i (each node sees the new positions of the nodes before it)"
)
ENERGY = (
    "E = sum_s 1/2 k_s (|x_j - x_i| - L_s)^2 + sum_c 1/2 kappa_c (V_c - V0_c)^2 / V0_c - "
    "sum_i F_i . (x_i - X_i): springs s (i, j, rest length L_s, stiffness k_s), and per "
    "hexahedron c the volume term (kappa_c = volume_stiffness[c], Pa; V_c the volume of the "
    "trilinear hexahedron of its 8 corners in the hexahedron node order of fpm.model.hexahedron, "
    "V0_c = rest_volumes[c]; absent when volume_stiffness is null); F_i the nodal forces (plus "
    "m_i g with gravity). Forces = -dE/dx; the static equilibrium is dE/dx = 0 over the free "
    "nodes with the fixed nodes at rest"
)
LOADS = {
    "node": "a force on a node acts at that node (the paper's model)",
    "hat": (
        "a force f meant for node i stands for a load over the node's share of the solid and "
        "is applied as f_j = f M_ij / sum_k M_ik on the nodes j around it, M the consistent "
        "mass matrix (int N_i N_j, 2 x 2 Gauss points per face) of the lattice's surface (the "
        "hexahedron faces that belong to one hexahedron) for a surface node, of its volume "
        "(2 x 2 x 2 per hexahedron) for an interior one; shares on fixed nodes go to the "
        "supports. On a flat face: 4/9 at i, 1/9 at each edge neighbour, 1/36 at each diagonal "
        "one. load_cases[].forces are already so applied (fpm.model.hat_loads)"
    ),
}
"""How the fit applied a nodal force (``fpm.loads``), as an engine must to get its figures."""


FIT_KEYS = (
    "relative_discrepancy",
    "loaded_discrepancy",
    "discrepancy_h",
    "validation_cases",
    "validation_relative_discrepancy",
    "validation_discrepancy_h",
    "compliance_ratio",
    "validation_compliance_ratio",
    "verdict",
)
"""The figures of a calibration result or parameter set the export's ``fit`` carries."""


def fit_figures(record: dict[str, Any]) -> dict[str, Any]:
    """The ``fit`` block of ``record`` (:data:`FIT_KEYS`, those it holds)."""
    return {k: record[k] for k in FIT_KEYS if k in record}


def load_shares(problem: Problem) -> dict[str, list]:
    """The ``hat`` rule (:data:`LOADS`) as a table for every surface node of the lattice (where
    a tool touches it), compressed by rows: row r is node ``nodes[r]``; its shares are
    ``weights[indptr[r]:indptr[r + 1]]`` on the nodes ``indices[indptr[r]:indptr[r + 1]]``."""
    from ...model.hat_loads import hat_shares, surface_mass

    hexahedra = problem.solid.elements()
    assert hexahedra is not None  # 'hat' is refused on a network
    masses = surface_mass(problem.nodes, hexahedra)
    surface = np.flatnonzero(np.asarray(masses.sum(axis=1)).ravel() > 0)
    rows = hat_shares(problem.nodes, hexahedra, surface, masses)[surface]
    return {
        "nodes": surface.tolist(),
        "indptr": rows.indptr.tolist(),
        "indices": rows.indices.tolist(),
        "weights": rows.data.tolist(),
    }


def engine_parameters(lattice: Lattice) -> dict[str, float] | None:
    """The JSON export's ``parameters.engine``: the d and dt at which the all-at-once step (an
    engine's: :mod:`fpm.runtime`, the C step, the web view's live model) settles fastest and
    stays stable, from the lattice at rest (:func:`fpm.dynamics.engine_damping.engine_damping`:
    its slowest and fastest modes), with what else an engine needs of them
    (:meth:`~fpm.dynamics.engine_damping.EngineDamping.as_export`). None where the modes
    cannot be had (the eigensolver failed: the export then carries null). Computed once per
    export."""
    from scipy.sparse.linalg import ArpackError

    from ...dynamics.engine_damping import RestLattice, engine_damping
    from ...model.forces import cells

    problem = lattice.problem
    volume = lattice.volume is not None
    model = RestLattice(
        rest=problem.nodes,
        masses=problem.solid.masses,
        fixed=problem.fixed,
        springs=problem.solid.springs.astype(np.int64),
        stiffness=lattice.stiffness,
        hexahedra=lattice.hexahedra if volume else np.zeros((0, 8), np.int64),
        kappa=np.asarray(lattice.volume, dtype=float) if volume else np.zeros(0),
        rest_volumes=cells(problem).volume if volume else np.zeros(0),
    )
    try:
        found = engine_damping(model)
    except (ArpackError, ArithmeticError, RuntimeError, ValueError):
        return None
    block = found.as_export()
    if not all(math.isfinite(v) and v > 0 for v in block.values()):
        return None
    return block


def to_json(
    lattice: Lattice,
    fit: dict[str, Any] | None = None,
    max_steps: int | None = None,
    engine: dict[str, float] | None | bool = True,
) -> dict[str, Any]:
    """The ``json`` export (see the module docstring); ``fit``: figures to carry along (e.g. the
    relative discrepancy per load case); ``max_steps``: the cap the fit's runs had (a
    calibration result's ``max_steps``; None: :func:`resolved_max_steps`); ``engine``: the
    ``parameters.engine`` block (True: :func:`engine_parameters` computes it)."""
    problem, p = lattice.problem, lattice.params
    if engine is True:
        engine = engine_parameters(lattice)
    spec, solid = problem.spec, problem.solid
    settle = settle_parameters(lattice)
    springs = [
        [int(i), int(j), float(length), float(k)]
        for (i, j), length, k in zip(
            solid.springs, problem.rest_lengths, lattice.stiffness, strict=True
        )
    ]
    volume: dict[str, Any] = {"volume_stiffness": None, "rest_volumes": None}
    if lattice.volume is not None:
        from ...model.forces import cells

        volume = {
            "volume_stiffness": lattice.volume.tolist(),
            "rest_volumes": cells(problem).volume.tolist(),
        }
    return {
        "format": "fpm-lattice",
        "version": 1,
        "name": spec.name,
        "units": UNITS,
        "material": spec.material.model_dump(),
        "parameters": {
            "stiffness": p.stiffness,
            "volume_stiffness": p.volume_stiffness,
            "stiffness_mode": spec.fpm.stiffness,
            "stiffness_field": bool((p.field or {}).get("returned")),
            "stiffness_scale": list(spec.fpm.stiffness_scale),
            "d": p.d,
            "dt": p.dt,
            "engine": engine or None,
            "depth": p.depth,
            **{k: v for k, v in settle.items() if k != "cases"},
            "max_steps": int(max_steps or resolved_max_steps(lattice)),
            "gravity": list(spec.fpm.gravity),
            "loads": problem.loads,
        },
        "loads": LOADS[problem.loads],
        **({"load_shares": load_shares(problem)} if problem.loads == "hat" else {}),
        "energy": ENERGY,
        "step": STEP,
        "h": problem.h,
        "nodes": solid.nodes.tolist(),
        "masses": solid.masses.tolist(),
        "fixed": np.flatnonzero(problem.fixed).tolist(),
        "springs": springs,
        "spring_columns": ["i", "j", "rest_length", "stiffness"],
        "spring_family": solid.families.tolist(),
        "families": list(FAMILIES),
        "hexahedra": lattice.hexahedra.tolist(),
        **volume,
        "load_cases": [
            {
                "name": case.name,
                "nodes": case.nodes.tolist(),
                "forces": case.forces.tolist(),
                "perturbed_layers": [layer.tolist() for layer in layers],
                "settle_stiffness": stiffness,
            }
            for case, layers, stiffness in zip(
                problem.load_cases, lattice.layers, settle["cases"], strict=True
            )
        ],
        **({"fit": fit} if fit else {}),
    }


def settle_parameters(lattice: Lattice) -> dict[str, Any]:
    """How a run of the export settles, as the fit's runs settled: ``settle_tolerance`` (the
    force criterion: the largest unbalanced nodal force below it times the largest applied
    nodal force) and ``settle_stiffness`` (N/m, the distance criterion of
    :mod:`fpm.dynamics.settle`: the 2-norm of the unbalanced nodal forces below it times the
    2-norm of the displacements; 0 for none): the spec's settle_distance times the mode
    stiffness of each load case's list (``cases``, (L,)), the smallest of them for forces of
    the engine's own (``settle_stiffness``); or the force criterion."""
    from ...dynamics.settle import by_distance, force_tolerance, nominal_distance

    problem = lattice.problem
    cases = len(problem.load_cases)
    models = None
    if by_distance(problem.spec):
        from ...dynamics.step_caps import case_models

        p = lattice.params
        stiffness = model_stiffness(problem, p.theta(problem))
        models = case_models(problem, stiffness, p.depth, p.dt)
    if models is None:  # the force criterion (named, the paper method, or no modes at rest)
        tolerance = force_tolerance(problem.spec)  # FORCE_TOLERANCE where none is named
        return {"settle_tolerance": tolerance, "settle_stiffness": 0.0, "cases": [0.0] * cases}
    each = [nominal_distance(problem.spec) * m.mode_stiffness for m in models]
    return {"settle_tolerance": 0.0, "settle_stiffness": min(each), "cases": each}


def resolved_max_steps(lattice: Lattice) -> int:
    """The spec's fpm.max_steps as a number: its 'auto' resolved as for a run at the lattice's
    parameters (:func:`fpm.dynamics.modes.predicted_max_steps`, every load case)."""
    value = lattice.problem.spec.fpm.max_steps
    if value != "auto":
        return int(value)
    from ...dynamics.step_caps import predicted_max_steps

    p = lattice.params
    stiffness = model_stiffness(lattice.problem, p.theta(lattice.problem))
    return predicted_max_steps(lattice.problem, stiffness, p.d, p.depth, p.dt)
