"""The perturbed list (paper Sec. 3.1 and 3.3): its size on the paper's Fig. 7 lattice in closed
form, its layers as graph distances computed independently, and its lookup table."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp
from helpers_fpm import box_spec, chain_spec, lattice_index
from scipy.sparse.csgraph import shortest_path

import fpm
from fpm.dynamics.simulation import fpm_model
from fpm.model.perturbed_list import PerturbedList, PerturbedListCache, perturbed_list

FIG7 = (31, 15, 31)  # paper Fig. 7: 31 x 15 x 31 nodes, y is the height
TOP_CENTRE = (15, 14, 15)


def paper_count(n: int) -> int:
    """Nodes in the list of one stimulated node mid-face after n layers, paper Sec. 3.3.

    Layer i is the half-octahedron shell |a| + |c| + b = i, b >= 0: 2i^2 + 2i + 1 nodes;
    summed over i = 0..n this is (n+1)(2n^2+4n+3)/3."""
    return (n + 1) * (2 * n * n + 4 * n + 3) // 3


def fig7_problem(stimulated: list[tuple[int, int, int]], fixed: list | None = None) -> fpm.Problem:
    h = 0.01
    forces = [{"at": [i * h, j * h, k * h], "vector": [0.0, -0.1, 0.0]} for i, j, k in stimulated]
    return fpm.load_problem(
        box_spec(FIG7, h, connectivity="axis", fixed=fixed or [], forces=forces)
    )


@pytest.fixture(scope="module")
def fig7() -> fpm.Problem:
    return fig7_problem([TOP_CENTRE])


def graph_distances(problem: fpm.Problem, sources: np.ndarray) -> np.ndarray:
    """(N,) hop distance from the nearest source through the springs, with the fixed nodes cut
    out of the graph (they pass nothing on); inf where unreachable."""
    s = problem.solid.springs
    free = ~problem.fixed[s[:, 0]] & ~problem.fixed[s[:, 1]]
    s = s[free]
    n = problem.n_nodes
    graph = sp.coo_matrix((np.ones(len(s)), (s[:, 0], s[:, 1])), shape=(n, n)).tocsr()
    dist = shortest_path(graph, directed=False, unweighted=True, indices=sources)
    return np.atleast_2d(dist).min(axis=0)


def layer_of(plist: PerturbedList, n_nodes: int) -> np.ndarray:
    """(N,) layer index of each node in the list, -1 for the nodes not in it."""
    out = np.full(n_nodes, -1)
    for i in range(len(plist.layer_start) - 1):
        out[plist.layer(i)] = i
    return out


def test_stimulated_node_is_the_centre_of_the_top_face(fig7: fpm.Problem):
    node = lattice_index(FIG7, *TOP_CENTRE)
    assert fig7.load_cases[0].nodes.tolist() == [node]
    assert fig7.nodes[node].tolist() == pytest.approx([0.15, 0.14, 0.15])


@pytest.mark.parametrize("n", range(1, 15))
def test_paper_count_for_n_layers(fig7: fpm.Problem, n: int):
    plist = fpm_model(fig7).perturbed_list(0, n)
    assert len(plist.order) == paper_count(n)
    assert plist.layers == n
    sizes = np.diff(plist.layer_start)
    assert sizes.tolist() == [2 * i * i + 2 * i + 1 for i in range(n + 1)]
    assert len(np.unique(plist.order)) == len(plist.order)  # each node once


def test_at_fifteen_layers_the_bottom_cuts_one_node_off(fig7: fpm.Problem):
    """The lattice is 15 nodes high: layer 15 would reach 14 + 1 rows down, and the one node of
    the shell straight below the stimulated node does not exist (paper: 2736; here 2735)."""
    assert paper_count(15) == 2736
    plist = fpm_model(fig7).perturbed_list(0, 15)
    assert len(plist.order) == 2735
    assert len(np.unique(plist.order)) == 2735


def test_full_depth_lists_every_node_once(fig7: fpm.Problem):
    plist = fpm_model(fig7).perturbed_list(0, None)
    assert len(plist.order) == fig7.n_nodes == np.prod(FIG7)
    assert np.array_equal(np.sort(plist.order), np.arange(fig7.n_nodes))
    # The farthest nodes are the bottom corners: 15 + 15 + 14 hops away.
    assert plist.layers == 44


def test_depth_zero_is_the_stimulated_nodes(fig7: fpm.Problem):
    plist = fpm_model(fig7).perturbed_list(0, 0)
    assert plist.order.tolist() == fig7.load_cases[0].nodes.tolist()
    assert plist.layers == 0


def test_overlapping_regions_share_layers():
    """Two stimulated nodes four apart on the top face, bottom face fixed: every node's layer is
    its distance from the nearer stimulated node; the merged regions list each node once."""
    problem = fig7_problem([(13, 14, 15), (17, 14, 15)], fixed=[{"face": "y-"}])
    stimulated = problem.load_cases[0].nodes
    assert len(stimulated) == 2
    dist = graph_distances(problem, stimulated)
    for depth in (1, 3, 6, 13, 14, 20, None):
        plist = fpm_model(problem).perturbed_list(0, depth)
        assert len(np.unique(plist.order)) == len(plist.order)
        reach = np.inf if depth is None else depth
        expected = np.flatnonzero(np.isfinite(dist) & (dist <= reach))
        assert np.array_equal(np.sort(plist.order), expected)
        layer = layer_of(plist, problem.n_nodes)
        assert np.array_equal(layer[expected], dist[expected].astype(int))
        for i in range(len(plist.layer_start) - 1):
            assert np.all(np.diff(plist.layer(i)) > 0)  # ascending inside a layer
    # The two regions overlap from layer 2 on: fewer nodes than two separate lists.
    assert len(fpm_model(problem).perturbed_list(0, 6).order) < 2 * paper_count(6)


def test_fixed_nodes_are_never_listed_and_pass_nothing_on():
    problem = fig7_problem([TOP_CENTRE], fixed=[{"face": "y-"}])
    plist = fpm_model(problem).perturbed_list(0, None)
    assert not problem.fixed[plist.order].any()
    assert len(plist.order) == problem.n_nodes - 31 * 31
    # A chain fixed in the middle: the force stops at the fixed node.
    chain = fpm.load_problem(chain_spec(6, 0.01, (1, 0, 0), tip_force=[1, 0, 0]))
    chain.fixed[3] = True
    cut = perturbed_list(fpm_model(chain).adjacency, np.array([6]), chain.fixed, None)
    assert cut.order.tolist() == [6, 5, 4]


def test_lookup_table_returns_the_same_list_and_counts_hits(fig7: fpm.Problem):
    model = fpm_model(fig7)
    table = PerturbedListCache(model.adjacency, fig7.fixed)
    stimulated = fig7.load_cases[0].nodes
    first = table.get(stimulated, 5)
    assert (table.hits, table.misses, len(table)) == (0, 1, 1)
    assert table.get(stimulated, 5) is first
    assert table.get(stimulated.copy(), 5) is first  # keyed by value, not by array identity
    assert (table.hits, table.misses, len(table)) == (2, 1, 1)
    other = table.get(stimulated, 6)
    assert other is not first and len(other.order) == paper_count(6)
    assert (table.hits, table.misses, len(table)) == (2, 2, 2)
    # The same stimulated set in another order is the same key.
    pair = np.array([lattice_index(FIG7, 14, 14, 15), lattice_index(FIG7, 16, 14, 15)])
    assert table.get(pair, 2) is table.get(pair[::-1], 2)


def test_simulate_reuses_the_cached_list(fig7: fpm.Problem):
    problem = fig7_problem([TOP_CENTRE])
    table = fpm_model(problem).lists
    for _ in range(3):
        fpm.simulate(problem, k=10.0, d=1.0, depth=4, max_steps=1)
    assert (table.misses, table.hits) == (1, 2)
