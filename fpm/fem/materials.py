"""The FEM's elasticity element by element: material regions and transversely isotropic solids.

With ``material.regions`` (:mod:`fpm.model.regions`) every element takes the region of its
centroid (a lattice hexahedron the region of its cell, as the lattice does; a tetrahedron its
own tag, a refined element its parent's), with that region's C and density; a transversely
isotropic material (:mod:`fpm.model.anisotropy`) gives every element its rotated C. The
hexahedra integrate an anisotropic C with the general mean-dilatation B-bar
(:func:`fpm.fem.elasticity.mean_dilatation_stiffness`) under ``"selective"``, the 10-node
tetrahedra exactly. Specs with neither (:func:`has_materials`) take the spec's one C and
density.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from ..model.anisotropy import stiffness_tensor
from ..model.problem import Problem
from ..model.regions import element_materials
from ..model.spec import ProblemSpec
from .assembly import stiffness_matrix
from .elasticity import constitutive_matrix


def has_materials(spec: ProblemSpec) -> bool:
    """The spec has material regions or a transversely isotropic material."""
    return bool(spec.material.regions) or spec.material.type == "transversely-isotropic"


def elasticity(
    problem: Problem, centroids: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per element (centroids (E, 3), m): (M, 6, 6) C per material, Pa; (E,) each element's
    material; (M,) densities, kg/m^3."""
    spec = problem.spec
    m = spec.material
    if m.type == "transversely-isotropic":
        return (
            stiffness_tensor(m)[None],
            np.zeros(len(centroids), dtype=np.int64),
            np.array([m.density]),
        )
    which, materials = element_materials(spec, problem.regions, centroids)
    c = np.stack([constitutive_matrix(e, nu) for e, nu, _ in materials])
    return c, which, np.array([rho for _, _, rho in materials])


def hexahedron_stiffness(
    problem: Problem, nodes: np.ndarray, hexahedra: np.ndarray
) -> sp.bsr_matrix:
    """(3N, 3N) K, N/m, of ``hexahedra`` (H, 8) on ``nodes`` (N, 3) with every element's own C
    (the spec's one C without :func:`has_materials`), integrated as the spec's
    ``reference.integration`` says."""
    spec = problem.spec
    if not has_materials(spec):
        c = constitutive_matrix(spec.material.youngs_modulus, spec.material.poisson_ratio)
        return stiffness_matrix(nodes, hexahedra, c, spec.reference.integration)
    c, which, _ = elasticity(problem, nodes[hexahedra].mean(axis=1))
    return stiffness_matrix(nodes, hexahedra, c, spec.reference.integration, which)


def hexahedron_densities(
    problem: Problem, nodes: np.ndarray, hexahedra: np.ndarray
) -> np.ndarray | float:
    """(H,) every hexahedron's density, kg/m^3 (for the body force); the spec's one density
    without :func:`has_materials`."""
    if not has_materials(problem.spec):
        return problem.spec.material.density
    _, which, density = elasticity(problem, nodes[hexahedra].mean(axis=1))
    return density[which]


def tetrahedron_elasticity(
    problem: Problem, nodes: np.ndarray, tets: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Per tetrahedron (``tets`` (T, 4) on ``nodes``): (T, 6, 6) C, Pa, and (T,) density."""
    c, which, density = elasticity(problem, nodes[tets].mean(axis=1))
    return c[which], density[which]
