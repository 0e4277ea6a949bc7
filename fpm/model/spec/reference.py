"""``reference``: the FEM reference's discretisation, the solid's own tetrahedral mesh (m) or
supplied displacements (m)."""

from __future__ import annotations

from typing import Annotated, Any, Literal

from pydantic import (
    Field,
    ValidationInfo,
    field_validator,
    model_validator,
)

from .base import Vector3, _Strict

Integration = Literal["selective", "full"]


NodeIndex = Annotated[int, Field(ge=0, lt=2**31)]
"""A node index of a tetrahedral mesh (its range is checked against the nodes later)."""


class ReferenceMesh(_Strict):
    """A tetrahedral mesh of the solid for the FEM reference (10-node tetrahedra built on it:
    :mod:`fpm.fem.tet10`). Nodes in m, tetrahedra as 4 node indices (0-based) with positive
    volume (corner 3 on the positive side of face 0-1-2). Indices in range, distinct corners,
    and no inverted or degenerate tetrahedron are checked in :func:`fpm.model.problem.load_problem`
    (errors at ``reference.mesh.tetrahedra.<element>``). ``tags``: optional cell data, one
    integer per tetrahedron, that ``material.regions`` selectors name."""

    nodes: list[Vector3] = Field(min_length=4, description="node coordinates, m")
    tetrahedra: list[tuple[NodeIndex, NodeIndex, NodeIndex, NodeIndex]] = Field(
        min_length=1, description="4 node indices (0-based) per tetrahedron, positive volume"
    )
    tags: list[int] | None = Field(
        None,
        description="cell data: an integer tag per tetrahedron (e.g. Gmsh's physical group), "
        'for material.regions selectors {"tag": t}; null = none',
        exclude_if=lambda v: v is None,
    )

    @field_validator("tags")
    @classmethod
    def _one_per_tetrahedron(cls, v: list[int] | None, info: ValidationInfo) -> list[int] | None:
        tetrahedra = info.data.get("tetrahedra")
        if v is not None and tetrahedra is not None and len(v) != len(tetrahedra):
            raise ValueError(f"need one tag per tetrahedron ({len(tetrahedra)}), got {len(v)}")
        return v


MAX_REFINE = 6
"""reference.refine: at most this many uniform refinements (8^6 = 262,144 times the elements)."""


MESH_ID_PATTERN = r"^[0-9a-f]{64}$"
"""A mesh id: the sha256 hex digest the service's ``POST /v1/meshes`` returned."""


class ReferenceSettings(_Strict):
    """The FEM reference's discretisation (docs/physics.md, *The FEM reference*).

    ``integration``: how the FEM's 8-node hexahedra are integrated (linear and neo-Hookean).

    - ``"selective"`` (default): selective reduced integration, free of volumetric locking
      near nu = 1/2: the deviatoric (shear) part of C at the 2x2x2 Gauss points, the
      volumetric part (bulk modulus) on the element's mean dilatation, which is one-point
      integration at the centre on a parallelepiped. For the linear hexahedron this is
      exactly B-bar with the mean dilatation (Hughes 1980).
    - ``"full"``: 2x2x2 Gauss integration of all of C (the paper's element; it locks as nu
      approaches 1/2: 10% too stiff at nu 0.45 on the paper's cube). The paper's examples
      name it, so Table 1 is reproduced exactly.

    The neo-Hookean reference follows the same choice: ``"selective"`` is the decoupled
    neo-Hookean solid with its volume term on each element's mean dilatation (the large-strain
    B-bar, :class:`fpm.fem.neo_hookean.MeanDilatationNeoHookean`), ``"full"`` the compressible
    one at 2x2x2 points (it locks as the linear ``"full"`` does).

    ``mesh`` / ``mesh_id``: the solid's own tetrahedral mesh (inline, or the id of one uploaded
    to the service): the linear reference is then solved on it with 10-node tetrahedra and read
    at the lattice's nodes (:mod:`fpm.fem.tet10`); ``integration`` does not apply.

    ``displacements``: a reference brought by the user (their own nonlinear FEM, measured
    displacements), one list per load case (spec order) of one ``[ux, uy, uz]`` per lattice
    node (node order of the built solid), m. When given it takes the FEM's place in the cost and
    in every reported figure, and no FEM is solved. Its shape is checked against the built solid
    in :func:`fpm.model.problem.load_problem` (errors at ``reference.displacements``); values
    must be finite.
    """

    integration: Integration = Field(
        "selective",
        description="hexahedra (linear and neo-Hookean): 'selective' (shear at 2x2x2 Gauss "
        "points, volume on the mean dilatation: B-bar, no volumetric locking) or 'full' (2x2x2 "
        "for all, the paper's)",
    )
    displacements: list[list[Vector3]] | None = Field(
        None,
        description="a supplied reference instead of the FEM: per load case, per lattice node, "
        "[ux, uy, uz], m (finite); null = solve the FEM",
    )
    mesh: ReferenceMesh | None = Field(
        None,
        description="the solid's tetrahedral mesh: the linear FEM is solved on it with 10-node "
        "tetrahedra and read at the lattice nodes (loads and fixed nodes mapped by position); "
        "null = the lattice's hexahedra",
        exclude_if=lambda v: v is None,
    )
    mesh_id: str | None = Field(
        None,
        pattern=MESH_ID_PATTERN,
        description="service only: the id of a mesh uploaded with POST /v1/meshes, used as "
        "'mesh' is",
        exclude_if=lambda v: v is None,
    )
    refine: Annotated[int, Field(ge=0, le=MAX_REFINE)] | Literal["auto", "check"] | None = Field(
        None,
        description="uniform refinements of the reference's mesh (each tetrahedron or "
        "hexahedron into 8), the lattice's forces spread over each node's share of the solid: "
        "n (the result's estimated error is the change from n - 1), 'auto' (refine until the "
        "displacements at the lattice nodes change by less than 1% or the next level is over "
        "node_budget), 'check' (the reference as given, its error estimated by one refinement) "
        "or 0 (as given, point loads, no estimate); null = 'auto' for a tetrahedral mesh, "
        "'check' for hexahedra (on lattices of at most about 7,500 nodes), 0 for a neo-Hookean "
        "or supplied reference",
        exclude_if=lambda v: v is None,
    )
    node_budget: int | None = Field(
        None,
        ge=1_000,
        le=20_000_000,
        description="refine: the most FEM nodes a refined level may have (null = 400,000)",
        exclude_if=lambda v: v is None,
    )

    @model_validator(mode="after")
    def _one_reference(self) -> ReferenceSettings:
        given = [
            name for name in ("displacements", "mesh", "mesh_id") if getattr(self, name) is not None
        ]
        if len(given) > 1:
            raise ValueError(f"give at most one of displacements, mesh, mesh_id (got {given})")
        return self

    @field_validator("refine", mode="before")
    @classmethod
    def _no_bool(cls, v: Any) -> Any:
        if isinstance(v, bool):  # JSON true is not a number of refinements
            raise ValueError("give a number of refinements (0-6), 'auto' or 'check'")
        return v
