"""``geometry``, node selectors and forces: the solid's lattice (lengths in m), ``fixed``,
``load_cases`` (forces in N)."""

from __future__ import annotations

from typing import Annotated, Literal

from pydantic import (
    Field,
    field_validator,
    model_validator,
)

from .base import Connectivity, Face, Vector3, _Strict, exactly_one


class BoxGeometry(_Strict):
    """A rectangular block meshed as a regular lattice of nodes[0] x nodes[1] x nodes[2] nodes."""

    type: Literal["box"] = "box"
    size: tuple[float, float, float] = Field(description="edge lengths, m")
    nodes: tuple[int, int, int] = Field(description="nodes along x, y, z (each at least 2)")
    origin: Vector3 = (0.0, 0.0, 0.0)
    connectivity: Connectivity = "full"

    @field_validator("size")
    @classmethod
    def _positive_size(cls, v: tuple[float, float, float]) -> tuple[float, float, float]:
        if min(v) <= 0:
            raise ValueError("every edge length must be > 0")
        return v

    @field_validator("nodes")
    @classmethod
    def _two_nodes(cls, v: tuple[int, int, int]) -> tuple[int, int, int]:
        if min(v) < 2:
            raise ValueError("need at least 2 nodes along each axis")
        return v


class VoxelGeometry(_Strict):
    """An occupancy grid: ``occupancy[i][j][k]`` true fills the cell i (x), j (y), k (z)."""

    type: Literal["voxels"] = "voxels"
    occupancy: list[list[list[bool]]] = Field(description="cells along x, y, z; 1 = solid")
    spacing: tuple[float, float, float] = Field(description="cell edge lengths, m")
    origin: Vector3 = (0.0, 0.0, 0.0)
    connectivity: Connectivity = "full"

    @field_validator("spacing")
    @classmethod
    def _positive_spacing(cls, v: tuple[float, float, float]) -> tuple[float, float, float]:
        if min(v) <= 0:
            raise ValueError("every spacing must be > 0")
        return v

    @field_validator("occupancy")
    @classmethod
    def _rectangular(cls, v: list[list[list[bool]]]) -> list[list[list[bool]]]:
        if not v or not v[0] or not v[0][0]:
            raise ValueError("occupancy must be a non-empty 3-D grid")
        ny, nz = len(v[0]), len(v[0][0])
        if any(len(p) != ny or any(len(r) != nz for r in p) for p in v):
            raise ValueError("occupancy must be rectangular (every row the same length)")
        if not any(c for p in v for r in p for c in r):
            raise ValueError("occupancy has no solid cell")
        return v


class MeshGeometry(_Strict):
    """Explicit nodes and 8-node hexahedra (node order: see :mod:`fpm.model.hexahedron`)."""

    type: Literal["mesh"] = "mesh"
    nodes: list[Vector3] = Field(min_length=8, description="node coordinates, m")
    hexahedra: list[tuple[int, int, int, int, int, int, int, int]] = Field(min_length=1)
    connectivity: Connectivity = "full"
    levels: list[Annotated[int, Field(ge=0, le=8)]] | None = Field(
        default=None,
        description="per hexahedron, its level in a graded lattice: a cell of level L is "
        "2^-L the size of a level-0 cell, and its springs take 2^-L of their family's k "
        "(k ~ mu h); None: all 0 (one cell size)",
    )

    @model_validator(mode="after")
    def _levels_per_cell(self) -> MeshGeometry:
        if self.levels is not None and len(self.levels) != len(self.hexahedra):
            raise ValueError(
                f"levels: give one per hexahedron ({len(self.hexahedra)}), not {len(self.levels)}"
            )
        return self


class NetworkGeometry(_Strict):
    """A mass-spring network given directly (surface models, paper Fig. 4a-d). No FEM."""

    type: Literal["network"] = "network"
    nodes: list[Vector3] = Field(min_length=2, description="node coordinates, m")
    springs: list[tuple[int, int]] = Field(min_length=1, description="node index pairs")
    masses: float | list[float] = Field(description="node mass, kg: one for all, or one per node")

    @field_validator("masses")
    @classmethod
    def _positive_masses(cls, v: float | list[float]) -> float | list[float]:
        if min(v if isinstance(v, list) else [v]) <= 0:
            raise ValueError("every node mass must be > 0")
        return v


Geometry = Annotated[
    BoxGeometry | VoxelGeometry | MeshGeometry | NetworkGeometry, Field(discriminator="type")
]


