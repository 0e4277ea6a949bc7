"""A fitted parameter set with its lattice, for other engines: JSON, VTU (ParaView), SOFA scene.

The parameters (stiffness per family, d, depth, the dt they were fitted at) come from a
calibration result (``fpmcal calibrate --json``) or a stored parameter set (the service); the
lattice is rebuilt from the spec they were fitted on. Formats:

- ``json``: every number an engine needs, with units: nodes, springs ``[i, j, rest length,
  stiffness]`` (each spring's assembled stiffness; a field fit's per-cell factors included,
  ``fpm.stiffness: "field"``), the hexahedra with their volume stiffness
  kappa and rest volume (the volume term; null in the spring-only models), lumped masses, fixed
  nodes, the model's energy in words, d, dt, depth (null: every layer), and per load case the
  nodal forces and the perturbed list's layers (the paper's lookup table), ``parameters.engine``:
  the d and dt at which an engine's all-at-once step settles fastest (:func:`engine_parameters`;
  d and dt beside it are the calibration kernel's), and ``fit``: the
  figures per load and validation case (relative discrepancy, load compliance ratio) and the
  verdict on the fit (good, fair or poor, and why): from it alone
  another program rebuilds
  the model's static equilibrium (tests/test_export.py does, with its own linear solve);
- ``vtu``: the hexahedra and the springs (VTK_LINE cells) with, per load case and per
  validation case, the FPM's displacements (its static equilibrium at the parameters, where its
  runs settle: :func:`fpm_equilibria`) and the FEM's, the error between them and the perturbed
  list's layer as point data (written by meshio; ParaView reads it);
- ``sofa``: a SOFA scene (``.scn``) with the positions (``MechanicalObject``), the lumped masses
  (``DiagonalMass vertexMass``), every spring with its stiffness (``SpringForceField spring="i j
  ks kd L"``, kd = 0), the nodal damping d (``UniformVelocityDampingForceField``; the engine's d
  and dt, ``parameters.engine``, where they could be computed, else the kernel's), the fixed
  nodes (``FixedProjectiveConstraint``) and the load cases (``ConstantForceField``; the first
  one active). docs/physics.md, *Engines*, says why each component and where SOFA defines it.
  SOFA has no component for the volume term (a penalty on each trilinear hexahedron's volume):
  a scene of a families+volume fit says so in a comment, and :func:`export_warnings` warns;
- ``sofa-python``: a SofaPython3 scene (``.py``) with the same components plus the volume term
  as a ``Sofa.Core.ForceField`` subclass in NumPy (:mod:`fpm.io.sofa_scene`: addForce,
  addDForce, addKToMatrix), the lattice's numbers in the file: the whole default model in SOFA.
"""

from __future__ import annotations

import math
import re
import tempfile
import textwrap
from dataclasses import dataclass
from pathlib import Path
from typing import Any
from xml.sax.saxutils import quoteattr

import numpy as np

from ..model.forces import Stiffness
from ..model.hexahedron import FAMILIES
from ..model.problem import Problem
from ..model.stiffness import fitted_theta, has_volume, model_stiffness
from .errors import ExportError

FORMATS = ("json", "vtu", "sofa", "sofa-python")
MEDIA_TYPES = {
    "json": "application/json",
    "vtu": "application/xml",
    "sofa": "application/xml",
    "sofa-python": "text/x-python",
}
SUFFIXES = {"json": ".json", "vtu": ".vtu", "sofa": ".scn", "sofa-python": ".py"}
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
SOFA_NO_VOLUME = (
    "SOFA has no XML component for this model's volume term (1/2 kappa (V - V0)^2 / V0 per "
    "trilinear hexahedron): this scene has the springs only and is softer in compression than "
    "the fitted model; export format sofa-python for a SofaPython3 scene that carries the "
    "volume term as a Python ForceField"
)


