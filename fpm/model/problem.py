"""A validated problem as arrays: the data every other module of :mod:`fpm` works on.

Data flow: JSON -> :class:`fpm.model.spec.ProblemSpec` (schema checks) -> :func:`load_problem`
(checks that need the nodes) -> :class:`Problem` (arrays).
"""

from __future__ import annotations

import json
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from pydantic import ValidationError
from pydantic_core import InitErrorDetails, PydanticCustomError

from .geometry import Solid, SurfacePoint, build_solid, lumped_masses, spring_lengths, surface_point
from .hat_loads import hat_shares, spread_forces
from .regions import RegionMap, check_material, lattice_regions
from .spec import BoxGeometry, MeshGeometry, NetworkGeometry, ProblemSpec, Selector

Loc = tuple[str | int, ...]


class SpecError(ValueError):
    """A spec that passed the schema but does not fit its own solid; ``errors`` is [(loc, msg)].

    Converted to a pydantic :class:`ValidationError` by :func:`load_problem`, so callers see
    one kind of error for every bad spec.
    """

    def __init__(self, errors: list[tuple[Loc, str]]):
        super().__init__("; ".join(f"{'.'.join(map(str, loc))}: {msg}" for loc, msg in errors))
        self.errors = errors


@dataclass
class LoadCase:
    """Constant nodal forces of one load case.

    Attributes:
        name: label.
        nodes: (P,) indices of the stimulated nodes (unique, ascending).
        forces: (P, 3) force on each, N (forces on the same node are summed).
        given: the case as the spec gives it, when the lattice takes it otherwise
            (``fpm.loads: "hat"``: ``nodes`` and ``forces`` are then its shares,
            :mod:`fpm.model.hat_loads`); None: as given. The FEM reference spreads the given
            forces (:meth:`as_given`); the lattice and everything downstream take these.
    """

    name: str
    nodes: np.ndarray
    forces: np.ndarray
    given: LoadCase | None = None

    def as_given(self) -> LoadCase:
        """The case as the spec gives it (what the FEM reference loads)."""
        return self if self.given is None else self.given

    def dense(self, n_nodes: int) -> np.ndarray:
        """(N, 3) nodal force array."""
        f = np.zeros((n_nodes, 3))
        f[self.nodes] = self.forces
        return f


@dataclass
class Problem:
    """A problem ready to compute.

    Attributes:
        spec: the validated spec.
        solid: nodes, hexahedra, springs, masses (:class:`fpm.model.geometry.Solid`).
        fixed: (N,) bool, nodes that never move.
        load_cases: one :class:`LoadCase` per spec load case, in spec order.
        rest_lengths: (S,) spring rest lengths, m.
        h: shortest spring rest length, m (discrepancies are quoted in % of h).
        size: bounding-box diagonal, m (a node moving further than this has diverged).
        cache: derived models kept with the problem (e.g. the FPM's neighbour arrays).
        validation_cases: the spec's validation cases (never fitted), as load cases.
        notes: what the spec left to interpretation, one line each, for the user to check
            (e.g. which node a ``nearest`` selector took and how far it is from the point).
        regions: the material region of every lattice cell (:mod:`fpm.model.regions`); None
            without ``material.regions``.
        loads: how the lattice takes a nodal force, ``"node"`` or ``"hat"`` (``fpm.loads``
            with ``"auto"`` resolved: :func:`resolved_loads`).
        warnings: what the result must say of the lattice (a part one cell thick at its finest
            level: :func:`thin_part_warnings`).
    """

    spec: ProblemSpec
    solid: Solid
    fixed: np.ndarray
    load_cases: list[LoadCase]
    rest_lengths: np.ndarray
    h: float = field(init=False)
    size: float = field(init=False)
    cache: dict[str, Any] = field(init=False, repr=False, default_factory=dict)
    notes: list[str] = field(default_factory=list)
    validation_cases: list[LoadCase] = field(default_factory=list)
    regions: RegionMap | None = None
    loads: str = "node"
    warnings: list[str] = field(default_factory=list)

    def __post_init__(self) -> None:
        self.h = float(self.rest_lengths.min())
        self.size = float(np.linalg.norm(np.ptp(self.solid.nodes, axis=0)))

    @property
    def nodes(self) -> np.ndarray:
        """(N, 3) rest positions, m."""
        return self.solid.nodes

    @property
    def n_nodes(self) -> int:
        return len(self.solid.nodes)

    @property
    def all_cases(self) -> list[LoadCase]:
        """The load cases, then the validation cases (what the FEM reference solves)."""
        return self.load_cases + self.validation_cases

    def validation_problem(self) -> Problem:
        """The same solid with the validation cases as its load cases (none of its own), for
        simulating them at fitted parameters; kept in the cache."""
        found = self.cache.get("validation_problem")
        if found is None:
            found = self.cache["validation_problem"] = Problem(
                self.spec,
                self.solid,
                self.fixed,
                self.validation_cases,
                self.rest_lengths,
                regions=self.regions,
            )
        return found


