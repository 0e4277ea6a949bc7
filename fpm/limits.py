"""How large a problem may be: the checks the service runs at submit and ``fpmcal`` runs before
any work, with the same messages (one function, :func:`check_size`, for both).

The defaults are the service's (:class:`service.settings.Settings`); the environment overrides
them as it does the service's settings (``FPM_MAX_NODES``, ``FPM_MAX_LOAD_CASES``,
``FPM_MAX_CHAINS``, ``FPM_MAX_MESH_TETRAHEDRA``). The memory a calibration needs is checked by
:func:`worker.memory.check` (the worker before a job, ``fpmcal`` before a calibration).
"""

from __future__ import annotations

import math
import os
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from .model.spec import BoxGeometry, MeshGeometry, NetworkGeometry, ProblemSpec, VoxelGeometry

MAX_NODES = 100_000
"""Largest solid, in lattice nodes."""
MAX_LOAD_CASES = 20
"""Most load cases of a spec."""
MAX_CHAINS = 16
"""Most annealing chains of a calibration."""
MAX_MESH_TETRAHEDRA = 200_000
"""Most tetrahedra of a reference mesh."""


class LimitError(ValueError):
    """A problem over a size limit: ``field`` (a spec field, or a command-line flag) and
    ``message`` (what is over which limit)."""

    def __init__(self, field: str, message: str):
        super().__init__(f"{field}: {message}")
        self.field = field
        self.message = message


@dataclass(frozen=True)
class Limits:
    """The size limits (defaults: the module's constants)."""

    max_nodes: int = MAX_NODES
    max_load_cases: int = MAX_LOAD_CASES
    max_chains: int = MAX_CHAINS
    max_mesh_tetrahedra: int = MAX_MESH_TETRAHEDRA

    @classmethod
    def from_environ(cls, environ: Mapping[str, str] | None = None) -> Limits:
        """The limits with ``FPM_MAX_NODES`` etc. from the environment where set (as the
        service reads them).

        Raises:
            LimitError: a variable that is not a whole number >= 1.
        """
        env: Mapping[str, str] = os.environ if environ is None else environ
        values = {}
        for name in ("max_nodes", "max_load_cases", "max_chains", "max_mesh_tetrahedra"):
            variable = f"FPM_{name.upper()}"
            text = env.get(variable)
            if text is None:
                continue
            if not text.strip().isdigit() or int(text) < 1:
                raise LimitError(variable, f"must be a whole number >= 1 (got {text!r})")
            values[name] = int(text)
        return cls(**values)

    def check_nodes(self, nodes: int, field: str = "geometry") -> None:
        """Raise :class:`LimitError` at ``field`` when ``nodes`` is over the node limit."""
        if nodes > self.max_nodes:
            raise LimitError(field, f"{nodes} nodes is over the limit of {self.max_nodes}")


def node_count(spec: ProblemSpec) -> int:
    """Nodes the solid of ``spec`` will have, computed without building it."""
    g = spec.geometry
    if isinstance(g, BoxGeometry):
        return math.prod(int(n) for n in g.nodes)  # Python ints: np.prod wraps past 2**63
    if isinstance(g, VoxelGeometry):
        cells = np.asarray(g.occupancy, dtype=bool)
        nx, ny, nz = cells.shape
        used = np.zeros((nx + 1, ny + 1, nz + 1), dtype=bool)
        for dx in (0, 1):
            for dy in (0, 1):
                for dz in (0, 1):
                    used[dx : dx + nx, dy : dy + ny, dz : dz + nz] |= cells
        return int(used.sum())
    assert isinstance(g, MeshGeometry | NetworkGeometry)
    return len(g.nodes)


def check_size(spec: ProblemSpec, limits: Limits | None = None) -> int:
    """Check ``spec``'s size against ``limits`` (default :meth:`Limits.from_environ`) before
    anything is built: its nodes, load cases, annealing chains and reference mesh. Returns
    the node count.

    Raises:
        LimitError: the first limit exceeded, at its field (``geometry``, ``load_cases``,
            ``annealing.chains``, ``reference.mesh.tetrahedra``).
    """
    limits = Limits.from_environ() if limits is None else limits
    nodes = node_count(spec)
    limits.check_nodes(nodes)
    if len(spec.load_cases) > limits.max_load_cases:
        raise LimitError(
            "load_cases",
            f"{len(spec.load_cases)} load cases is over the limit of {limits.max_load_cases}",
        )
    if spec.annealing.chains > limits.max_chains:
        raise LimitError(
            "annealing.chains",
            f"{spec.annealing.chains} chains is over the limit of {limits.max_chains}",
        )
    mesh = spec.reference.mesh
    if mesh is not None and len(mesh.tetrahedra) > limits.max_mesh_tetrahedra:
        raise LimitError(
            "reference.mesh.tetrahedra",
            f"{len(mesh.tetrahedra)} tetrahedra is over the limit of {limits.max_mesh_tetrahedra}",
        )
    return nodes