@dataclass
class Parameters:
    """What a fit hands over: k per spring family present (N/m), d (N s/m), the depth
    (layers; None: every layer, what a fit at its full depth means: a load anywhere else
    moves the whole lattice, as the validation cases were judged), the time step d was
    fitted at (s), the volume stiffness kappa (Pa; None for the spring-only models) and, for
    ``fpm.stiffness: "field"``, the field (its per-cell factors: every spring's and cell's
    stiffness is then its own)."""

    stiffness: dict[str, float]
    d: float
    depth: int | None
    dt: float
    volume_stiffness: float | None = None
    field: dict[str, Any] | None = None

    @classmethod
    def from_record(cls, problem: Problem, record: dict[str, Any]) -> Parameters:
        """From a calibration result or a parameter set (both carry ``stiffness``, ``d`` (or
        ``damping``) and ``depth``; a parameter set also ``dt``, else the spec's; a depth at
        or beyond the result's ``full_depth``, or null, is every layer); checked against the
        lattice the spec builds."""
        try:
            stiffness = record.get("stiffness") or {"axis": float(record["k"])}
            d = float(record["d"] if "d" in record else record["damping"])
            full = record.get("full_depth")
            depth = None if record["depth"] is None else int(record["depth"])
            if depth is not None and full is not None and depth >= int(full):
                depth = None
        except (KeyError, TypeError, ValueError):
            raise ExportError(
                "the parameters need stiffness (or k), d (or damping) and depth: give a "
                "calibration result (fpmcal calibrate --json) or a parameter set"
            ) from None
        geometry = record.get("geometry") or {}
        nodes = geometry.get("nodes") if isinstance(geometry.get("nodes"), int) else None
        h = record.get("h", geometry.get("h"))
        if (nodes is not None and nodes != problem.n_nodes) or (
            h is not None and not math.isclose(float(h), problem.h, rel_tol=1e-6)
        ):
            raise ExportError(
                f"these parameters were fitted on another lattice ({nodes or '?'} nodes, h = "
                f"{float(h or 'nan'):.4g} m); the spec builds {problem.n_nodes} nodes, h = "
                f"{problem.h:.4g} m: export with the spec they were fitted on"
            )
        mode = record.get("stiffness_mode", problem.spec.fpm.stiffness)
        if mode != problem.spec.fpm.stiffness:
            raise ExportError(
                f"the parameters were fitted with fpm.stiffness {mode!r}, the spec says "
                f"{problem.spec.fpm.stiffness!r}: export with the spec they were fitted on"
            )
        kappa = record.get("volume_stiffness")
        params = cls(
            {k: float(v) for k, v in stiffness.items()},
            d,
            depth,
            0.0,
            None if kappa is None else float(kappa),
            record.get("field"),
        )
        dt = record.get("dt") or problem.spec.fpm.dt
        if dt == "auto":  # a record from before the fit reported its dt: resolve it the same way
            from ..dynamics.stability import auto_time_step

            dt = auto_time_step(problem, model_stiffness(problem, params.theta(problem)))
        params.dt = float(dt)
        return params

    def theta(self, problem: Problem) -> list[float] | Stiffness:
        """The stiffness parameters as the solvers take them (:func:`fitted_theta`: a returned
        field's Stiffness, every spring's and cell's own)."""
        record = {
            "stiffness": self.stiffness,
            "volume_stiffness": self.volume_stiffness,
            "field": self.field,
        }
        try:
            return fitted_theta(problem, record)
        except ValueError as e:
            raise ExportError(str(e)) from None


@dataclass
class Lattice:
    """The lattice with every spring's stiffness: what all three formats write.

    Attributes:
        problem: the problem (nodes, masses, fixed nodes, load cases).
        params: the parameters.
        stiffness: (S,) per-spring stiffness, N/m (family k, assembled from cells for
            families+volume, times the spec's stiffness_scale).
        layers: per load case, the perturbed list's layers at ``params.depth`` (node arrays).
        volume: (H,) kappa per hexahedron, Pa, or None (the spring-only models).
    """

    problem: Problem
    params: Parameters
    stiffness: np.ndarray
    layers: list[list[np.ndarray]]
    volume: np.ndarray | None = None

    @property
    def hexahedra(self) -> np.ndarray:
        elements = self.problem.solid.elements()
        if elements is None:
            raise ExportError("a network geometry has no hexahedra and no calibration to export")
        return elements


