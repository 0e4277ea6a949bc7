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

    def neighbours_of(self, nodes: np.ndarray) -> np.ndarray:
        """All neighbours (with repeats) of ``nodes`` (K,), as one flat int array."""
        start = self.ptr[nodes]
        count = self.ptr[nodes + 1] - start
        if not len(nodes) or not count.sum():
            return np.zeros(0, dtype=np.int32)
        first = np.repeat(start - np.concatenate([[0], np.cumsum(count)[:-1]]), count)
        return self.neighbour[first + np.arange(count.sum())]


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
