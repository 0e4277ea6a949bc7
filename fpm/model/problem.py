"""A validated problem as arrays: the data every other module of :mod:`fpm` works on.

Data flow: JSON -> :class:`fpm.model.spec.ProblemSpec` (schema checks) -> :func:`load_problem`
(checks that need the nodes) -> :class:`Problem` (arrays).
"""

from __future__ import annotations

import json
import threading
import weakref
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from pydantic import ValidationError
from pydantic_core import InitErrorDetails, PydanticCustomError

from .checks import (
    SpecError,
    check_indices,
    check_refine,
    check_stiffness_mode,
    check_supplied_reference,
    thin_part_warnings,
)
from .geometry import Solid, build_solid, hexahedron_volumes, lumped_masses, spring_lengths
from .hat_loads import hat_shares, spread_forces
from .regions import RegionMap, check_material, lattice_regions
from .selectors import Loc, NodeFinder, dotted, fmt
from .spec import MeshGeometry, ProblemSpec, Selector

if TYPE_CHECKING:
    import scipy.sparse as sp

    from .perturbed_list import PerturbedListCache
    from .volume import Cells


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
class ProblemCache:
    """What is derived from a :class:`Problem` once and kept with it: each attribute is None
    until the function named beside it fills it on first use. Spring arrays are in the solid's
    spring order (S springs), cell arrays in its hexahedra's (H cells).

    The dynamics and fitting layers' objects sit above :mod:`fpm.model`, which imports
    nothing of theirs: their attributes are typed ``Any`` (or containers of it) and name
    their class here; the function that fills one returns it with its own type.

    Attributes:
        cells: the lattice cells, :class:`fpm.model.volume.Cells`
            (:func:`fpm.model.forces.cells`).
        cell_shares: (S, H) sparse CSR, the share of its family's k each cell gives each spring,
            dimensionless (:func:`fpm.model.shares.cell_shares`).
        assembly_weights: (S,) the row sums of ``cell_shares``, dimensionless
            (:func:`fpm.model.stiffness.assembly_weights`).
        axis_factors: (S,) per-spring factor of the spec's stiffness_scale, dimensionless
            (:func:`fpm.model.stiffness.axis_factors`; stays None for a scale of (1, 1, 1)).
        validation_problem: the solid with the validation cases as its load cases
            (:meth:`Problem.validation_problem`).
        region_weights: (R, S) per material region and spring, the share its cells give it,
            dimensionless (:func:`fpm.model.materials.region_weights`).
        axial_cosines: (S,) ``(e . a)^2`` of each spring's rest direction and the material axis,
            dimensionless (:func:`fpm.model.materials.spring_axial_cosines`).
        modes: the slowest modes of the last stiffness asked for: ((the stiffness parameters'
            bytes, depth in layers or None), {a perturbed list's nodes' bytes:
            ``fpm.dynamics.modes.Modes``}) (:func:`fpm.dynamics.step_caps.case_models`).
        fpm_model: the problem's ``fpm.dynamics.simulation.FpmModel``
            (:func:`fpm.dynamics.simulation.fpm_model`).
        spring_lists: the perturbed lists over the springs' adjacency, shared by the static
            solvers (:func:`fpm.dynamics.spring_system.spring_lists`).
        spring_systems: free nodes' bytes -> ``fpm.dynamics.spring_system.SpringSystem``, held
            by weak reference: a system lives as long as some solver keeps it
            (:func:`fpm.dynamics.spring_system.shared_system`).
        static_solvers: a ``threading.local`` whose ``solver`` is this thread's
            ``fpm.dynamics.equilibrium.StaticSolver``
            (:func:`fpm.dynamics.equilibrium.static_solver`).
        reduced_units: (depth in layers or None, free nodes' bytes) ->
            ``fpm.fitting.unit_matrices.UnitMatrices``, one perturbed list's K_p at rest
            (:func:`fpm.fitting.unit_matrices.unit_matrices`); set back to None by the damping
            stage once its reduced fit is done (:mod:`fpm.fitting.damping.polish`).
    """

    cells: Cells | None = None
    cell_shares: sp.csr_matrix | None = None
    assembly_weights: np.ndarray | None = None
    axis_factors: np.ndarray | None = None
    validation_problem: Problem | None = None
    region_weights: np.ndarray | None = None
    axial_cosines: np.ndarray | None = None
    modes: tuple[tuple[bytes, int | None], dict[bytes, Any]] | None = None
    fpm_model: Any = None
    spring_lists: PerturbedListCache | None = None
    spring_systems: weakref.WeakValueDictionary[bytes, Any] | None = None
    static_solvers: threading.local | None = None
    reduced_units: dict[tuple[int | None, bytes], Any] | None = None


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
        spacing: the lattice's cell size, m, what the stiffness scales with (k ~ mu spacing):
            :func:`lattice_spacing`. It is h on a regular lattice; on a lattice conformed to a
            mesh's surface, whose moved nodes make some springs many times shorter than the
            cells, it is the cells' typical size.
        size: bounding-box diagonal, m (a node moving further than this has diverged).
        cache: what is derived from the problem once and kept with it (e.g. the FPM's
            neighbour arrays): :class:`ProblemCache`.
        validation_cases: the spec's validation cases (never fitted), as load cases.
        notes: what the spec left to interpretation, one line each, for the user to check
            (e.g. which node a ``nearest`` selector took and how far it is from the point).
        regions: the material region of every lattice cell (:mod:`fpm.model.regions`); None
            without ``material.regions``.
        loads: how the lattice takes a nodal force, ``"node"`` or ``"hat"`` (``fpm.loads``
            with ``"auto"`` resolved: :func:`resolved_loads`).
        warnings: what the result must say of the lattice (a part one cell thick at its finest
            level: :func:`fpm.model.checks.thin_part_warnings`).
    """

    spec: ProblemSpec
    solid: Solid
    fixed: np.ndarray
    load_cases: list[LoadCase]
    rest_lengths: np.ndarray
    h: float = field(init=False)
    spacing: float = field(init=False)
    size: float = field(init=False)
    cache: ProblemCache = field(init=False, repr=False, default_factory=ProblemCache)
    notes: list[str] = field(default_factory=list)
    validation_cases: list[LoadCase] = field(default_factory=list)
    regions: RegionMap | None = None
    loads: str = "node"
    warnings: list[str] = field(default_factory=list)

    def __post_init__(self) -> None:
        self.h = float(self.rest_lengths.min())
        self.spacing = lattice_spacing(self.solid, self.spec, self.h)
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
        found = self.cache.validation_problem
        if found is None:
            found = self.cache.validation_problem = Problem(
                self.spec,
                self.solid,
                self.fixed,
                self.validation_cases,
                self.rest_lengths,
                regions=self.regions,
            )
        return found


def lattice_spacing(solid: Solid, spec: ProblemSpec, h: float) -> float:
    """The cell size the lattice's stiffness scales with, m.

    A box or a voxel lattice is regular: its shortest spring ``h``. A mesh of hexahedra (a
    lattice conformed to a surface, a graded lattice, a user's mesh): the median over its cells
    of the cube root of the volume, times 2^level for a graded lattice's finer cells (a cell of
    level L is 2^-L the size of a level-0 one, and its springs get 2^-L of the family's k).
    The shortest spring is not that size there: conforming the lattice to the surface moves
    nodes up to 0.75 of a cell, leaving springs 2-30 times shorter than the cells. A network
    has no cells: ``h``.
    """
    if not isinstance(spec.geometry, MeshGeometry) or solid.hexahedra is None:
        return h
    size = np.cbrt(np.abs(hexahedron_volumes(solid.nodes, solid.hexahedra)))
    if solid.levels is not None:
        size = size * 2.0 ** solid.levels.astype(float)
    return float(np.median(size))


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
    """Arrays for a schema-valid spec; raises :class:`fpm.model.checks.SpecError` where it does not
    fit its solid (``mesh`` as :func:`load_problem`'s)."""
    check_indices(spec)
    solid = build_solid(spec.geometry, spec.material.density)
    errors: list[tuple[Loc, str]] = []
    lengths = spring_lengths(solid.nodes, solid.springs)
    if len(lengths) and lengths.min() <= 0:
        errors.append((("geometry",), "a spring joins two nodes at the same point"))
        raise SpecError(errors)
    h = float(lengths.min())
    finder = NodeFinder(solid.nodes, tol=1e-3 * h, cells=solid.elements)

    fixed = np.zeros(len(solid.nodes), dtype=bool)
    for i, sel in enumerate(spec.fixed):
        picked = finder.select(sel, ("fixed", i), errors)
        fixed[picked] = True

    load_cases = _load_cases(spec.load_cases, "load_cases", finder, fixed, errors)
    validation = _load_cases(spec.validation_cases, "validation_cases", finder, fixed, errors)
    check_stiffness_mode(spec, errors)
    check_supplied_reference(spec, len(solid.nodes), errors)
    check_refine(spec, errors)
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
    return NodeFinder(problem.nodes, tol=1e-3 * problem.h).select(selector, (), errors)


def _load_cases(
    cases: list[Any],
    field: str,
    finder: NodeFinder,
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
            where = dotted((*loc, force.kind))
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
                    f"{where}: {len(picked)} nodes each get {fmt(force.vector)} N (total "
                    f'{fmt(vector * len(picked))} N); set "distribute": true to split the '
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


def _all_fixed(picked: np.ndarray) -> str:
    if len(picked) == 1:
        return f"node {int(picked[0])} is fixed; a force on it does nothing (load a free node)"
    return (
        f"all {len(picked)} nodes it selects are fixed; a force on them does nothing (select "
        "free nodes)"
    )
