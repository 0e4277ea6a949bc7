"""Material regions (``material.regions``): which part of the solid is which material.

A region names part of the solid by a selector (:class:`fpm.model.spec.RegionSelector`: a box, a
sphere, or a cell-data tag of the tetrahedral reference mesh) and gives it its own E, nu and
density (each defaulting to the spec's material). Regions are applied in list order, so where
two overlap the later one takes the shared part (:func:`assign`; the problem's notes say where).
What is in no region is the spec's own material, the *base* region.

- **The lattice**: a cell takes the region of its centre (for a tag: the tag of the tetrahedron
  holding its centre, :func:`locate_tags`); :func:`lattice_regions` builds the
  :class:`RegionMap` and refuses a region that takes no cell and a tag no tetrahedron carries.
  The fit gives each region present its own families and kappa (:mod:`fpm.model.stiffness`).
- **The FEM**: a hexahedron takes the region of its centroid (the lattice's cells are the FEM's
  hexahedra, so both agree); a tetrahedron its own tag, or the region of its centroid for a box
  or a sphere (:func:`assign`).

Arrays and the spec only: no :class:`fpm.model.problem.Problem` here (it is built with them).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from .spec import BASE_REGION, MaterialRegion, ProblemSpec, RegionSelector, region_names
from .tetrahedra import Location, TetMesh

Loc = tuple[str | int, ...]

NEAREST = 16
"""Tetrahedra (nearest centroids first) tried for each point before a wider search."""


@dataclass(frozen=True)
class RegionMap:
    """The regions the lattice's cells take, base first when any cell is in no region.

    Attributes:
        names: per region present, its name (``"base"`` for the spec's own material).
        materials: per region present, (E, Pa; nu; density, kg/m^3).
        cells: (H,) the region (index into ``names``) of every lattice cell, aligned with the
            solid's hexahedra.
        tagged: the tagged tetrahedral mesh the tag selectors were read from, (nodes (M, 3),
            tetrahedra (T, 4), tags (T,)), so that the FEM's elements find their tags the same
            way (:func:`element_tags`); None without tag selectors.
    """

    names: tuple[str, ...]
    materials: tuple[tuple[float, float, float], ...]
    cells: np.ndarray
    tagged: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None

    def __len__(self) -> int:
        return len(self.names)

    @property
    def counts(self) -> list[int]:
        """Cells per region."""
        return np.bincount(self.cells, minlength=len(self.names)).tolist()

    def cell_densities(self) -> np.ndarray:
        """(H,) every cell's density, kg/m^3."""
        return np.array([m[2] for m in self.materials])[self.cells]


def region_material(spec: ProblemSpec, index: int) -> tuple[float, float, float]:
    """(E, Pa; nu; density, kg/m^3) of region ``index`` of ``material.regions`` (-1: the
    material itself); a region's unset constants are the material's."""
    m = spec.material
    base = (m.youngs_modulus, m.poisson_ratio, m.density)
    if index < 0:
        return base
    r: MaterialRegion = m.regions[index]
    return (
        base[0] if r.youngs_modulus is None else r.youngs_modulus,
        base[1] if r.poisson_ratio is None else r.poisson_ratio,
        base[2] if r.density is None else r.density,
    )


def selected(selector: RegionSelector, points: np.ndarray, tags: np.ndarray | None) -> np.ndarray:
    """(P,) bool: the ``points`` (P, 3), m, a selector takes (``tags`` (P,): each point's tag,
    needed for a tag selector)."""
    if selector.box is not None:
        lo, hi = np.asarray(selector.box[0]), np.asarray(selector.box[1])
        return np.all((points >= lo) & (points <= hi), axis=1)
    if selector.sphere is not None:
        centre = np.asarray(selector.sphere.centre)
        return np.linalg.norm(points - centre, axis=1) <= selector.sphere.radius
    if tags is None:
        raise ValueError("a tag selector needs the points' tags")
    return tags == selector.tag


def assign(
    regions: list[MaterialRegion], points: np.ndarray, tags: np.ndarray | None = None
) -> tuple[np.ndarray, dict[tuple[int, int], int]]:
    """Each point's region, in list order (a later region takes what it shares with an earlier
    one).

    Returns:
        (P,) index into ``regions`` (-1: none), and {(later, earlier): points the later took
        from the earlier}.
    """
    which = np.full(len(points), -1, dtype=np.int64)
    overlaps: dict[tuple[int, int], int] = {}
    for i, region in enumerate(regions):
        inside = selected(region.selector, points, tags)
        taken = which[inside]
        for j, count in zip(*np.unique(taken[taken >= 0], return_counts=True), strict=True):
            overlaps[(i, int(j))] = int(count)
        which[inside] = i
    return which, overlaps


def locate_tags(nodes: np.ndarray, tets: np.ndarray, points: np.ndarray) -> Location:
    """Where ``points`` (P, 3), m, lie in the tagged mesh ``tets`` (T, 4) on ``nodes`` (N, 3):
    the first of the :data:`NEAREST` nearest centroids' tetrahedra holding each, else the
    lowest-numbered tetrahedron holding it; a point outside the mesh takes the tetrahedron of
    the nearest centroid (``inside`` False)."""
    return TetMesh(nodes, tets).locate(points, NEAREST, ordered=True, project=False)


def tetrahedral_mesh(spec: ProblemSpec, mesh: dict[str, Any] | None) -> dict[str, Any] | None:
    """The reference's tetrahedral mesh: the spec's ``reference.mesh``, else ``mesh`` (the
    upload ``reference.mesh_id`` names, as the service stored it), else None."""
    inline = spec.reference.mesh
    if inline is not None:
        return {"nodes": inline.nodes, "tetrahedra": inline.tetrahedra, "tags": inline.tags}
    if spec.reference.mesh_id is not None and mesh is not None:
        return mesh
    return None


def tag_selectors(spec: ProblemSpec) -> list[int]:
    """The indices of ``material.regions`` that select by a tag of the tetrahedral mesh (whose
    tags the spec carries in ``reference.mesh`` or the upload ``reference.mesh_id`` names)."""
    return [i for i, r in enumerate(spec.material.regions or []) if r.selector.tag is not None]


def lattice_regions(
    spec: ProblemSpec,
    nodes: np.ndarray,
    hexahedra: np.ndarray,
    mesh: dict[str, Any] | None = None,
) -> tuple[RegionMap | None, list[tuple[Loc, str]], list[str]]:
    """The :class:`RegionMap` of the lattice (cells ``hexahedra`` (H, 8) on ``nodes`` (N, 3)),
    with the spec errors and the notes it found; None when the spec has no regions.

    Errors (at the region's field): a tag when the reference has no tagged tetrahedral mesh, a
    tag no tetrahedron carries, a region that takes no cell (its selector misses every cell
    centre, or later regions took all of its cells). Notes: overlaps, and cell centres outside
    the tagged mesh (they take the nearest tetrahedron's tag).
    """
    regions = spec.material.regions
    if not regions:
        return None, [], []
    errors: list[tuple[Loc, str]] = []
    notes: list[str] = []
    centres = nodes[hexahedra].mean(axis=1)
    tags = None
    tagged: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
    with_tags = tag_selectors(spec)
    if with_tags:
        tetra = tetrahedral_mesh(spec, mesh)
        if tetra is None or tetra.get("tags") is None:
            if tetra is not None:
                where = "the mesh has no tags"
            elif spec.reference.mesh_id is not None:
                where = (
                    "the uploaded mesh reference.mesh_id names was not given to read them from "
                    "(in-process: fpm.load_problem(spec, mesh), or the mesh with its tags in "
                    "reference.mesh)"
                )
            else:
                where = "the spec has no tetrahedral mesh"
            for i in with_tags:
                errors.append(
                    (
                        ("material", "regions", i, "selector", "tag"),
                        "a tag names cell data of the tetrahedral reference mesh "
                        f"(reference.mesh.tags, or an uploaded mesh with tags), and {where}: "
                        "give the mesh's tags, or select by box or sphere",
                    )
                )
            return None, errors, notes
        tet_tags = np.asarray(tetra["tags"], dtype=np.int64)
        known = sorted(set(tet_tags.tolist()))
        for i in with_tags:
            if regions[i].selector.tag not in known:
                shown = ", ".join(map(str, known[:20])) + (", ..." if len(known) > 20 else "")
                errors.append(
                    (
                        ("material", "regions", i, "selector", "tag"),
                        f"no tetrahedron of the mesh has tag {regions[i].selector.tag} (its "
                        f"tags: {shown})",
                    )
                )
        if errors:
            return None, errors, notes
        tagged = (
            np.asarray(tetra["nodes"], dtype=float),
            np.asarray(tetra["tetrahedra"], dtype=np.int64),
            tet_tags,
        )
        located = locate_tags(tagged[0], tagged[1], centres)
        tags = tet_tags[located.element]
        if not located.inside.all():
            notes.append(
                f"material.regions: {int((~located.inside).sum())} lattice cell centres lie "
                "outside the tagged mesh and take the tag of the nearest tetrahedron"
            )
    which_region, overlaps = assign(regions, centres, tags)
    names = region_names(regions)
    for (later, earlier), count in sorted(overlaps.items()):
        notes.append(
            f"material.regions.{later} ({names[later]}) overlaps material.regions.{earlier} "
            f"({names[earlier]}) in {count} lattice cells: regions apply in list order, so "
            f"the later one, {names[later]}, takes them"
        )
    counts = np.bincount(which_region + 1, minlength=len(regions) + 1)
    for i in range(len(regions)):
        if counts[i + 1] == 0:
            overlapped = any(earlier == i for _, earlier in overlaps)
            why = (
                "later regions take all of its cells"
                if overlapped
                else "no lattice cell has its centre in it"
            )
            errors.append(
                (
                    ("material", "regions", i, "selector"),
                    f"region {names[i]} takes no lattice cell ({why}): move or widen it, or "
                    "drop it",
                )
            )
    if errors:
        return None, errors, notes
    present = [j for j in range(-1, len(regions)) if counts[j + 1] > 0]
    slot = np.zeros(len(regions) + 1, dtype=np.int32)
    slot[[j + 1 for j in present]] = np.arange(len(present), dtype=np.int32)
    return (
        RegionMap(
            names=tuple(BASE_REGION if j < 0 else names[j] for j in present),
            materials=tuple(region_material(spec, j) for j in present),
            cells=slot[which_region + 1],
            tagged=tagged,
        ),
        errors,
        notes,
    )


def element_tags(regions: RegionMap | None, centroids: np.ndarray) -> np.ndarray | None:
    """(E,) the tag of the tetrahedron of the tagged mesh that holds each element's centroid
    (E, 3), m (a tetrahedron of that mesh finds its own tag; a hexahedron or a refined
    tetrahedron its parent's), or None when the regions select no tag."""
    if regions is None or regions.tagged is None:
        return None
    nodes, tets, tags = regions.tagged
    return tags[locate_tags(nodes, tets, centroids).element]


def element_materials(
    spec: ProblemSpec, regions: RegionMap | None, centroids: np.ndarray
) -> tuple[np.ndarray, list[tuple[float, float, float]]]:
    """FEM elements' regions: (E,) the index into the returned materials of each element
    (centroids (E, 3), m) and the materials, (E, Pa; nu; density, kg/m^3), the spec's own
    first, then ``material.regions`` in order. ``regions``: the lattice's (their tagged mesh
    gives the elements' tags, :func:`element_tags`)."""
    which, _ = assign(spec.material.regions, centroids, element_tags(regions, centroids))
    return which + 1, [region_material(spec, j) for j in range(-1, len(spec.material.regions))]


def check_material(spec: ProblemSpec) -> list[tuple[Loc, str]]:
    """What regions and a transversely isotropic material need of the rest of the spec: the
    fit 'families+volume' (with isotropic regions also 'field', the per-cell field on top of
    each region's parameters), the linear FEM (the neo-Hookean reference is one isotropic
    material), and for the transversely isotropic material the default stiffness_scale (its
    axial scale is fitted)."""
    m = spec.material
    if not m.regions and m.type == "isotropic":
        return []
    what = "material.regions" if m.regions else "a transversely isotropic material"
    errors: list[tuple[Loc, str]] = []
    allowed = (
        ("families+volume",) if m.type == "transversely-isotropic" else ("families+volume", "field")
    )
    if spec.fpm.stiffness not in allowed:
        errors.append(
            (
                ("fpm", "stiffness"),
                f"{what} is fitted with fpm.stiffness {' or '.join(repr(a) for a in allowed)} "
                f"(each region, or the axial scale, gets its own parameters; the field refines "
                f"an isotropic region's), not {spec.fpm.stiffness!r}",
            )
        )
    if m.model != "linear" and spec.reference.displacements is None:
        errors.append(
            (
                ("material", "model"),
                f"{what} has a linear FEM reference only: use material.model 'linear' (or "
                "supply the reference in reference.displacements)",
            )
        )
    if m.type == "transversely-isotropic" and tuple(spec.fpm.stiffness_scale) != (1.0, 1.0, 1.0):
        errors.append(
            (
                ("fpm", "stiffness_scale"),
                "a transversely isotropic material's axial scale is fitted: leave "
                "stiffness_scale at [1, 1, 1]",
            )
        )
    return errors
