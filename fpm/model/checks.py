"""The checks of a problem that the schema cannot make: the indices a solid is built from, the
stiffness mode against the geometry, ``reference.refine`` and ``reference.displacements``
against the reference; and the warning of a lattice one cell thick over a part.

Each check appends ``(loc, msg)`` to an error list (the index checks, which must pass before the
solid can be built, raise theirs at once), which :func:`fpm.model.problem.load_problem` raises
as one pydantic :class:`~pydantic.ValidationError` (through :class:`SpecError`).
"""

from __future__ import annotations

import numpy as np

from .geometry import Solid, thin_parts
from .selectors import Loc, fmt
from .spec import BoxGeometry, MeshGeometry, NetworkGeometry, ProblemSpec


class SpecError(ValueError):
    """A spec that passed the schema but does not fit its own solid; ``errors`` is [(loc, msg)].

    Converted to a pydantic :class:`ValidationError` by :func:`fpm.model.problem.load_problem`, so
    callers see one kind of error for every bad spec.
    """

    def __init__(self, errors: list[tuple[Loc, str]]):
        super().__init__("; ".join(f"{'.'.join(map(str, loc))}: {msg}" for loc, msg in errors))
        self.errors = errors


def check_indices(spec: ProblemSpec) -> None:
    """Index checks that must pass before the solid can be built."""
    g = spec.geometry
    errors: list[tuple[Loc, str]] = []
    if isinstance(g, MeshGeometry):
        n = len(g.nodes)
        for e, hexa in enumerate(g.hexahedra):
            if max(hexa) >= n or min(hexa) < 0:
                bad = max(hexa) if max(hexa) >= n else min(hexa)
                errors.append(
                    (("geometry", "hexahedra", e), f"node index {bad} out of range (0..{n - 1})")
                )
            elif len(set(hexa)) != 8:
                errors.append((("geometry", "hexahedra", e), "a hexahedron needs 8 distinct nodes"))
        if not errors:  # a node in no hexahedron would have no mass and no stiffness
            used = np.zeros(n, dtype=bool)
            used[np.asarray(g.hexahedra).ravel()] = True
            errors.extend(
                (("geometry", "nodes", int(i)), f"node {i} belongs to no hexahedron")
                for i in np.flatnonzero(~used)
            )
    if isinstance(g, NetworkGeometry):
        n = len(g.nodes)
        for s, (a, b) in enumerate(g.springs):
            if max(a, b) >= n or min(a, b) < 0:
                errors.append((("geometry", "springs", s), f"node index out of range (0..{n - 1})"))
            elif a == b:
                errors.append((("geometry", "springs", s), "a spring needs two distinct nodes"))
        if isinstance(g.masses, list) and len(g.masses) != n:
            errors.append(
                (("geometry", "masses"), f"need {n} masses (one per node), got {len(g.masses)}")
            )
    mesh = spec.reference.mesh
    if mesh is not None:
        from .tetrahedra import check_tetrahedra

        errors.extend(
            (("reference", "mesh", field) + (() if index is None else (index,)), msg)
            for field, index, msg in check_tetrahedra(
                np.asarray(mesh.nodes, dtype=float), np.asarray(mesh.tetrahedra, dtype=np.int64)
            )
        )
    if errors:
        raise SpecError(errors[:20])