SELECTOR_FIELDS = ("face", "node", "at", "nearest", "box")
"""The ways a :class:`Selector` (and a :class:`Force`) names nodes; give exactly one."""


class Selector(_Strict):
    """Selects nodes: exactly one of ``face``, ``node``, ``at``, ``nearest``, ``box``.

    - ``node``: one node by index;
    - ``at``: the node at a point (it must lie within 1e-3 h of a node; else an error);
    - ``nearest``: the node nearest a point, however far (the distance is reported in
      :attr:`fpm.model.problem.Problem.notes`): for points read off a picture or another mesh;
    - ``face``: every node on that side of the solid's bounding box;
    - ``box``: every node inside an axis-aligned box (a box that holds no node is an error).
    """

    face: Face | None = Field(
        None, description="all nodes on that side of the solid's bounding box"
    )
    node: int | None = Field(None, ge=0, description="a node index")
    at: Vector3 | None = Field(None, description="the node at this point, m")
    nearest: Vector3 | None = Field(
        None, description="the node nearest this point, m (its distance is reported)"
    )
    box: tuple[Vector3, Vector3] | None = Field(
        None, description="all nodes inside [[x0,y0,z0],[x1,y1,z1]], m"
    )

    @field_validator("box")
    @classmethod
    def _ordered_corners(cls, v: tuple[Vector3, Vector3] | None) -> tuple[Vector3, Vector3] | None:
        if v is not None and any(lo > hi for lo, hi in zip(v[0], v[1], strict=True)):
            raise ValueError(
                "give the low corner first: [[x0,y0,z0],[x1,y1,z1]] with x0 <= x1, y0 <= y1, "
                "z0 <= z1"
            )
        return v

    @model_validator(mode="after")
    def _exactly_one(self) -> Selector:
        return exactly_one(self, SELECTOR_FIELDS)

    @property
    def kind(self) -> str:
        """Which selector field is given (``"face"``, ``"node"``, ...)."""
        return next(n for n in SELECTOR_FIELDS if getattr(self, n) is not None)

    @property
    def single(self) -> bool:
        """True if it names one node (``node``, ``at``, ``nearest``)."""
        return self.face is None and self.box is None


FORCE_FIELDS = (*SELECTOR_FIELDS, "point")
"""The ways a :class:`Force` says where it acts; give exactly one."""


class Force(Selector):
    """A constant force, N, on the nodes of one selector (``node``, ``at``, ``nearest``,
    ``face`` or ``box``), or at a ``point`` of the solid's surface: exactly one.

    On a selector of several nodes, ``vector`` goes to each node, so the total force is
    ``vector`` times the number of nodes; with ``"distribute": true`` the vector is split
    evenly over them instead (a patch load: the total force is ``vector``). Fixed nodes among
    a face's or box's nodes take no share (they are reported in
    :attr:`fpm.model.problem.Problem.notes`); a force on a single fixed node, or on a selection that
    is all fixed, is an error.

    ``point``: the force acts at that point of the solid's surface (m), not at a node: the
    point is taken to the nearest point of the lattice's surface (within the lattice spacing h
    of it, else an error with its distance) and the force is spread over the 4 nodes of the
    surface cell face it falls on by their trilinear shape functions there
    (:func:`fpm.model.geometry.surface_point`): the shares sum to the force and their
    centroid is the point. The FEM reference sees the same nodal forces, each spread over its
    node's share of the solid (:mod:`fpm.fem.loads`).
    """

    point: Vector3 | None = Field(
        None,
        description="the force acts at this point of the solid's surface, m (within the "
        "lattice spacing of it), spread over the nodes of the surface cell it falls on by "
        "their shape functions",
        exclude_if=lambda v: v is None,
    )
    vector: Vector3 = Field(description="force, N (per node, or in total with distribute)")
    distribute: bool = Field(
        False,
        description="split vector evenly over the selected nodes (total force = vector); "
        "false: every selected node gets vector",
    )

    @model_validator(mode="after")
    def _exactly_one(self) -> Force:
        return exactly_one(self, FORCE_FIELDS)

    @property
    def kind(self) -> str:
        """Where the force acts: ``"point"`` or the selector field given."""
        return next(n for n in FORCE_FIELDS if getattr(self, n) is not None)


class LoadCase(_Strict):
    """A set of constant nodal forces applied together, from rest (forces on the same node add
    up)."""

    name: str | None = None
    forces: list[Force] = Field(min_length=1)
