"""A lattice nodal force as the load it stands for: spread over that node's share of the solid.

A lattice node stands for the part of the solid around it, so a force on it is a load on that
part, not on a point: a point load's displacement in a continuum is infinite at the point and
grows without bound under refinement, so a reference that is to converge under refinement
(:mod:`fpm.fem.refine`) cannot apply it as one. A node's *share* is its *hat*, the trilinear
shape function of the lattice's cells around it,
``phi_x(p) = prod_k max(0, 1 - |p_k - x_k| / h_k)`` (1 at the node, 0 at its neighbours and
beyond, 2 h_k across; ``h_k`` the lattice's spacing along axis k,
:func:`fpm.fem.samples.lattice_spacing`), and each lattice nodal force ``f`` at node ``x`` becomes:

- on a node of the lattice's surface (a corner of a hexahedron face that belongs to one
  hexahedron only): a traction on the solid's surface within its hat, in proportion to the hat;
- on an interior node: a body load on the solid's volume within its hat, in proportion to it;
- where the hat holds no surface (the solid's surface runs past the node's share), its volume;
  where it holds neither, a point load at the node's place in the solid.

The hat's load falls to zero continuously at the edge of its support, so a refined mesh
resolves it sooner than a uniform patch's, which jumps.

The surface and the volume are sampled (:class:`fpm.fem.samples.Samples`: points no further
apart than h / :data:`~fpm.fem.samples.SAMPLES_PER_H`, each with its area or volume), so the
load is the same at every level of refinement and only the FEM's resolution of it changes.
Every sample then carries a point load that goes to its element's nodes by their shape function
values there (the consistent load of the sampled traction: same resultant, same moment, for any
element whose shape functions reproduce a linear field).

**Resultant and moment.** The shares sum to ``f`` exactly. A load's resultant acts at the
weighted centroid of its samples, which where the hat is cut by an edge of the solid is not on
the force's line of action, so the spread force would add a couple the lattice's force has
not. The weights are therefore tilted linearly across the samples (``w_q (1 + g . (p_q - c))``,
which leaves their sum unchanged) so that their centroid moves onto the line through ``x``
along ``f``, as far as their extent allows (not off a flat surface's plane) and no weight
turns negative: on a flat surface the spread load then has the lattice force's resultant and
moment exactly (tests/core/test_refine.py).

Units: m, N, m^2, m^3.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from ..model.tetrahedra import EDGES
from .samples import Samples, concatenate, trilinear


@dataclass
class Spread:
    """Point loads at samples equivalent to the lattice's nodal forces (:func:`spread`).

    Attributes:
        samples: the samples that carry load (surface, then volume, then fallback points).
        forces: (L, Q, 3) the load on each sample per load case, N.
        kinds: per loaded lattice node, how it was spread: ``"traction"``, ``"body"`` or
            ``"point"`` (keyed by node index).
    """

    samples: Samples
    forces: np.ndarray
    kinds: dict[int, str]


def spread(
    lattice: np.ndarray,
    surface: np.ndarray,
    spacing: np.ndarray,
    forces: np.ndarray,
    on_surface: Samples,
    in_volume: Callable[[], Samples],
    at_nodes: Samples,
) -> Spread:
    """Spread the lattice's nodal ``forces`` (L, N, 3), N, over the nodes' hats (module
    docstring).

    Args:
        lattice: (N, 3) lattice node positions, m.
        surface: (N,) bool, the lattice's surface nodes
            (:func:`fpm.fem.samples.lattice_surface`).
        spacing: (3,) the lattice's spacing along each axis
            (:func:`fpm.fem.samples.lattice_spacing`), m.
        forces: (L, N, 3) nodal forces per load case, N.
        on_surface: samples of the solid's surface near the loaded nodes.
        in_volume: makes the samples of the solid's volume near the loaded nodes (called only
            when an interior node is loaded, or a surface node's hat holds no surface).
        at_nodes: (N) one sample per lattice node: where it lies in the solid (the fallback
            point load).
    """
    loaded = np.flatnonzero(np.any(forces != 0, axis=(0, 2)))
    n_cases = len(forces)
    volume: list[Samples] = []  # made on first need

    def share(node: int) -> tuple[Samples, str]:
        if surface[node] and (chosen := _under_hat(on_surface, lattice[node], spacing)) is not None:
            return chosen, "traction"
        if not volume:
            volume.append(in_volume())
        if (chosen := _under_hat(volume[0], lattice[node], spacing)) is not None:
            return chosen, "body"
        return at_nodes.take(np.array([node])), "point"

    pieces: list[Samples] = []
    loads: list[np.ndarray] = []
    kinds: dict[int, str] = {}
    for node in (int(i) for i in loaded):
        chosen, kinds[node] = share(node)
        on_samples = np.zeros((n_cases, len(chosen), 3))
        for case in range(n_cases):
            f = forces[case, node]
            if np.any(f != 0):
                on_samples[case] = (
                    tilted_weights(chosen.points, chosen.weights, lattice[node], f)[:, None]
                    * f[None, :]
                )
        pieces.append(chosen)
        loads.append(on_samples)
    width = at_nodes.local.shape[1]
    samples = concatenate(pieces, width)
    out = np.concatenate(loads, axis=1) if loads else np.zeros((n_cases, 0, 3))
    return Spread(samples, out, kinds)


def hat(points: np.ndarray, node: np.ndarray, spacing: np.ndarray) -> np.ndarray:
    """(Q,) the lattice node's hat at ``points`` (Q, 3): the trilinear shape function of the
    lattice's cells around ``node`` (3,), ``spacing`` (3,) m apart (module docstring)."""
    return np.prod(np.clip(1.0 - np.abs(points - node) / spacing, 0.0, None), axis=1)


