"""Selectors resolved to lattice nodes: which nodes ``node``, ``at``, ``nearest``, ``face`` and
``box`` name, and where a force at a point falls on the lattice's surface.

What a selection leaves to interpretation (a ``nearest`` node's distance, a point's spread) is
kept as notes for :attr:`fpm.model.problem.Problem.notes`; a miss is an error at its spec
location, ``(loc, msg)``, for :class:`fpm.model.checks.SpecError`.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

from .geometry import SurfacePoint, surface_point
from .spec import Selector

Loc = tuple[str | int, ...]  # a spec location, as a pydantic error's loc: ("fixed", 0, "box")


def dotted(loc: Loc) -> str:
    """``loc`` as the notes write it: fixed.0.box."""
    return ".".join(map(str, loc))


def fmt(v: Any) -> str:
    """A vector as [a, b, c] with 4 significant digits."""
    return "[" + ", ".join(f"{float(x):.4g}" for x in v) + "]"


class NodeFinder:
    """Resolves selectors to node indices; ``tol`` (m) is how far ``at`` may miss a node.

    ``notes`` collects what the user should know about a selection (a ``nearest`` node's
    distance), as ``field.path: text`` lines.
    """

    def __init__(
        self,
        nodes: np.ndarray,
        tol: float,
        cells: Callable[[], np.ndarray | None] = lambda: None,
    ):
        self.nodes = nodes
        self.tol = tol
        self.cells = cells  # the lattice's hexahedra, built only for a force at a point
        self.lo = nodes.min(axis=0)
        self.hi = nodes.max(axis=0)
        self.notes: list[str] = []

    def select(self, sel: Selector, loc: Loc, errors: list[tuple[Loc, str]]) -> np.ndarray:
        """Indices (ascending for face and box) of the nodes ``sel`` names; on a miss, an error
        is appended to ``errors`` at ``loc`` + the selector's field and none is returned."""
        n = len(self.nodes)
        none = np.zeros(0, dtype=np.int64)
        if sel.node is not None:
            if sel.node >= n:
                errors.append(((*loc, "node"), f"node index {sel.node} out of range (0..{n - 1})"))
                return none
            return np.array([sel.node])
        point = sel.at if sel.at is not None else sel.nearest
        if point is not None:
            dist = np.linalg.norm(self.nodes - np.asarray(point), axis=1)
            best = int(np.argmin(dist))
            if sel.nearest is not None:
                self.notes.append(
                    f"{dotted((*loc, 'nearest'))}: node {best} at {fmt(self.nodes[best])} is "
                    f"{dist[best] * 1e3:.3g} mm from the point"
                )
            elif dist[best] > self.tol:
                errors.append(
                    (
                        (*loc, "at"),
                        f"no node at {list(point)} (nearest node {best} is {dist[best]:.3g} m "
                        f"away, at {fmt(self.nodes[best])}): give a node's coordinates, or use "
                        '"nearest" to take the nearest node',
                    )
                )
                return none
            return np.array([best])
        if sel.face is not None:
            axis = "xyz".index(sel.face[0])
            edge = self.lo[axis] if sel.face[1] == "-" else self.hi[axis]
            return np.flatnonzero(np.abs(self.nodes[:, axis] - edge) <= self.tol)
        assert sel.box is not None
        lo, hi = np.asarray(sel.box[0]), np.asarray(sel.box[1])
        inside = np.all((self.nodes >= lo - self.tol) & (self.nodes <= hi + self.tol), axis=1)
        picked = np.flatnonzero(inside)
        if not len(picked):
            errors.append(
                (
                    (*loc, "box"),
                    f"selects no node: the solid's nodes span {fmt(self.lo)} to "
                    f"{fmt(self.hi)} m; move or widen the box",
                )
            )
        return picked

    def surface(self, point: Any, loc: Loc, errors: list[tuple[Loc, str]]) -> SurfacePoint | None:
        """Where ``point`` (m) falls on the lattice's surface
        (:func:`fpm.model.geometry.surface_point`); None, with an error at ``loc``, when the
        lattice has no cells or the point is more than the lattice spacing from its surface."""
        hexahedra = self.cells()
        if hexahedra is None:
            errors.append((loc, "a force at a point needs a lattice of cells (not a network)"))
            return None
        found = surface_point(self.nodes, hexahedra, np.asarray(point, dtype=float))
        x = self.nodes[hexahedra]
        spacing = float(np.median(x.max(axis=1) - x.min(axis=1), axis=0).max())
        if found.distance > spacing:
            errors.append(
                (
                    loc,
                    f"{fmt(point)} is {found.distance:.3g} m from the solid's surface (nearest "
                    f"surface point {fmt(found.point)}), more than the lattice spacing "
                    f"{spacing:.3g} m: a force at a point acts on the surface; give a point on "
                    "it (lengths in m), or select a node (node, nearest)",
                )
            )
            return None
        self.notes.append(
            f"{dotted(loc)}: acts at {fmt(found.point)} ({found.distance * 1e3:.3g} mm from "
            f"the point given), spread over nodes {found.nodes.tolist()} by weights "
            f"{fmt(found.weights)}"
        )
        return found
