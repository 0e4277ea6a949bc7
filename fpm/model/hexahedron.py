"""The 8-node hexahedron: local node order and the spring families it spawns.

Local node numbering (the usual VTK / Abaqus C3D8 order), natural coordinates (r, s, t)::

         7 -------- 6          t
        /|         /|          |  s
       4 -------- 5 |          | /
       | |        | |          |/
       | 3 -------|-2          +---- r
       |/         |/
       0 -------- 1

    node:  0   1   2   3   4   5   6   7
    r:    -1  +1  +1  -1  -1  +1  +1  -1
    s:    -1  -1  +1  +1  -1  -1  +1  +1
    t:    -1  -1  -1  -1  +1  +1  +1  +1

Nodes 0-3 form the bottom face (t = -1) counter-clockwise seen from above, 4-7 the top face.
"""

from __future__ import annotations

from itertools import product

import numpy as np

NATURAL = np.array(
    [
        [-1, -1, -1],
        [+1, -1, -1],
        [+1, +1, -1],
        [-1, +1, -1],
        [-1, -1, +1],
        [+1, -1, +1],
        [+1, +1, +1],
        [-1, +1, +1],
    ],
    dtype=float,
)
"""(8, 3) natural coordinates (r_i, s_i, t_i) of the local nodes (paper Eq. 3)."""
FACE_CORNERS = np.array(
    [np.flatnonzero(NATURAL[:, axis] == side) for axis in range(3) for side in (-1.0, 1.0)]
)
"""(6, 4) the local nodes (ascending) of each local face ``2 * axis + (side > 0)``: r-, r+, s-,
s+, t-, t+."""

EDGES = [
    (0, 1),
    (1, 2),
    (2, 3),
    (3, 0),
    (4, 5),
    (5, 6),
    (6, 7),
    (7, 4),
    (0, 4),
    (1, 5),
    (2, 6),
    (3, 7),
]
FACE_DIAGONALS = [
    (0, 2),
    (1, 3),
    (4, 6),
    (5, 7),
    (0, 5),
    (1, 4),
    (3, 6),
    (2, 7),
    (0, 7),
    (3, 4),
    (1, 6),
    (2, 5),
]
BODY_DIAGONALS = [(0, 6), (1, 7), (2, 4), (3, 5)]

SPRING_FAMILIES: dict[str, list[tuple[int, int]]] = {
    "axis": EDGES,
    "axis+face": EDGES + FACE_DIAGONALS,
    "full": EDGES + FACE_DIAGONALS + BODY_DIAGONALS,
}
"""Local node pairs joined by a spring, per connectivity (physics.md, Geometry)."""


FAMILIES = ("axis", "face", "body")
"""Spring families: hexahedron edges, face diagonals, body diagonals (docs/physics.md,
*Springs*)."""


GAUSS_POINTS = np.array(list(product((-1, 1), repeat=3)), dtype=float) / np.sqrt(3.0)
"""(8, 3) natural coordinates of the 2x2x2 Gauss-Legendre points; every weight is 1."""


def shape_functions(point: np.ndarray) -> np.ndarray:
    """(8,) trilinear N_i = (1 + r r_i)(1 + s s_i)(1 + t t_i) / 8 at ``point`` (paper Eq. 3)."""
    return np.prod(1 + NATURAL * np.asarray(point), axis=1) / 8


def shape_function_gradients(point: np.ndarray) -> np.ndarray:
    """(8, 3) dN_i / d(r, s, t) at natural ``point`` (3,)."""
    factors = 1 + NATURAL * np.asarray(point)  # (8, 3): (1 + r r_i), (1 + s s_i), (1 + t t_i)
    grad = np.empty((8, 3))
    for a in range(3):
        others = [b for b in range(3) if b != a]
        grad[:, a] = NATURAL[:, a] * factors[:, others[0]] * factors[:, others[1]] / 8
    return grad


def jacobians(coords: np.ndarray, point: np.ndarray) -> np.ndarray:
    """(H, 3, 3) J_ab = d x_b / d xi_a at natural ``point`` for ``coords`` (H, 8, 3), m."""
    return np.einsum("na,hnb->hab", shape_function_gradients(point), coords)


def connectivity_families(connectivity: str) -> tuple[str, ...]:
    """The families a connectivity has: axis 1, axis+face 2, full 3."""
    return FAMILIES[: {"axis": 1, "axis+face": 2, "full": 3}[connectivity]]


def local_families(connectivity: str) -> np.ndarray:
    """(P,) int8 family index (into :data:`FAMILIES`) of each of :func:`local_pairs`."""
    sizes = [len(EDGES), len(FACE_DIAGONALS), len(BODY_DIAGONALS)]
    family = np.repeat(np.arange(3, dtype=np.int8), sizes)
    return family[: len(SPRING_FAMILIES[connectivity])]


def local_pairs(connectivity: str) -> np.ndarray:
    """(P, 2) local node pairs of one hexahedron for ``connectivity``."""
    return np.array(SPRING_FAMILIES[connectivity], dtype=np.int64)