def load_patterns(problem: Problem) -> list[list[int]]:
    """The load cases grouped by force pattern: cases whose nodal forces are positive multiples
    of one another (the same nodes, proportional vectors) form one group, in spec order.
    Leaving one of a group out tests only the force's size, never another load, so the
    cross-validation leaves a whole group out at a time."""
    groups: list[tuple[np.ndarray, np.ndarray, list[int]]] = []
    for j, case in enumerate(problem.load_cases):
        shape = case.forces / max(float(np.linalg.norm(case.forces)), 1e-300)
        for nodes, other, members in groups:
            if np.array_equal(nodes, case.nodes) and np.allclose(shape, other, atol=1e-9):
                members.append(j)
                break
        else:
            groups.append((case.nodes, shape, [j]))
    return [members for _, _, members in groups]


def load_problem(
    spec: dict[str, Any] | str | Path | ProblemSpec, mesh: dict[str, Any] | None = None
) -> Problem:
    """Validate ``spec`` (a dict, a JSON file path, a JSON string or a ProblemSpec) and build it.

    ``mesh``: the tetrahedral mesh ``reference.mesh_id`` names (as the service stored it:
    nodes, tetrahedra, tags), needed only when ``material.regions`` select by its tags.

    Raises:
        pydantic.ValidationError: for any bad spec; each error's ``loc`` names the field.
    """
    if isinstance(spec, ProblemSpec):
        parsed = spec
    elif isinstance(spec, dict):
        parsed = ProblemSpec.model_validate(spec)
    else:
        text = str(spec)
        if not text.lstrip().startswith("{"):
            text = Path(text).read_text()
        parsed = ProblemSpec.model_validate(json.loads(text))
    try:
        return build_problem(parsed, mesh)
    except SpecError as e:
        raise ValidationError.from_exception_data(
            "ProblemSpec",
            [
                InitErrorDetails(type=PydanticCustomError("spec", msg), loc=loc, input=None)
                for loc, msg in e.errors
            ],
        ) from None


def build_problem(spec: ProblemSpec, mesh: dict[str, Any] | None = None) -> Problem:
    """Arrays for a schema-valid spec; raises :class:`SpecError` where it does not fit its solid
    (``mesh`` as :func:`load_problem`'s)."""
    _check_indices(spec)
    solid = build_solid(spec.geometry, spec.material.density)
    errors: list[tuple[Loc, str]] = []
    lengths = spring_lengths(solid.nodes, solid.springs)
    if len(lengths) and lengths.min() <= 0:
        errors.append((("geometry",), "a spring joins two nodes at the same point"))
        raise SpecError(errors)
    h = float(lengths.min())
    finder = _NodeFinder(solid.nodes, tol=1e-3 * h, cells=solid.elements)

    fixed = np.zeros(len(solid.nodes), dtype=bool)
    for i, sel in enumerate(spec.fixed):
        picked = finder.select(sel, ("fixed", i), errors)
        fixed[picked] = True

    load_cases = _load_cases(spec.load_cases, "load_cases", finder, fixed, errors)
    validation = _load_cases(spec.validation_cases, "validation_cases", finder, fixed, errors)
    _check_stiffness_mode(spec, errors)
    _check_supplied_reference(spec, len(solid.nodes), errors)
    _check_refine(spec, errors)
    errors.extend(check_material(spec))
    warnings = thin_part_warnings(spec, solid)
    regions = _material_regions(spec, solid, mesh, errors, finder.notes)
    if spec.fpm.loads == "hat" and solid.elements() is None:
        errors.append(
            (("fpm", "loads"), "'hat' spreads a force over its node's cells: a network has none")
        )
    if errors:
        raise SpecError(errors)
    loads = resolved_loads(spec, solid.elements() is not None)
    if loads == "hat":
        load_cases, validation = (
            _hat_loads(solid, fixed, load_cases),
            _hat_loads(solid, fixed, validation),
        )
    elif spec.fpm.loads == "node" and _spreads(spec) and solid.elements() is not None:
        finder.notes.append(
            "fpm.loads = 'node': the lattice takes each force at its node, where the refined "
            "reference spreads it over the node's share of the surface; 'hat' (what 'auto', "
            "the default, takes here) takes it as the reference does (on the bench's organ mesh "
            "at 3.25 mm the worst unseen press 10.8% -> 6.4%, on the voxel ellipsoid at 5 mm "
            "with refine 2 5.4% -> 3.4%; docs/howto/reference-error.md)"
        )
    return Problem(
        spec,
        solid,
        fixed,
        load_cases,
        lengths,
        notes=finder.notes,
        validation_cases=validation,
        regions=regions,
        loads=loads,
        warnings=warnings,
    )


