"""The lattice an export writes, with the fitted parameters on it: what every format shares.

:class:`Parameters` is what a fit hands over (a calibration result's or a stored parameter
set's stiffness, d, depth and dt, checked against the lattice the spec builds);
:func:`build_lattice` puts them on the problem's lattice (every spring's stiffness, the volume
term's kappa per hexahedron, each load case's perturbed layers): the :class:`Lattice` that
:mod:`.json_format`, :mod:`.vtu` and :mod:`.sofa` write.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from ...model.forces import Stiffness
from ...model.problem import Problem
from ...model.stiffness import fitted_theta, model_stiffness
from ..errors import ExportError


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
            from ...dynamics.stability import auto_time_step

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
    from ...dynamics.simulation import fpm_model

    depth = lattice.params.depth if lattice is not None else depth
    model = fpm_model(problem)
    out = []
    for j in range(len(problem.load_cases)):
        plist = model.perturbed_list(j, depth)
        out.append([plist.layer(i) for i in range(len(plist.layer_start) - 1)])
    return out
