"""research.graded: the lattice coarsened to 2h inside keeps what a 2h lattice can represent."""

import numpy as np
import pytest

import fpm
from fpm.fem.samples import lattice_surface
from research.graded import coarse_constraint, grid_indices, surface_depth
from tests.helpers_fpm import box_spec


@pytest.fixture(scope="module")
def box():
    problem = fpm.load_problem(box_spec((9, 9, 9), 0.01))
    hexahedra = problem.solid.elements()
    index = grid_indices(problem.solid.nodes, hexahedra, problem.h)
    surface = lattice_surface(hexahedra, problem.n_nodes)
    return problem, hexahedra, index, surface


def test_grid_indices_and_depth_on_a_box(box):
    problem, hexahedra, index, surface = box
    x = problem.solid.nodes
    assert np.array_equal(index, np.round((x - x[~surface][0]) / 0.01).astype(int))
    with pytest.raises(ValueError, match="not on a grid of spacing"):
        grid_indices(problem.solid.nodes, hexahedra, 0.004)  # e.g. the shortest spring
    depth = surface_depth(hexahedra, surface, 5)
    from_faces = np.min(np.minimum(index - index.min(0), index.max(0) - index), axis=1)
    assert np.array_equal(depth, np.minimum(from_faces, 6))


@pytest.mark.parametrize("parity", [(0, 0, 0), (1, 1, 0), (1, 0, 1)])
def test_the_constraint_reproduces_linear_fields_and_keeps_the_kept_nodes(box, parity):
    """A trilinear 2h cell reproduces any linear displacement (the patch test): T of the
    field's values at the kept free nodes is the field at every free node, and a kept node
    is its own unknown."""
    problem, hexahedra, index, surface = box
    grid = np.all((index - np.array(parity)) % 2 == 0, axis=1)
    kept = (surface_depth(hexahedra, surface, 1) <= 1) | grid
    fixed = np.zeros(problem.n_nodes, dtype=bool)  # a linear field is not zero on a face
    t = coarse_constraint(index, kept, fixed, np.array(parity))
    assert (~kept).sum() > 100 and t.shape == (problem.n_nodes, kept.sum())
    field = problem.solid.nodes @ np.array([1.0, -2.0, 0.5]) + 0.3
    assert t @ field[kept] == pytest.approx(field, abs=1e-12)
    assert np.array_equal(t[kept].toarray(), np.eye(int(kept.sum())))
    with pytest.raises(ValueError, match="is not kept"):
        coarse_constraint(index, kept & ~grid, fixed, np.array(parity))