def _material_regions(
    spec: ProblemSpec,
    solid: Solid,
    mesh: dict[str, Any] | None,
    errors: list[tuple[Loc, str]],
    notes: list[str],
) -> RegionMap | None:
    """The lattice cells' material regions (:func:`fpm.model.regions.lattice_regions`); a region
    of another density changes the lumped masses of its cells' corners."""
    hexahedra = solid.elements()
    if not spec.material.regions or hexahedra is None:
        return None
    regions, found, more = lattice_regions(spec, solid.nodes, hexahedra, mesh)
    errors.extend(found)
    notes.extend(more)
    if regions is not None and any(m[2] != spec.material.density for m in regions.materials):
        solid.masses = lumped_masses(solid.nodes, hexahedra, regions.cell_densities())
    return regions


def select_nodes(problem: Problem, selector: Selector) -> np.ndarray:
    """(K,) indices of the lattice nodes ``selector`` names in ``problem`` (as :func:`load_problem`
    resolved it; the spec was checked, so it names at least one)."""
    errors: list[tuple[Loc, str]] = []
    return _NodeFinder(problem.nodes, tol=1e-3 * problem.h).select(selector, (), errors)


def _load_cases(
    cases: list[Any],
    field: str,
    finder: _NodeFinder,
    fixed: np.ndarray,
    errors: list[tuple[Loc, str]],
) -> list[LoadCase]:
    """The spec's ``cases`` (its ``field``: load_cases or validation_cases) as arrays; bad
    selections are appended to ``errors`` at their location."""
    load_cases = []
    for c, case in enumerate(cases):
        idx: list[int] = []
        vec: list[np.ndarray] = []
        for f, force in enumerate(case.forces):
            loc: Loc = (field, c, "forces", f)
            where = _dotted((*loc, force.kind))
            if force.point is not None:
                spread = finder.surface(force.point, (*loc, "point"), errors)
                if spread is None:
                    continue
                free = spread.weights * ~fixed[spread.nodes]
                if not free.any():
                    errors.append(((*loc, "point"), _all_fixed(spread.nodes)))
                    continue
                if not free.all():
                    finder.notes.append(
                        f"{where}: {100 * (1 - free.sum()):.3g}% of the force falls on fixed "
                        "nodes of its cell and goes to the supports"
                    )
                keep = free > 0
                idx.extend(spread.nodes[keep].tolist())
                vec.extend(w * np.asarray(force.vector, dtype=float) for w in free[keep])
                continue
            picked = finder.select(force, loc, errors)
            free = picked[~fixed[picked]]
            if len(picked) and not len(free):
                errors.append((loc, _all_fixed(picked)))
            elif len(free) < len(picked):
                finder.notes.append(
                    f"{where}: {len(picked) - len(free)} of its {len(picked)} nodes are fixed and "
                    "take no force"
                )
            picked = free
            if not len(picked):
                continue
            vector = np.asarray(force.vector, dtype=float)
            if force.distribute:
                vector = vector / len(picked)
            elif len(picked) > 1:
                finder.notes.append(
                    f"{where}: {len(picked)} nodes each get {_fmt(force.vector)} N (total "
                    f'{_fmt(vector * len(picked))} N); set "distribute": true to split the '
                    "vector over them instead"
                )
            idx.extend(picked.tolist())
            vec.extend([vector] * len(picked))
        nodes, inverse = np.unique(np.asarray(idx, dtype=np.int64), return_inverse=True)
        forces = np.zeros((len(nodes), 3))
        np.add.at(forces, inverse, np.asarray(vec, dtype=float).reshape(-1, 3))
        if len(vec) and not np.any(forces):
            errors.append(((field, c, "forces"), "all forces are zero"))
        load_cases.append(LoadCase(case_name(case.name, c), nodes, forces))
    return load_cases


def case_name(name: str | None, index: int) -> str:
    """How results, warnings and the status answer name the spec's case ``index`` (0-based) of
    ``name``: that name, else "load case {index + 1}"."""
    return name or f"load case {index + 1}"


def resolved_refine(spec: ProblemSpec) -> int | str:
    """What ``reference.refine`` means for ``spec``: as given, else ``"auto"`` for a tetrahedral
    mesh, ``"check"`` for the linear hexahedra, 0 for a neo-Hookean or supplied reference
    (:mod:`fpm.fem.refine`; 0 and "check" load the forces at their nodes, every other value
    spreads each over its node's hat, :mod:`fpm.fem.loads`)."""
    reference = spec.reference
    if reference.refine is not None:
        return reference.refine
    if reference.displacements is not None or spec.material.model != "linear":
        return 0
    if reference.mesh is not None or reference.mesh_id is not None:
        return "auto"
    return "check"


