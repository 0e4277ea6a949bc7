"""The perturbed list (paper Sec. 3.1, Fig. 1 and 2) and its lookup table.

Layer 0 holds the stimulated nodes (all nodes with a force in the load case, together); layer i
holds the not-yet-visited, non-fixed spring neighbours of layer i-1. Layers of overlapping
regions merge, so the propagation stays synchronised and each node is listed once. Inside a
layer, nodes are in ascending index order.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Adjacency:
    """Spring neighbours in compressed sparse row form (every spring seen from both ends).

    Attributes:
        ptr: (N+1,) int64; node i's entries are ``ptr[i]:ptr[i+1]``.
        neighbour: (2S,) int32 neighbour node index.
        rest_length: (2S,) rest length of that spring, m.
        stiffness_factor: (2S,) per-spring stiffness factor (paper Fig. 5), or (0,) if all 1.
        spring: (2S,) int64 index of the spring (a row of the (S, 2) pairs) of each entry.
    """

    ptr: np.ndarray
    neighbour: np.ndarray
    rest_length: np.ndarray
    stiffness_factor: np.ndarray
    spring: np.ndarray

    @classmethod
    def from_springs(
        cls, n_nodes: int, springs: np.ndarray, rest_length: np.ndarray, factor: np.ndarray | None
    ) -> Adjacency:
        """Build from (S, 2) node pairs, (S,) rest lengths and (S,) factors (None = all 1)."""
        ends = np.concatenate([springs[:, 0], springs[:, 1]])
        order = np.argsort(ends, kind="stable")
        neighbour = np.concatenate([springs[:, 1], springs[:, 0]])[order].astype(np.int32)
        rest = np.concatenate([rest_length, rest_length])[order]
        fac = np.zeros(0) if factor is None else np.concatenate([factor, factor])[order]
        ptr = np.zeros(n_nodes + 1, dtype=np.int64)
        np.cumsum(np.bincount(ends, minlength=n_nodes), out=ptr[1:])
        return cls(ptr, neighbour, rest, fac, order % len(springs))

    def entries_of(self, nodes: np.ndarray) -> np.ndarray:
        """(E,) int64 indices of the entries of ``nodes`` (K,), row after row in their order."""
        start = self.ptr[nodes]
        count = self.ptr[nodes + 1] - start
        if not len(nodes) or not count.sum():
            return np.zeros(0, dtype=np.int64)
        first = np.repeat(start - np.concatenate([[0], np.cumsum(count)[:-1]]), count)
        return first + np.arange(count.sum())

    def neighbours_of(self, nodes: np.ndarray) -> np.ndarray:
        """All neighbours (with repeats) of ``nodes`` (K,), as one flat int array."""
        return self.neighbour[self.entries_of(nodes)]


@dataclass(frozen=True)
class PerturbedList:
    """The nodes one load case moves, in propagation order.

    Attributes:
        order: (M,) int32 node indices, layer by layer.
        layer_start: (L+1,) offsets: layer i is ``order[layer_start[i]:layer_start[i+1]]``.
    """

    order: np.ndarray
    layer_start: np.ndarray

    @property
    def layers(self) -> int:
        """Number of layers after the stimulated one (the depth actually reached)."""
        return len(self.layer_start) - 2

    def layer(self, i: int) -> np.ndarray:
        return self.order[self.layer_start[i] : self.layer_start[i + 1]]


@dataclass(frozen=True)
class ListLayout:
    """A perturbed list's own numbering of the nodes, for the dynamic kernel's memory access.

    The list's nodes come first, in visiting order (local 0..M-1), then every other node. The
    kernel then walks its arrays front to back, and a node's neighbours, in the layers beside
    its own, sit near it in memory instead of anywhere in the solid's numbering. The same
    arithmetic in the same order: every result is the same to the bit (tested).

    Attributes:
        order: (M,) local indices of the list's nodes in visiting order (0..M-1), the dtype
            of :attr:`PerturbedList.order`.
        nodes: (N,) int64 the solid's index of each local node (local -> solid).
        local: (N,) int64 the local index of each of the solid's nodes (solid -> local).
        rows: the list's nodes' rows of the solid's :class:`Adjacency`, in local indices (M
            rows: the other nodes never move); its ``spring`` is int32 when the springs are
            fewer than 2^31 (a 10^6-node lattice has 1.3e7).
    """

    order: np.ndarray
    nodes: np.ndarray
    local: np.ndarray
    rows: Adjacency

    @classmethod
    def of(cls, adjacency: Adjacency, plist: PerturbedList) -> ListLayout:
        """The layout of ``plist`` over the solid of ``adjacency``."""
        n = len(adjacency.ptr) - 1
        listed = np.zeros(n, dtype=bool)
        listed[plist.order] = True
        nodes = np.concatenate([plist.order, np.flatnonzero(~listed)]).astype(np.int64)
        local = np.empty(n, dtype=np.int64)
        local[nodes] = np.arange(n)
        entries = adjacency.entries_of(plist.order)
        ptr = np.zeros(len(plist.order) + 1, dtype=np.int64)
        np.cumsum(adjacency.ptr[plist.order + 1] - adjacency.ptr[plist.order], out=ptr[1:])
        factor = adjacency.stiffness_factor
        rows = Adjacency(
            ptr=ptr,
            neighbour=local[adjacency.neighbour[entries]].astype(np.int32),
            rest_length=adjacency.rest_length[entries],
            stiffness_factor=factor[entries] if len(factor) else factor,
            spring=adjacency.spring[entries].astype(
                np.int32 if len(adjacency.spring) < 2**31 else np.int64
            ),
        )
        return cls(np.arange(len(plist.order), dtype=plist.order.dtype), nodes, local, rows)


def perturbed_list(
    adjacency: Adjacency, stimulated: np.ndarray, fixed: np.ndarray, depth: int | None
) -> PerturbedList:
    """Breadth-first layers from ``stimulated`` (K,) up to ``depth`` layers (None = all).

    Fixed nodes ((N,) bool) are never listed: they neither move nor pass the force on.
    """
    visited = fixed.copy()
    layer = np.unique(stimulated[~fixed[stimulated]]).astype(np.int32)
    visited[layer] = True
    layers = [layer]
    while len(layer) and (depth is None or len(layers) <= depth):
        candidates = np.unique(adjacency.neighbours_of(layer))
        layer = candidates[~visited[candidates]]
        visited[layer] = True
        if len(layer):
            layers.append(layer)
        else:
            break
    starts = np.concatenate([[0], np.cumsum([len(x) for x in layers])])
    return PerturbedList(np.concatenate(layers).astype(np.int32), starts)


class PerturbedListCache:
    """The lookup table the paper proposes in its conclusion: lists by (stimulated set, depth).

    A real-time loop asks for the same few lists again and again; building one is a graph
    search, using one is a dictionary lookup.
    """

    def __init__(self, adjacency: Adjacency, fixed: np.ndarray):
        self.adjacency = adjacency
        self.fixed = fixed
        self._table: dict[tuple[bytes, int | None], PerturbedList] = {}
        self.hits = 0
        self.misses = 0

    def get(self, stimulated: np.ndarray, depth: int | None) -> PerturbedList:
        key = (np.unique(stimulated).astype(np.int64).tobytes(), depth)
        found = self._table.get(key)
        if found is None:
            self.misses += 1
            found = self._table[key] = perturbed_list(self.adjacency, stimulated, self.fixed, depth)
        else:
            self.hits += 1
        return found

    def __len__(self) -> int:
        return len(self._table)
