"""A problem spec from a mesh file: :func:`spec_from_mesh` (``fpmcal spec from-mesh``, the
SDK's ``spec_from_mesh``)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from ...model.problem import Problem, load_patterns, load_problem
from ..errors import MeshError
from .conform import conform_spec
from .geometry import geometry_from_mesh
from .reading import read_mesh
from .selectors import FORCE_HELP, SELECTOR_HELP, parse_force, parse_selector
from .sizing import graded_nodes, spacing_for_nodes
from .voxelise import support_planes


def spec_from_mesh(
    mesh: Any,
    *,
    fix: list[str],
    forces: list[str],
    youngs_modulus: float,
    poisson_ratio: float,
    density: float = 1000.0,
    spacing: float | None = None,
    nodes: int | None = None,
    connectivity: str = "full",
    scale: float = 1.0,
    voxelise: bool = False,
    name: str | None = None,
    dt: float | str = "auto",
    voxel_reference: bool = False,
    conform: bool = False,
    lattice: str | None = None,
    stiffness: str | None = None,
    loads: str | None = None,
    validation: list[str] | None = None,
) -> tuple[dict[str, Any], list[str]]:
    """A problem spec for a mesh file (or a ``meshio.Mesh``), and notes for the user.

    Args:
        mesh: a path meshio reads, or a ``meshio.Mesh``.
        fix: fixed nodes, each a short selector (:func:`parse_selector`), e.g. ``"face:z-"``.
        forces: one string per load case (:func:`parse_force`), e.g.
            ``"nearest:0,0,0.05:0,0,-0.5"``.
        validation: one string per validation case, in the same form: loads the fit never
            sees, simulated at the fitted parameters and reported beside the fit (the honest
            figure: docs/howto/validation-cases.md).
        youngs_modulus, poisson_ratio, density: the material (Pa, -, kg/m^3).
        spacing, connectivity, scale, voxelise: as :func:`geometry_from_mesh`.
        nodes: instead of ``spacing``, about how many lattice nodes (a real-time budget): the
            spacing is chosen for it (:func:`~fpm.io.meshes.sizing.spacing_for_nodes`, three
            significant digits; a note gives it and the count found).
        name: the spec's name (default: the file's name).
        dt: the FPM time step, s, or ``"auto"`` (resolved by the fit: half the lattice's
            stability estimate at the fitted stiffness, at most 1 ms).
        voxel_reference: for a tetrahedral mesh, solve the FEM reference on the voxel lattice's
            hexahedra (the staircase) instead of on the tetrahedra; by default the spec keeps
            the tetrahedra in ``reference.mesh`` and the reference is solved on them with
            10-node tetrahedra (:mod:`fpm.fem.tet10`).
        lattice: for a tetrahedral mesh, ``"conforming"`` (the default) or ``"voxels"``.
            The conforming lattice (:func:`conform_spec`) is the voxels with their surface
            nodes moved onto the mesh's surface, a hexahedral ``mesh`` geometry: the organ's
            solid, not its staircase (docs/explanation/organs-lattice.md). ``"voxels"``: the
            ``voxels`` occupancy grid (also what ``voxel_reference`` gets, which has no mesh to
            conform to). Hexahedral meshes and closed surfaces take no choice (None).
        conform: ``True`` is ``lattice="conforming"``.
        stiffness: ``fpm.stiffness`` (a :data:`fpm.model.spec.settings.StiffnessMode`); None:
            ``"field"`` for an organ, a tetrahedral mesh whose reference is its tetrahedra,
            loaded in two force patterns or more (:func:`default_stiffness`), else the
            schema's default (families+volume).
        loads: ``fpm.loads`` (``"node"`` or ``"hat"``); None: ``"hat"`` where the reference is
            the tetrahedra (it spreads each force over its node's hat, and the lattice then
            takes the same load: :mod:`fpm.model.hat_loads`), else the schema's (``"node"``).

    Raises:
        MeshError: the mesh cannot become a solid. ValueError: a bad selector or force.
        pydantic.ValidationError: the spec does not fit its solid (e.g. a box with no node).
    """
    if isinstance(mesh, str | Path):
        name = name or Path(mesh).name
        mesh = read_mesh(mesh)
    if not fix:
        raise ValueError(f"give the fixed nodes (--fix {SELECTOR_HELP})")
    fixed = [parse_selector(s) for s in fix]
    options: dict[str, Any] = dict(
        connectivity=connectivity, scale=scale, voxelise=voxelise, planes=support_planes(fixed)
    )
    if nodes is not None and spacing is not None:
        raise ValueError("give the spacing (--spacing) or the node count (--nodes), not both")
    if nodes is not None:  # the conforming lattice's count includes its refined parts
        graded = not voxel_reference and not voxelise and lattice in (None, "conforming")
        count = graded_nodes if graded else None
        _, made = spacing_for_nodes(mesh, nodes, count, **options)
    else:
        made = geometry_from_mesh(mesh, spacing=spacing, **options)
    if not forces:
        raise ValueError(f"give at least one load case (--force {FORCE_HELP})")
    spec: dict[str, Any] = {
        "name": name or "mesh",
        "material": {
            "youngs_modulus": youngs_modulus,
            "poisson_ratio": poisson_ratio,
            "density": density,
        },
        "geometry": made.geometry,
        "fixed": fixed,
        "load_cases": [{"name": text.strip(), "forces": parse_force(text)} for text in forces],
    }
    if validation:
        spec["validation_cases"] = [
            {"name": text.strip(), "forces": parse_force(text)} for text in validation
        ]
    if made.tetrahedra is not None and not voxel_reference:
        spec["reference"] = {"mesh": made.tetrahedra}
    chosen = _lattice(lattice, conform, made.kind, voxel_reference)
    conformed: list[str] = []
    if chosen == "conforming":
        spec, conformed = conform_spec(spec)
    elif made.kind == "tetrahedra":
        conformed = [
            "lattice: the voxels (--lattice voxels"
            + (", as --voxel-reference needs" if voxel_reference and lattice is None else "")
            + "); the default follows the mesh's surface (conforming)"
        ]
    spec["fpm"] = {"dt": "auto" if dt == "auto" else float(dt)}
    if loads is not None:
        spec["fpm"]["loads"] = loads
    elif "mesh" in spec.get("reference", {}):
        spec["fpm"]["loads"] = "hat"  # as the refined tetrahedra take them (fpm.model.hat_loads)
    if stiffness is not None:
        spec["fpm"]["stiffness"] = stiffness
    problem = load_problem(spec)  # selectors and the fpm settings checked against the solid
    size = (
        f"{problem.n_nodes} nodes, cells of {problem.spacing:.4g} m (the stiffness's scale), "
        f"the shortest spring h = {problem.h:.4g} m (discrepancies are in % of it)"
    )
    notes = [*made.notes, *conformed, size]
    notes += problem.notes
    if made.tetrahedra is not None:
        notes.append(
            "FEM reference: the voxel lattice's hexahedra (--voxel-reference)"
            if voxel_reference
            else f"FEM reference: the {len(made.tetrahedra['tetrahedra'])} tetrahedra "
            "themselves (10-node, reference.mesh), read at the lattice nodes"
        )
    if spec["fpm"].get("loads") == "hat" and loads is None:
        notes.append(
            "fpm.loads = 'hat': a force on a node acts over the node's share of the surface, as "
            "the reference applies it (the lattice takes it by its shape functions; --loads node "
            "for the paper's, all of it at the node)"
        )
    if dt == "auto":
        notes.append(
            "fpm.dt = 'auto': half the lattice's stability estimate at the fitted stiffness, at "
            "most 1 ms (the result's dt says which)"
        )
    if stiffness is None:  # valid by construction: two force patterns or more
        mode, why = default_stiffness(spec, problem)
        if mode is not None:
            spec["fpm"]["stiffness"] = mode
        if why:
            notes.append(why)
    return spec, notes


def default_stiffness(spec: dict[str, Any], problem: Problem) -> tuple[str | None, str]:
    """``fpm.stiffness`` for a spec made from a mesh, and a note saying why: ``"field"`` (a
    factor per cell on the families' springs and on kappa, chosen by cross-validation and
    returned only where it predicts a left-out load better: docs/explanation/physics/
    stiffness-field.md) for an organ whose reference is its own tetrahedra, loaded in two
    force patterns or more; else None (the schema's default, families+volume). Why: a load it
    was not fitted on decides whether it is returned, and where it is not it costs only its
    cross-validation (docs/explanation/organs-spec.md, *Why the stiffness field for organs*).
    With one pattern there is nothing to cross-validate, so it would never be returned."""
    if "mesh" not in spec.get("reference", {}):
        return None, ""
    if len(load_patterns(problem)) < 2:
        return None, (
            "fpm.stiffness: families+volume (the load cases are one force pattern: a "
            "stiffness field would have no other load to be judged on)"
        )
    return "field", (
        "fpm.stiffness = 'field': a stiffness factor per cell, returned only where it predicts "
        "each left-out force pattern better than the four parameters (--stiffness to choose)"
    )


LATTICES = ("conforming", "voxels")
"""The lattices a tetrahedral mesh can become (:func:`spec_from_mesh`'s ``lattice``)."""


def _lattice(lattice: str | None, conform: bool, kind: str, voxel_reference: bool) -> str | None:
    """The lattice :func:`spec_from_mesh` builds: ``"conforming"`` or ``"voxels"`` for
    tetrahedra, None for a mesh of another ``kind`` (its hexahedra, or a surface's voxels).

    Raises:
        MeshError: a lattice that this mesh cannot have.
    """
    if lattice is not None and lattice not in LATTICES:
        raise MeshError(f"lattice {lattice!r}: use one of {', '.join(LATTICES)}")
    if conform:
        if lattice == "voxels":
            raise MeshError("conform asks for the conforming lattice, lattice for the voxels")
        lattice = "conforming"
    if kind != "tetrahedra":
        if lattice is not None and (lattice == "conforming" or kind == "hexahedra"):
            raise MeshError(
                f"a {lattice} lattice is made from a tetrahedral mesh (this one holds {kind}): "
                + (
                    "a conforming lattice moves a voxel lattice's surface onto its tetrahedral "
                    "mesh's: give a tetrahedral mesh (not hexahedra, not a surface)"
                    if lattice == "conforming"
                    else "a hexahedral mesh is used as it is (--voxelise resamples it)"
                )
            )
        return None
    if lattice is None:
        return "voxels" if voxel_reference else "conforming"
    if lattice == "conforming" and voxel_reference:
        raise MeshError(
            "a conforming lattice moves a voxel lattice's surface onto its tetrahedral mesh's: "
            "give a tetrahedral mesh (not hexahedra, not a surface, not --voxel-reference)"
        )
    return lattice