def build_lattice(problem: Problem, params: Parameters) -> Lattice:
    """The lattice of ``problem`` carrying ``params``."""
    stiffness = model_stiffness(problem, params.theta(problem))
    layers = _layers(problem, None, params.depth)
    return Lattice(problem, params, stiffness.springs, layers, stiffness.volume)


def _layers(
    problem: Problem, lattice: Lattice | None, depth: int | None = None
) -> list[list[np.ndarray]]:
    """Per load case of ``problem``, its perturbed list's layers (node indices) at the
    lattice's depth (or ``depth``)."""
    from ..dynamics.simulation import fpm_model

    depth = lattice.params.depth if lattice is not None else depth
    model = fpm_model(problem)
    out = []
    for j in range(len(problem.load_cases)):
        plist = model.perturbed_list(j, depth)
        out.append([plist.layer(i) for i in range(len(plist.layer_start) - 1)])
    return out


def fpm_displacements(lattice: Lattice) -> tuple[np.ndarray, list[int], list[bool]]:
    """(L, N, 3) displacements of the FPM run from rest to settling at the parameters, per load
    case, with the steps taken and whether each settled (the result's last dynamic run)."""
    from ..dynamics.simulation import simulate

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

    from ..dynamics.equilibrium import StaticSolver
    from ..dynamics.modes import single_threaded_blas

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


