"""The finite element reference (paper Sec. 4.1): static nodal displacements from ``F = K X``.

Small-strain linear elasticity on the problem's 8-node hexahedra (:mod:`fpm.fem.elasticity`),
assembled into a block-sparse K (:mod:`fpm.fem.assembly`), fixed nodes as Dirichlet conditions
(their displacement is zero), the load cases' nodal forces as right-hand sides, one
factorisation for all of them (:mod:`fpm.fem.linear_solver`). The hexahedra are integrated as
the spec's ``reference.integration`` says: ``"selective"`` (B-bar with the mean dilatation, the
default: no volumetric locking near nu = 1/2) or ``"full"`` (2x2x2 Gauss points, the paper's).
With ``fpm.gravity`` set, every load case also carries the solid's weight as the consistent
body force ``int N_a rho g dV`` (:func:`fpm.fem.assembly.body_forces`); density plays no other
part. Nodes that belong to no hexahedron (possible in a ``mesh``) carry no stiffness; they stay
at rest and may not be loaded.

With ``material.model: "neo-hookean"`` the same hexahedra, supports and loads go to the
large-deformation reference instead (:mod:`fpm.fem.hyperelastic`); :func:`solve_fem` dispatches on
the model, and the result carries its load steps and Newton iterations.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

from ..model.problem import Problem, resolved_refine
from ..model.support import unheld_reason
from .assembly import body_forces
from .elasticity import min_jacobian_determinants
from .linear_solver import choose_method
from .materials import hexahedron_densities, hexahedron_stiffness
from .solution import FemError, FemResult, solve_dirichlet


def reference_label(spec: Any) -> str:
    """Which reference a calibration of ``spec`` (a :class:`fpm.model.spec.ProblemSpec`) is fitted
    to: ``"supplied"`` (``reference.displacements``), ``"fem-neo-hookean-selective"`` /
    ``"fem-neo-hookean-full"`` or ``"fem-linear-selective"`` / ``"fem-linear-full"`` (model and
    integration), or
    ``"fem-linear-tet10"`` (``reference.mesh`` or ``reference.mesh_id``: 10-node tetrahedra)."""
    if spec.reference.displacements is not None:
        return "supplied"
    if spec.reference.mesh is not None or spec.reference.mesh_id is not None:
        return "fem-linear-tet10"
    if spec.material.model == "neo-hookean":
        return f"fem-neo-hookean-{spec.reference.integration}"
    return f"fem-linear-{spec.reference.integration}"


def supplied_reference(problem: Problem) -> FemResult | None:
    """The spec's ``reference.displacements`` as a :class:`FemResult` (model and method
    ``"supplied"``, residuals 0; one field per load case, then per validation case), or None
    when the spec supplies none. Its shape was checked by :func:`fpm.load_problem`."""
    supplied = problem.spec.reference.displacements
    if supplied is None:
        return None
    cases = problem.all_cases  # the load cases, then the validation cases
    u = np.asarray(supplied, dtype=float).reshape(len(cases), len(problem.nodes), 3)
    names = [case.name for case in cases]
    return FemResult(problem.nodes.copy(), u, [0.0] * len(names), names, "supplied", "supplied")


def reference_for(
    problem: Problem,
    method: str = "auto",
    *,
    load_steps: int = 1,
    mesh: dict[str, Any] | None = None,
    progress: Callable[[dict[str, Any]], None] | None = None,
) -> FemResult:
    """The reference ``problem`` is calibrated against: the supplied displacements when the
    spec has them (no FEM is solved), else :func:`solve_fem` (``mesh`` and ``progress`` as
    there)."""
    supplied = supplied_reference(problem)
    if supplied is not None:
        return supplied
    return solve_fem(problem, method, load_steps=load_steps, mesh=mesh, progress=progress)


def solve_fem(
    problem: Problem,
    method: str = "auto",
    *,
    load_steps: int = 1,
    mesh: dict[str, Any] | None = None,
    progress: Callable[[dict[str, Any]], None] | None = None,
) -> FemResult:
    """Nodal displacements of ``problem`` for every load case, by the spec's material model.

    With ``reference.mesh`` (or ``reference.mesh_id`` and ``mesh``) the reference is solved with
    10-node tetrahedra on that mesh (nodes at one point numbered twice joined:
    :func:`fpm.model.tetrahedra.merge_coincident`) and read at the lattice nodes
    (:mod:`fpm.fem.tet10`); the result has the same shape, on the lattice, with ``element``
    ``"tet10"``.

    Args:
        problem: from :func:`fpm.load_problem`; needs a box, voxels or mesh geometry.
        method: ``"auto"`` (by size), ``"direct"`` or ``"amg"`` (see :mod:`fpm.fem.linear_solver`).
        load_steps: neo-Hookean only: planned load steps per load case (halved where Newton
            fails, :mod:`fpm.fem.hyperelastic`).
        mesh: the mesh ``reference.mesh_id`` names, ``{"nodes": (N, 3), "tetrahedra": (T, 4)}``
            (m, 0-based), as the service stored it; ignored when the spec has none.
        progress: told each level of a refined reference as it starts (``reference.refine``
            a number or "auto": :func:`fpm.fem.levels.converge`).

    Raises:
        FemError: a network geometry, an inverted or degenerate hexahedron, a solid that is
            not held, or a force on a node that belongs to no hexahedron.
        fpm.fem.hyperelastic.NewtonError (a FemError): neo-Hookean, a load case whose equilibrium
            was not found (the message names it, the load step and why).
    """
    if method not in ("auto", "direct", "amg"):
        raise ValueError(f"unknown method {method!r} (use 'auto', 'direct' or 'amg')")
    settings = problem.spec.reference
    from .refine import refined_hex_reference, refined_tet_reference

    refine = resolved_refine(problem.spec)  # 0: the mesh as given, point loads, no estimate
    asked = method
    if settings.mesh is not None or settings.mesh_id is not None:
        from ..model.tetrahedra import lattice_pieces, merge_coincident
        from .tet10 import tet10_reference

        if settings.mesh is not None:
            mesh = {"nodes": settings.mesh.nodes, "tetrahedra": settings.mesh.tetrahedra}
        elif mesh is None:
            raise FemError(
                f"reference.mesh_id {settings.mesh_id} names an uploaded mesh, which was not "
                "given: submit the spec to the service, or put the mesh in reference.mesh"
            )
        # Nodes numbered twice at one point joined (as spec_from_mesh joins them): else the
        # tetrahedra on either side share no face, a crack or two pieces the lattice has not.
        x, t, _ = merge_coincident(mesh["nodes"], mesh["tetrahedra"])
        hexahedra = problem.solid.elements()
        if hexahedra is not None and len(hexahedra):  # as the service refuses it at submit
            apart = lattice_pieces(x, t, problem.nodes[hexahedra].mean(axis=1)).joined_apart(x, t)
            if apart:
                raise FemError(f"reference.mesh: {apart}")
        if refine == 0:
            return tet10_reference(problem, x, t, method)
        return refined_tet_reference(problem, x, t, method, progress)
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
            "check their node order (see fpm.model.hexahedron)"
        )
    material = problem.spec.material
    # The validation cases too (after the load cases): the fit never sees them, the result does.
    forces = np.stack(
        [case.as_given().dense(len(nodes)) for case in problem.all_cases]
    )  # (L + V, N, 3)
    in_solid = np.zeros(len(nodes), dtype=bool)
    in_solid[hexahedra] = True
    stray = np.flatnonzero(~in_solid & np.any(forces != 0, axis=(0, 2)))
    if len(stray):
        raise FemError(f"node {int(stray[0])} is loaded but belongs to no hexahedron")
    gravity = np.asarray(problem.spec.fpm.gravity, dtype=float)
    if refine not in (0, "check"):  # refined hexahedra, the forces spread (fpm.fem.refine)
        return refined_hex_reference(problem, hexahedra, asked, None, progress)
    if np.any(gravity):  # the solid's own weight, in every load case
        density = hexahedron_densities(problem, nodes, hexahedra)
        forces = forces + body_forces(nodes, hexahedra, density, gravity)[None]
    free = np.repeat(in_solid & ~problem.fixed, 3)
    method = choose_method(int(free.sum())) if method == "auto" else method
    names = [case.name for case in problem.all_cases]
    if material.model == "neo-hookean":
        from ..model.spec import lame_constants
        from .hyperelastic import solve_hyperelastic
        from .neo_hookean import neo_hookean_law

        mu, lam = lame_constants(material.youngs_modulus, material.poisson_ratio)
        law = neo_hookean_law(mu, lam, problem.spec.reference.integration)
        u, paths = solve_hyperelastic(
            nodes, hexahedra, law, forces, free, method, names, load_steps
        )
        return FemResult(
            nodes.copy(),
            u,
            [path.residual for path in paths],
            names,
            method,
            material.model,
            [path.load_steps for path in paths],
            [path.newton_iterations for path in paths],
        )
    k = hexahedron_stiffness(problem, nodes, hexahedra)  # regions: fpm.fem.materials
    u, residuals = solve_dirichlet(k, forces.reshape(len(forces), -1), free, nodes, method)
    result = FemResult(nodes.copy(), u.reshape(forces.shape), residuals.tolist(), names, method)
    if refine == "check":  # the same reference, its error estimated by one refinement
        return refined_hex_reference(problem, hexahedra, asked, result)
    return result
