"""What every FEM reference hands back, and the linear solve they share.

:class:`FemResult` (the displacements per load case, with how they were found), :class:`FemError`
(a problem the FEM cannot solve) and :func:`solve_dirichlet` (K u = f with u = 0 on the held
unknowns) are used by the hexahedron reference (:mod:`fpm.fem.reference`), the 10-node
tetrahedra (:mod:`fpm.fem.tet10`) and the neo-Hookean solver (:mod:`fpm.fem.hyperelastic`); they
live here, below all three, so none of those imports another for them.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
import scipy.sparse as sp

from .assembly import keep_nodes
from .linear_solver import SingularStiffnessError, factorize, rigid_body_modes

RESIDUAL_LIMIT = 1e-6
"""A relative residual above this after the solve means K was (nearly) singular."""


class FemError(ValueError):
    """A problem the FEM cannot solve (no hexahedra, not held, inverted hexahedra)."""


@dataclass
class FemResult:
    """Static FEM displacements, one set per load case.

    Attributes:
        nodes: (N, 3) rest positions, m.
        displacements: (L, N, 3) nodal displacements, m, load cases in spec order.
        residuals: (L,) ||K u - f|| / ||f|| over the free unknowns (reactions excluded); for
            the neo-Hookean model the final unbalanced force ||f_int(u) - f|| / ||f||.
        load_cases: (L,) load case names.
        method: linear solver used, ``"direct"`` or ``"amg"`` (``"supplied"``: no solve).
        model: the material model, ``"linear"`` or ``"neo-hookean"``, or ``"supplied"`` for
            displacements the spec brought (:func:`supplied_reference`).
        load_steps: (L,) load steps taken per load case (neo-Hookean; empty for linear).
        newton_iterations: (L, steps) Newton iterations of each load step (neo-Hookean).
        element: the FEM's element: ``"hex8"`` (the lattice's hexahedra) or ``"tet10"`` (the
            spec's ``reference.mesh`` in 10-node tetrahedra, read at the lattice nodes:
            :mod:`fpm.fem.tet10`).
        estimated_error: (L,) per load case (then validation case), the reference's estimated
            error, %: the relative change at the lattice nodes from one refinement to the next
            (:mod:`fpm.fem.refine`); None when not estimated (``reference.refine`` 0, a
            supplied or neo-Hookean reference, a check over its budget, a stored reference
            older than the estimate).
        refinements: uniform refinements of the mesh the displacements were solved on (0: the
            mesh as given).
        loads: how the lattice's nodal forces were applied: ``"nodal"`` (point loads at the
            nodes) or ``"spread"`` (over each node's share of the solid: :mod:`fpm.fem.loads`).
        levels: per level solved: ``refinements``, ``fem_nodes``, ``change`` (per case, %, from
            the level before) and ``seconds``; empty when the reference was solved once.
        notes: what the user should know about the reference (a refinement the node budget
            refused, an error not estimated).
        iterations: (L,) CG iterations per load case (then validation case) of the solve that
            gave the displacements; empty for a direct solve or where not recorded (the
            tetrahedra record them: :mod:`fpm.fem.refine` predicts a finer level's work).
    """

    nodes: np.ndarray
    displacements: np.ndarray
    residuals: list[float]
    load_cases: list[str]
    method: str
    model: str = "linear"
    load_steps: list[int] = field(default_factory=list)
    newton_iterations: list[list[int]] = field(default_factory=list)
    element: str = "hex8"
    estimated_error: list[float] | None = None
    refinements: int = 0
    loads: str = "nodal"
    levels: list[dict[str, Any]] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)
    iterations: list[int] = field(default_factory=list)

    @property
    def positions(self) -> np.ndarray:
        """(L, N, 3) deformed nodal positions q_i, m (paper Eq. 2)."""
        return self.nodes[None] + self.displacements

    def to_dict(self) -> dict[str, Any]:
        """JSON-able dict (nested lists of floats)."""
        return {
            "nodes": self.nodes.tolist(),
            "displacements": self.displacements.tolist(),
            **self._fields(),
        }

    def _fields(self) -> dict[str, Any]:
        """:meth:`to_dict` but for ``nodes`` and ``displacements``."""
        return {
            "residuals": [float(r) for r in self.residuals],
            "load_cases": list(self.load_cases),
            "method": self.method,
            "model": self.model,
            "load_steps": list(self.load_steps),
            "newton_iterations": [list(steps) for steps in self.newton_iterations],
            "element": self.element,
            "estimated_error": (
                None if self.estimated_error is None else [float(e) for e in self.estimated_error]
            ),
            "refinements": int(self.refinements),
            "loads": self.loads,
            "levels": [dict(level) for level in self.levels],
            "notes": list(self.notes),
            "iterations": [int(n) for n in self.iterations],
        }

    def to_stored(self) -> tuple[dict[str, Any], bytes]:
        """(layout, raw arrays) as the store keeps a reference
        (:data:`store.records.RAW_REFERENCE`): :meth:`to_dict` without ``nodes`` and
        ``displacements``, with their ``shapes``; the two as little-endian float64, nodes
        first."""
        arrays = {"nodes": self.nodes, "displacements": self.displacements}
        layout = self._fields()
        layout["shapes"] = {name: list(a.shape) for name, a in arrays.items()}
        raw = b"".join(np.ascontiguousarray(a, dtype="<f8").tobytes() for a in arrays.values())
        return layout, raw

    @classmethod
    def from_stored(cls, layout: dict[str, Any], raw: bytes) -> FemResult:
        """Inverse of :meth:`to_stored`."""
        shapes = layout["shapes"]
        n = int(np.prod(shapes["nodes"]))
        flat = np.frombuffer(raw, dtype="<f8").astype(float)
        arrays = {
            "nodes": flat[:n].reshape(shapes["nodes"]),
            "displacements": flat[n:].reshape(shapes["displacements"]),
        }
        return cls.from_dict({**layout, **arrays})

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> FemResult:
        """Inverse of :meth:`to_dict` (a dict stored before the model fields reads as linear,
        one stored before the estimate as unrefined, point loads, error not estimated)."""
        nodes = np.asarray(data["nodes"], dtype=float).reshape(-1, 3)
        displacements = np.asarray(data["displacements"], dtype=float).reshape(-1, len(nodes), 3)
        return cls(
            nodes,
            displacements,
            [float(r) for r in data["residuals"]],
            list(data["load_cases"]),
            data["method"],
            data.get("model", "linear"),
            [int(n) for n in data.get("load_steps", [])],
            [[int(n) for n in steps] for steps in data.get("newton_iterations", [])],
            data.get("element", "hex8"),
            (
                None
                if data.get("estimated_error") is None
                else [float(e) for e in data["estimated_error"]]
            ),
            int(data.get("refinements", 0)),
            data.get("loads", "nodal"),
            [dict(level) for level in data.get("levels", [])],
            [str(note) for note in data.get("notes", [])],
            [int(n) for n in data.get("iterations", [])],
        )


def solve_dirichlet(
    k: sp.bsr_matrix, forces: np.ndarray, free: np.ndarray, nodes: np.ndarray, method: str
) -> tuple[np.ndarray, np.ndarray]:
    """Solve K u = f with u = 0 on the unknowns that are not ``free``.

    Args:
        k: (n, n) stiffness, N/m, n = 3N, in 3x3 blocks (:func:`fpm.fem.assembly.stiffness_matrix`).
        forces: (L, n) nodal forces, N.
        free: (n,) bool, unknowns to solve for (the rest are held at zero).
        nodes: (N, 3) rest positions, m (for the rigid-body modes of AMG).
        method: ``"direct"`` or ``"amg"``.

    Returns:
        u (L, n) displacements, m, and residuals (L,) ||K u - f|| / ||f|| over the free unknowns.

    Raises:
        FemError: the reduced K is singular (part of the solid can still move freely).
    """
    per_node = free.reshape(-1, 3)
    if np.array_equal(per_node.all(axis=1), per_node.any(axis=1)):  # whole nodes: keep blocks
        kff = keep_nodes(k, per_node[:, 0])
    else:
        kff = k.tocsr()[free][:, free]
    f = forces[:, free].T
    singular = FemError(
        "the stiffness matrix is singular: part of the solid can still move freely "
        "(fix more nodes, or join loose hexahedra by a face)"
    )
    try:
        x = factorize(kff, method, rigid_body_modes(nodes)[free])(f)
    except SingularStiffnessError:
        raise singular from None
    scale = np.linalg.norm(f, axis=0)
    residuals = np.linalg.norm(kff @ x - f, axis=0) / np.where(scale > 0, scale, 1.0)
    if not np.all(np.isfinite(x)) or residuals.max() > RESIDUAL_LIMIT:
        raise singular
    u = np.zeros_like(forces, dtype=float)
    u[:, free] = x.T
    return u, residuals