def load_shares(problem: Problem) -> dict[str, list]:
    """The ``hat`` rule (:data:`LOADS`) as a table for every surface node of the lattice (where
    a tool touches it), compressed by rows: row r is node ``nodes[r]``; its shares are
    ``weights[indptr[r]:indptr[r + 1]]`` on the nodes ``indices[indptr[r]:indptr[r + 1]]``."""
    from ..model.hat_loads import hat_shares, surface_mass

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
    export (about 0.2 s at 1,000 nodes, 1-2 s at 10,000)."""
    from scipy.sparse.linalg import ArpackError

    from ..dynamics.engine_damping import RestLattice, engine_damping
    from ..model.forces import cells

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
        from ..model.forces import cells

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
    from ..dynamics.settle import by_distance, force_tolerance, nominal_distance

    problem = lattice.problem
    cases = len(problem.load_cases)
    models = None
    if by_distance(problem.spec):
        from ..dynamics.modes import case_models

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
    from ..dynamics.modes import predicted_max_steps

    p = lattice.params
    stiffness = model_stiffness(lattice.problem, p.theta(lattice.problem))
    return predicted_max_steps(lattice.problem, stiffness, p.d, p.depth, p.dt)


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


SOFA_PLUGINS = {
    "Sofa.Component.StateContainer": "MechanicalObject",
    "Sofa.Component.Topology.Container.Constant": "MeshTopology",
    "Sofa.Component.Mass": "DiagonalMass",
    "Sofa.Component.SolidMechanics.Spring": "SpringForceField",
    "Sofa.Component.MechanicalLoad": "UniformVelocityDampingForceField ConstantForceField",
    "Sofa.Component.Constraint.Projective": "FixedProjectiveConstraint",
    "Sofa.Component.ODESolver.Backward": "EulerImplicitSolver",
    "Sofa.Component.LinearSolver.Iterative": "CGLinearSolver",
}
"""The SOFA modules the scene loads, with the components it takes from each."""


def _numbers(values: Any) -> str:
    return " ".join(repr(float(v)) for v in np.asarray(values, dtype=float).ravel())


def _indices(values: Any) -> str:
    return " ".join(str(int(v)) for v in np.asarray(values).ravel())


def sofa_scene(lattice: Lattice) -> str:
    """The ``sofa`` export: a scene SOFA (v24.06 or later) loads (module docstring)."""
    problem, p = lattice.problem, lattice.params
    springs = np.column_stack(
        [
            problem.solid.springs.astype(float),
            lattice.stiffness,
            np.zeros(len(lattice.stiffness)),
            problem.rest_lengths,
        ]
    )
    spring_text = " ".join(
        f"{int(i)} {int(j)} {ks!r} 0 {length!r}" for i, j, ks, _, length in springs.tolist()
    )
    g = " ".join(repr(float(v)) for v in problem.spec.fpm.gravity)
    engine = engine_parameters(lattice)
    d, dt = (engine["d"], engine["dt"]) if engine else (p.d, p.dt)
    lines = [
        '<?xml version="1.0"?>',
        _comment(
            f"FPM lattice {problem.spec.name}: SI units (m, kg, s, N). {problem.n_nodes} nodes, "
            f"{len(springs)} springs (spring = i j ks kd L: ks in N/m, kd = 0, L the rest "
            f"length in m); stiffness {_fmt_stiffness(p.stiffness)} N/m; "
            + _sofa_damping_words(p, engine)
            + "; the FPM's perturbed list has no SOFA counterpart: SOFA moves every node (full "
            "depth)." + ("" if lattice.volume is None else " " + SOFA_NO_VOLUME + ".")
        ),
        f'<Node name="root" dt={quoteattr(repr(dt))} gravity="{g}">',
    ]
    lines += [
        f'    <RequiredPlugin name="{plugin}"/> <!-- {what} -->'
        for plugin, what in SOFA_PLUGINS.items()
    ]
    lines += [
        "    <DefaultAnimationLoop/>",
        f'    <Node name="{_identifier(problem.spec.name)}">',
        '        <EulerImplicitSolver name="odesolver" rayleighStiffness="0" rayleighMass="0"/>',
        '        <CGLinearSolver name="linearsolver" iterations="1000" tolerance="1e-12" '
        'threshold="1e-20"/>',
        '        <MechanicalObject name="dofs" template="Vec3d" '
        f'position="{_numbers(problem.nodes)}"/>',
        '        <MeshTopology name="topology" position="@dofs.position" '
        f'hexahedra="{_indices(lattice.hexahedra)}"/>',
        f'        <DiagonalMass name="mass" vertexMass="{_numbers(problem.solid.masses)}"/>',
        f'        <SpringForceField name="springs" spring="{spring_text}"/>',
        '        <UniformVelocityDampingForceField name="damping" '
        f'dampingCoefficient="{d!r}" implicit="true"/>',
    ]
    fixed = np.flatnonzero(problem.fixed)
    if len(fixed):
        lines.append(
            f'        <FixedProjectiveConstraint name="fixed" indices="{_indices(fixed)}"/>'
        )
    for j, case in enumerate(problem.load_cases):
        element = (
            f"<ConstantForceField name={quoteattr(f'load case {j + 1}')} "
            f'indices="{_indices(case.nodes)}" forces="{_numbers(case.forces)}"/>'
        )
        if j == 0:
            lines.append("        " + _comment(f"load case 1: {case.name}"))
            lines.append(f"        {element}")
        else:
            lines.append(
                "        "
                + _comment(f"load case {j + 1}: {case.name} (uncomment to apply) {element}")
            )
    lines += ["    </Node>", "</Node>", ""]
    return "\n".join(lines)


def _sofa_damping_words(p: Parameters, engine: dict[str, float] | None) -> str:
    """What a SOFA scene says of its d and dt (the engine's, where the export has them)."""
    kernel = (
        f"the calibration's d = {p.d!r} N s/m was fitted at dt = {p.dt!r} s for the FPM's "
        "node-by-node step"
    )
    if engine is None:
        return f"nodal damping: {kernel} (choose d again for this integrator and time step)"
    return (
        f"nodal damping d = {engine['d']!r} N s/m and dt = {engine['dt']!r} s: the engine's "
        "(the export's parameters.engine), the fastest-settling pair of the explicit all-at-once "
        "step at rest, each mode's error shrinking by "
        f"{engine['decay_per_step']!r} a step; under SOFA's implicit Euler every dt is stable "
        "and this d is close to the slowest mode's critical damping (2 m w_min), so it settles "
        f"near fastest at this dt as well ({kernel})"
    )


def _identifier(text: str) -> str:
    """``text`` as a SOFA node name (letters, digits, underscores), "fpm" if nothing is left."""
    return re.sub(r"[^0-9A-Za-z_]+", "_", text).strip("_") or "fpm"


def _comment(text: str) -> str:
    """An XML comment of ``text`` (which may not hold "--")."""
    while "--" in text:
        text = text.replace("--", "- -")
    return f"<!-- {text.rstrip('-')} -->"


def _fmt_stiffness(stiffness: dict[str, float]) -> str:
    return ", ".join(f"{name} {value:.6g}" for name, value in stiffness.items())


def sofa_python_scene(lattice: Lattice) -> str:
    """The ``sofa-python`` export: :mod:`fpm.io.sofa_scene`'s code with the lattice in MODEL."""
    import json

    template = (Path(__file__).parent / "sofa_scene.py").read_text()
    doc = to_json(lattice)
    model = {
        key: doc[key]
        for key in (
            "name", "units", "parameters", "nodes", "masses", "fixed", "springs", "hexahedra",
            "volume_stiffness", "rest_volumes",
        )
    }  # fmt: skip
    model["load_cases"] = [
        {k: case[k] for k in ("name", "nodes", "forces")} for case in doc["load_cases"]
    ]
    if "load_shares" in doc:  # a hat fit: applied() spreads a force as the fit did
        model["load_shares"] = doc["load_shares"]
    placeholder = 'MODEL: dict[str, Any] = json.loads("{}")'
    if placeholder not in template:
        raise RuntimeError("fpm/io/sofa_scene.py lost its MODEL line")
    p = lattice.params
    words = textwrap.wrap(
        _sofa_damping_words(p, doc["parameters"]["engine"]) + ".",
        width=97,
        break_long_words=False,
        break_on_hyphens=False,
    )
    header = (
        f"# FPM lattice {lattice.problem.spec.name!r} for SofaPython3: SI units (m, kg, s, N).\n"
        f"# {lattice.problem.n_nodes} nodes, {len(lattice.stiffness)} springs.\n"
        + "".join(f"# {line}\n" for line in words)
        + "# Run: runSofa this_file.py (or python with SofaPython3). Generated by fpm.\n"
    )
    return header + template.replace(
        placeholder, f"MODEL: dict[str, Any] = json.loads({json.dumps(model)!r})"
    )


def export_warnings(problem: Problem, fmt: str) -> list[str]:
    """What the user should know about an export of ``problem`` in ``fmt`` (one line each)."""
    if fmt == "sofa" and has_volume(problem):
        return [SOFA_NO_VOLUME]
    return []


def export(
    problem: Problem,
    record: dict[str, Any],
    fmt: str,
    *,
    fem: np.ndarray | None = None,
) -> bytes:
    """The export of ``record``'s parameters on ``problem``'s lattice in format ``fmt``.

    Args:
        problem: the problem of the spec the parameters were fitted on.
        record: a calibration result or a parameter set (:meth:`Parameters.from_record`).
        fmt: ``json``, ``vtu``, ``sofa`` or ``sofa-python``.
        fem: (L, N, 3) FEM displacements for ``vtu``, then (V, N, 3) those of the
            validation cases if it holds them (a stored reference does; None: solved now).
    """
    import json

    if fmt not in FORMATS:
        raise ExportError(f"unknown format {fmt!r}: one of {', '.join(FORMATS)}")
    lattice = build_lattice(problem, Parameters.from_record(problem, record))
    if fmt == "json":
        keys = (
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
        fit = {k: record[k] for k in keys if k in record}
        return json.dumps(to_json(lattice, fit, record.get("max_steps"))).encode()
    if fmt == "sofa":
        return sofa_scene(lattice).encode()
    if fmt == "sofa-python":
        return sofa_python_scene(lattice).encode()
    if fem is None:
        from ..fem.reference import solve_fem

        fem = solve_fem(problem).displacements
    fem = np.asarray(fem, dtype=float)
    fpm, checked, _ = fpm_equilibria(lattice)
    n, v = len(problem.load_cases), len(problem.validation_cases)
    validation = (fem[n : n + v], checked) if v and len(fem) >= n + v else None
    return vtu_bytes(lattice, fem[:n], fpm, validation)