def _under_hat(samples: Samples, node: np.ndarray, spacing: np.ndarray) -> Samples | None:
    """The ``samples`` within ``node``'s hat, each weight times the hat there (None: none)."""
    values = hat(samples.points, node, spacing)
    inside = np.flatnonzero(values > 0)
    if not len(inside) or values[inside] @ samples.weights[inside] <= 0:
        return None
    chosen = samples.take(inside)
    return Samples(chosen.points, chosen.weights * values[inside], chosen.element, chosen.local)


def tilted_weights(
    points: np.ndarray, weights: np.ndarray, node: np.ndarray, force: np.ndarray
) -> np.ndarray:
    """(Q,) shares of ``force`` on the samples (``points`` (Q, 3) with ``weights`` (Q,)), summing
    to 1: the weights, tilted linearly so that their centroid lies on the line through ``node``
    along ``force`` where the samples' extent allows it, none negative (module docstring)."""
    total = weights.sum()
    if len(points) == 1 or total <= 0:
        return np.full(len(points), 1.0 / len(points))
    w = weights / total
    centroid = w @ points
    direction = force / np.linalg.norm(force)
    target = node + ((centroid - node) @ direction) * direction
    d = points - centroid
    second = (w[:, None] * d).T @ d  # (3, 3) second moment about the centroid
    values, vectors = np.linalg.eigh(second)
    scale = values.max()
    if scale <= 0:
        return w
    keep = values > 1e-6 * scale
    shift = vectors[:, keep].T @ (target - centroid)
    g = vectors[:, keep] @ (shift / values[keep])  # sum w (1 + g.d) d = second @ g = target - c
    tilt = d @ g
    lowest = tilt.min()
    if lowest < -1:  # would turn a weight negative: go as far as it allows
        tilt *= -1 / lowest
    out = w * (1 + tilt)
    return out / out.sum()


def tetrahedron_nodal_loads(
    elements: np.ndarray, n_nodes: int, samples: Samples, forces: np.ndarray
) -> np.ndarray:
    """(L, M, 3) consistent nodal forces of point loads ``forces`` (L, Q, 3) at ``samples``
    (barycentric ``local``) on 10-node tetrahedra ``elements`` (T, 10) of ``n_nodes`` nodes."""
    lam = samples.local
    corner = lam * (2 * lam - 1)
    edge = 4 * lam[:, EDGES[:, 0]] * lam[:, EDGES[:, 1]]
    weights = np.concatenate([corner, edge], axis=1)  # (Q, 10)
    return _scatter(elements[samples.element], weights, forces, n_nodes)


def hexahedron_nodal_loads(
    hexahedra: np.ndarray, n_nodes: int, samples: Samples, forces: np.ndarray
) -> np.ndarray:
    """(L, M, 3) consistent nodal forces of point loads ``forces`` (L, Q, 3) at ``samples``
    (natural ``local``) on 8-node hexahedra (H, 8) of ``n_nodes`` nodes."""
    weights, _ = trilinear(samples.local)  # (Q, 8)
    return _scatter(hexahedra[samples.element], weights, forces, n_nodes)


def _scatter(
    nodes: np.ndarray, weights: np.ndarray, forces: np.ndarray, n_nodes: int
) -> np.ndarray:
    """Sum ``forces`` (L, Q, 3) times ``weights`` (Q, k) onto ``nodes`` (Q, k)."""
    out = np.zeros((len(forces), n_nodes, 3))
    flat = nodes.ravel()
    for case in range(len(forces)):
        for i in range(3):
            out[case, :, i] = np.bincount(
                flat, (forces[case, :, i, None] * weights).ravel(), n_nodes
            )
    return out