def check_stiffness_mode(spec: ProblemSpec, errors: list[tuple[Loc, str]]) -> None:
    """families+volume (and field, built on it) needs cells (hexahedra) with face diagonals; a
    field needs two load cases or more (its smoothness is chosen by leaving one out) and the
    two-stage method."""
    mode = spec.fpm.stiffness
    if mode == "field":
        if len(spec.load_cases) < 2:
            errors.append(
                (
                    ("load_cases",),
                    f"fpm.stiffness 'field' needs at least two load cases, not "
                    f"{len(spec.load_cases)}: its smoothness weight is chosen by leaving one "
                    "load case out at a time (nothing to cross-validate with one); add a load "
                    "case, or use 'families+volume'",
                )
            )
        if spec.annealing.method != "two-stage":
            errors.append(
                (
                    ("annealing", "method"),
                    "fpm.stiffness 'field' is fitted on static equilibria after the two-stage "
                    "method's stiffness stage: use annealing.method 'two-stage'",
                )
            )
    if mode not in ("families+volume", "field"):
        return
    g = spec.geometry
    if isinstance(g, NetworkGeometry):
        errors.append(
            (
                ("fpm", "stiffness"),
                f"a network geometry has no cells for the volume term of {mode!r}: "
                "use 'single' or 'families'",
            )
        )
    elif g.connectivity == "axis":
        errors.append(
            (
                ("fpm", "stiffness"),
                f"{mode!r} needs face diagonals for shear (geometry.connectivity "
                "'axis+face' or 'full'; an 'axis' lattice has no shear stiffness): change the "
                "connectivity, or use 'single' or 'families'",
            )
        )


def check_refine(spec: ProblemSpec, errors: list[tuple[Loc, str]]) -> None:
    """reference.refine (n >= 1, 'auto', 'check') refines the linear FEM reference only."""
    reference = spec.reference
    if reference.refine in (None, 0):
        return
    loc: Loc = ("reference", "refine")
    if reference.displacements is not None:
        errors.append(
            (
                loc,
                "a supplied reference (reference.displacements) is not solved, so it cannot be "
                "refined: drop reference.refine",
            )
        )
    elif spec.material.model != "linear":
        errors.append(
            (
                loc,
                "refinement applies to the linear reference: use material.model 'linear', or "
                "drop reference.refine",
            )
        )


def check_supplied_reference(
    spec: ProblemSpec, n_nodes: int, errors: list[tuple[Loc, str]]
) -> None:
    """reference.displacements: one (N, 3) field per load case, then one per validation case."""
    supplied = spec.reference.displacements
    if supplied is None:
        return
    field_loc: Loc = ("reference", "displacements")
    cases, extra = len(spec.load_cases), len(spec.validation_cases)
    if len(supplied) != cases + extra:
        more = (
            f" and one per validation case after them ({extra}): the validation figures need "
            "their own fields (or drop validation_cases)"
            if extra
            else ""
        )
        errors.append(
            (field_loc, f"need one field per load case ({cases}){more}; got {len(supplied)}")
        )
    for c, one in enumerate(supplied):
        if len(one) != n_nodes:
            errors.append(
                (
                    (*field_loc, c),
                    f"need one [ux, uy, uz] per lattice node ({n_nodes}), got {len(one)}",
                )
            )


def thin_part_warnings(spec: ProblemSpec, solid: Solid) -> list[str]:
    """A lattice made from an organ's mesh (``voxels`` or ``mesh`` geometry with the mesh in
    ``reference.mesh`` or ``mesh_id``) that is one cell thick over a part
    (:func:`fpm.model.geometry.thin_parts`) at its finest cells: a warning with the largest
    part's place and size. The part is modelled as it is (a single layer of cells bends, but
    too stiffly); ``spec from-mesh`` refines such parts where it can
    (:mod:`fpm.io.meshes.graded`), so what remains is thinner than its finest level."""
    g = spec.geometry
    organ = spec.reference.mesh is not None or spec.reference.mesh_id is not None
    hexahedra = solid.elements()
    if not organ or isinstance(g, NetworkGeometry | BoxGeometry) or hexahedra is None:
        return []
    parts = thin_parts(hexahedra)
    if not parts:
        return []
    part = parts[0]
    centre = solid.nodes[hexahedra[part]].mean(axis=(0, 1))
    size = np.median(np.ptp(solid.nodes[hexahedra[part]], axis=1), axis=0)
    where = f"geometry.hexahedra[{int(part[0])}]" if isinstance(g, MeshGeometry) else "geometry"
    return [
        f"{where}: the lattice is one cell thick over a part of {len(part)} cells around "
        f"{fmt(centre)} m ({len(parts)} such part(s), cells of {fmt(size)} m there): modelled "
        "as it is, a single layer of cells, which bends too stiffly; a finer lattice (--nodes "
        "more, or a smaller --spacing) resolves more of it"
    ]
