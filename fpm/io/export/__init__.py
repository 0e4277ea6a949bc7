"""A fitted parameter set with its lattice, for other engines: JSON, VTU (ParaView), SOFA scene.

The parameters (stiffness per family, d, depth, the dt they were fitted at) come from a
calibration result (``fpmcal calibrate --json``) or a stored parameter set (the service); the
lattice is rebuilt from the spec they were fitted on (:mod:`.lattice`: :class:`Parameters`,
:func:`build_lattice`). Formats, one module each (:func:`export` picks one):

- ``json`` (:mod:`.json_format`): every number an engine needs, with units: the lattice, its
  springs and hexahedra, the model's energy and step in words, per load case the forces and the
  perturbed list's layers, ``parameters.engine`` (:func:`engine_parameters`) and the fit's
  figures; from it alone another program rebuilds the model's static equilibrium;
- ``vtu`` (:mod:`.vtu`): the hexahedra and the springs with the FPM's displacements (its static
  equilibria: :func:`fpm_equilibria`) and the FEM's per load and validation case, for ParaView;
- ``sofa`` (:mod:`.sofa`): a SOFA scene (``.scn``); SOFA has no component for the volume term,
  which :func:`export_warnings` says;
- ``sofa-python`` (:mod:`.sofa`): a SofaPython3 scene (``.py``, :mod:`fpm.io.sofa_scene`'s code)
  with the volume term as a Python ForceField: the whole default model in SOFA.
"""

from __future__ import annotations

import json
from typing import Any

import numpy as np

from ...model.problem import Problem
from ...model.stiffness import has_volume
from ..errors import ExportError
from .json_format import (
    engine_parameters,
    fit_figures,
    resolved_max_steps,
    to_json,
)
from .lattice import Parameters, build_lattice
from .sofa import SOFA_NO_VOLUME, sofa_python_scene, sofa_scene
from .vtu import fpm_displacements, fpm_equilibria, vtu_export

__all__ = [
    "FORMATS",
    "MEDIA_TYPES",
    "SOFA_NO_VOLUME",
    "SUFFIXES",
    "ExportError",
    "Parameters",
    "build_lattice",
    "engine_parameters",
    "export",
    "export_warnings",
    "fpm_displacements",
    "fpm_equilibria",
    "resolved_max_steps",
    "sofa_python_scene",
    "sofa_scene",
    "to_json",
]

FORMATS = ("json", "vtu", "sofa", "sofa-python")
MEDIA_TYPES = {
    "json": "application/json",
    "vtu": "application/xml",
    "sofa": "application/xml",
    "sofa-python": "text/x-python",
}
SUFFIXES = {"json": ".json", "vtu": ".vtu", "sofa": ".scn", "sofa-python": ".py"}


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
    if fmt not in FORMATS:
        raise ExportError(f"unknown format {fmt!r}: one of {', '.join(FORMATS)}")
    lattice = build_lattice(problem, Parameters.from_record(problem, record))
    if fmt == "json":
        fit = fit_figures(record)
        return json.dumps(to_json(lattice, fit, record.get("max_steps"))).encode()
    if fmt == "sofa":
        return sofa_scene(lattice).encode()
    if fmt == "sofa-python":
        return sofa_python_scene(lattice).encode()
    return vtu_export(lattice, fem)
