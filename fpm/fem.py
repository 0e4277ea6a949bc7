"""The finite element reference (paper Sec. 4.1): static nodal displacements from ``F = K X``.

Small-strain linear elasticity on the problem's 8-node hexahedra (:mod:`fpm.elasticity`),
assembled into a block-sparse K (:mod:`fpm.assembly`), fixed nodes as Dirichlet conditions
(their displacement is zero), the load cases' nodal forces as right-hand sides, one
factorisation for all of them (:mod:`fpm.linear_solver`). Density plays no part. Nodes that
belong to no hexahedron (possible in a ``mesh``) carry no stiffness; they stay at rest and may
not be loaded.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import scipy.sparse as sp

from .assembly import keep_nodes, stiffness_matrix
from .elasticity import constitutive_matrix, min_jacobian_determinants
from .linear_solver import SingularStiffnessError, choose_method, factorize, rigid_body_modes
from .problem import Problem
from .support import unheld_reason

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
        residuals: (L,) ||K u - f|| / ||f|| over the free unknowns (reactions excluded).
        load_cases: (L,) load case names.
        method: linear solver used, ``"direct"`` or ``"amg"``.
    """

    nodes: np.ndarray
    displacements: np.ndarray
    residuals: list[float]
    load_cases: list[str]
    method: str

    @property
    def positions(self) -> np.ndarray:
        """(L, N, 3) deformed nodal positions q_i, m (paper Eq. 2)."""
        return self.nodes[None] + self.displacements

    def to_dict(self) -> dict[str, Any]:
        """JSON-able dict (nested lists of floats)."""
        return {
            "nodes": self.nodes.tolist(),
            "displacements": self.displacements.tolist(),
            "residuals": [float(r) for r in self.residuals],
            "load_cases": list(self.load_cases),
            "method": self.method,
        }

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> FemResult:
        """Inverse of :meth:`to_dict`."""
        nodes = np.asarray(data["nodes"], dtype=float).reshape(-1, 3)
        displacements = np.asarray(data["displacements"], dtype=float).reshape(-1, len(nodes), 3)
        return cls(
            nodes,
            displacements,
            [float(r) for r in data["residuals"]],
            list(data["load_cases"]),
            data["method"],
        )


def solve_fem(problem: Problem, method: str = "auto") -> FemResult:
    """Nodal displacements of ``problem`` for every load case.

    Args:
        problem: from :func:`fpm.load_problem`; needs a box, voxels or mesh geometry.
        method: ``"auto"`` (by size), ``"direct"`` or ``"amg"`` (see :mod:`fpm.linear_solver`).

    Raises:
        FemError: a network geometry, an inverted or degenerate hexahedron, a solid that is
            not held, or a force on a node that belongs to no hexahedron.
    """
    if method not in ("auto", "direct", "amg"):
        raise ValueError(f"unknown method {method!r} (use 'auto', 'direct' or 'amg')")
    hexahedra = problem.solid.elements()
    if hexahedra is None:
        raise FemError(
            f"geometry '{problem.spec.geometry.type}' has no hexahedra, so it has no FEM "
            "reference; use a box, voxels or mesh geometry"
        )
    nodes = problem.nodes
    reason = unheld_reason(
        nodes, hexahedra, problem.fixed, one_block=problem.solid.shape is not None
    )
    if reason:
        raise FemError(reason)
    bad = np.flatnonzero(min_jacobian_determinants(nodes[hexahedra]) <= 0)
    if len(bad):
        raise FemError(
            f"{len(bad)} hexahedra are inverted or degenerate (e.g. hexahedron {int(bad[0])}): "
            "check their node order (see fpm.hexahedron)"
        )
    material = problem.spec.material
    k = stiffness_matrix(
        nodes, hexahedra, constitutive_matrix(material.youngs_modulus, material.poisson_ratio)
    )
    forces = np.stack([case.dense(len(nodes)) for case in problem.load_cases])  # (L, N, 3)
    in_solid = np.zeros(len(nodes), dtype=bool)
    in_solid[hexahedra] = True
    stray = np.flatnonzero(~in_solid & np.any(forces != 0, axis=(0, 2)))
    if len(stray):
        raise FemError(f"node {int(stray[0])} is loaded but belongs to no hexahedron")
    free = np.repeat(in_solid & ~problem.fixed, 3)
    method = choose_method(int(free.sum())) if method == "auto" else method
    u, residuals = solve_dirichlet(k, forces.reshape(len(forces), -1), free, nodes, method)
    return FemResult(
        nodes.copy(),
        u.reshape(forces.shape),
        residuals.tolist(),
        [case.name for case in problem.load_cases],
        method,
    )


def solve_dirichlet(
    k: sp.bsr_matrix, forces: np.ndarray, free: np.ndarray, nodes: np.ndarray, method: str
) -> tuple[np.ndarray, np.ndarray]:
    """Solve K u = f with u = 0 on the unknowns that are not ``free``.

    Args:
        k: (n, n) stiffness, N/m, n = 3N, in 3x3 blocks (:func:`fpm.assembly.stiffness_matrix`).
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
