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
"""Spring families: hexahedron edges, face diagonals, body diagonals (physics.md, Round 2)."""


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