def _spreads(spec: ProblemSpec) -> bool:
    """Whether ``spec``'s FEM reference spreads each lattice force over its node's hat (a
    refined or tetrahedral reference: :func:`resolved_refine` neither 0 nor "check")."""
    return resolved_refine(spec) not in (0, "check")


def resolved_loads(spec: ProblemSpec, cells: bool) -> str:
    """``fpm.loads`` as the lattice takes its forces: as given, or for ``"auto"`` ``"hat"``
    where the reference spreads them (:func:`_spreads`) and the lattice has ``cells``, else
    ``"node"`` (the paper's; a supplied, neo-Hookean or unrefined reference loads the nodes)."""
    if spec.fpm.loads != "auto":
        return spec.fpm.loads
    return "hat" if cells and _spreads(spec) else "node"


def _hat_loads(solid: Solid, fixed: np.ndarray, cases: list[LoadCase]) -> list[LoadCase]:
    """``cases`` as the lattice takes them with ``fpm.loads: "hat"`` (each keeps itself as
    ``given``, what the reference loads)."""
    if not cases:
        return cases
    hexahedra = solid.elements()
    assert hexahedra is not None
    loaded = np.unique(np.concatenate([case.nodes for case in cases]))
    shares = hat_shares(solid.nodes, hexahedra, loaded)
    return [
        LoadCase(case.name, *spread_forces(shares, case.nodes, case.forces, fixed), given=case)
        for case in cases
    ]


def _check_stiffness_mode(spec: ProblemSpec, errors: list[tuple[Loc, str]]) -> None:
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


def thin_part_warnings(spec: ProblemSpec, solid: Solid) -> list[str]:
    """A lattice made from an organ's mesh (``voxels`` or ``mesh`` geometry with the mesh in
    ``reference.mesh`` or ``mesh_id``) that is one cell thick over a part
    (:func:`fpm.model.geometry.thin_parts`) at its finest cells: a warning with the largest
    part's place and size. The part is modelled as it is (a single layer of cells bends, but
    too stiffly); ``spec from-mesh`` refines such parts where it can
    (:mod:`fpm.io.meshes.graded`), so what remains is thinner than its finest level."""
    from .geometry import thin_parts

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
        f"{_fmt(centre)} m ({len(parts)} such part(s), cells of {_fmt(size)} m there): modelled "
        "as it is, a single layer of cells, which bends too stiffly; a finer lattice (--nodes "
        "more, or a smaller --spacing) resolves more of it"
    ]


def _check_refine(spec: ProblemSpec, errors: list[tuple[Loc, str]]) -> None:
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


def _check_supplied_reference(
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


def _all_fixed(picked: np.ndarray) -> str:
    if len(picked) == 1:
        return f"node {int(picked[0])} is fixed; a force on it does nothing (load a free node)"
    return (
        f"all {len(picked)} nodes it selects are fixed; a force on them does nothing (select "
        "free nodes)"
    )


def _dotted(loc: Loc) -> str:
    return ".".join(map(str, loc))


def _fmt(v: Any) -> str:
    """A vector as [a, b, c] with 4 significant digits."""
    return "[" + ", ".join(f"{float(x):.4g}" for x in v) + "]"


def _check_indices(spec: ProblemSpec) -> None:
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


class _NodeFinder:
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
                    f"{_dotted((*loc, 'nearest'))}: node {best} at {_fmt(self.nodes[best])} is "
                    f"{dist[best] * 1e3:.3g} mm from the point"
                )
            elif dist[best] > self.tol:
                errors.append(
                    (
                        (*loc, "at"),
                        f"no node at {list(point)} (nearest node {best} is {dist[best]:.3g} m "
                        f"away, at {_fmt(self.nodes[best])}): give a node's coordinates, or use "
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
                    f"selects no node: the solid's nodes span {_fmt(self.lo)} to "
                    f"{_fmt(self.hi)} m; move or widen the box",
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
                    f"{_fmt(point)} is {found.distance:.3g} m from the solid's surface (nearest "
                    f"surface point {_fmt(found.point)}), more than the lattice spacing "
                    f"{spacing:.3g} m: a force at a point acts on the surface; give a point on "
                    "it (lengths in m), or select a node (node, nearest)",
                )
            )
            return None
        self.notes.append(
            f"{_dotted(loc)}: acts at {_fmt(found.point)} ({found.distance * 1e3:.3g} mm from "
            f"the point given), spread over nodes {found.nodes.tolist()} by weights "
            f"{_fmt(found.weights)}"
        )
        return found
