"""The load cases' CG in lockstep (fpm/fem/load_case_cg.py): each column the answer of K u = f,
bit for bit the same whatever columns share its group or however many threads."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp
from pyamg.util.utils import get_block_diag

from fpm.fem.linear_solver import NegativeCurvature, _block_gauss_seidel
from fpm.fem.load_case_cg import (
    block_gauss_seidel_columns,
    column_dots,
    compiled_sweep_columns,
    lockstep_cg,
    solve_columns,
)


def spd_blocks(nodes: int = 40, seed: int = 0) -> sp.bsr_matrix:
    """A sparse SPD matrix in 3x3 blocks: a random graph Laplacian-like pattern, made SPD."""
    rng = np.random.default_rng(seed)
    pairs = rng.integers(0, nodes, size=(4 * nodes, 2))
    pairs = pairs[pairs[:, 0] != pairs[:, 1]]
    graph = sp.coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), (nodes, nodes))
    graph = ((graph + graph.T) > 0).astype(float)
    block = rng.normal(size=(3, 3))
    k = sp.kron(graph, block @ block.T * 0.1, format="csr")
    k = k + sp.kron(sp.identity(nodes), np.eye(3) * (abs(k).sum(axis=1).max() + 1.0))
    out = sp.bsr_matrix(k, blocksize=(3, 3))
    out.sort_indices()
    return out


def jacobi(k: sp.bsr_matrix):
    diagonal = k.diagonal()
    return lambda r: r / diagonal[:, None]


def test_each_column_solves_its_system_and_is_the_same_alone_as_in_a_group():
    k = spd_blocks()
    n = k.shape[0]
    rng = np.random.default_rng(1)
    b = rng.normal(size=(n, 4))
    b[:, 2] = 0.0  # a load case with no force: zero, at once
    x0 = np.zeros((n, 4))
    x0[:, 1] = np.linalg.solve(k.toarray(), b[:, 1]) * (1 + 1e-3)  # a start near the answer
    together = lockstep_cg(k, b, jacobi(k), rtol=1e-10, max_iterations=500, x0=x0)
    dense = k.toarray()
    for j, result in enumerate(together):
        alone = lockstep_cg(k, b[:, [j]], jacobi(k), rtol=1e-10, max_iterations=500, x0=x0[:, [j]])[
            0
        ]
        assert np.array_equal(result.x, alone.x) and result.iterations == alone.iterations
        assert result.converged
        assert (
            np.linalg.norm(dense @ result.x - b[:, j])
            <= 1e-10 * max(np.linalg.norm(b[:, j]), 1e-300)
            or not b[:, j].any()
        )
    assert together[2].iterations == 0 and not together[2].x.any()
    assert together[1].iterations < together[0].iterations  # the start near the answer
    threaded = solve_columns(k, b, jacobi(k), rtol=1e-10, max_iterations=500, threads=2, x0=x0)
    assert all(np.array_equal(a.x, c.x) for a, c in zip(together, threaded, strict=True))


def test_an_indefinite_matrix_is_refused():
    k = sp.bsr_matrix(sp.diags(np.r_[np.ones(5), -np.ones(1)]).tocsr(), blocksize=(3, 3))
    with pytest.raises(NegativeCurvature):
        lockstep_cg(k, np.ones((6, 2)), lambda r: r.copy(), rtol=1e-12, max_iterations=50)


def test_the_column_sweep_and_dots_are_the_one_vector_ones_per_column():
    k = spd_blocks(seed=3)
    inverse = get_block_diag(k, blocksize=3, inv_flag=True)
    rng = np.random.default_rng(2)
    b = rng.normal(size=(k.shape[0], 3))
    for forward in (True, False):
        for sweep in (block_gauss_seidel_columns, compiled_sweep_columns()):
            x = rng.normal(size=b.shape)
            one = [x[:, j].copy() for j in range(3)]
            sweep(k.indptr, k.indices, k.data, inverse, x, b, forward)
            for j in range(3):
                _block_gauss_seidel(
                    k.indptr, k.indices, k.data, inverse, one[j], b[:, j].copy(), forward
                )
                assert np.array_equal(x[:, j], one[j])
    sums = column_dots(b, 2 * b)
    assert np.allclose(sums, 2 * (b * b).sum(axis=0), rtol=1e-13)
