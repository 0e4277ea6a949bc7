"""The ``binary`` export: the JSON export's step data in a compact little-endian layout.

What the native step (``fpm/native/fpm_step.c``) reads; the JSON export stays the contract and
this is a packing of its numbers (no names, perturbed lists or fit figures). Layout, version 1,
every integer unsigned 32-bit unless said, every real float64, all little-endian::

    offset  field              type        meaning
    0       magic              4 bytes     b"FPMB"
    4       version            u32         1
    8       n_nodes            u32         N
    12      n_springs          u32         S
    16      n_hexahedra        u32         H (0: no volume term)
    20      n_fixed            u32         F
    24      n_cases            u32         L load cases
    28      n_case_entries     u32         E loaded nodes over all load cases
    32      n_share_rows       u32         R nodes with load shares (loads "hat"; else 0)
    36      n_share_entries    u32         Z
    40      d                  f64         nodal damping, N s/m (see below)
    48      dt                 f64         time step, s
    56      settle_tolerance   f64         the export's parameters.settle_tolerance
    64      settle_stiffness   f64         N/m, parameters.settle_stiffness
    72      gravity            f64[3]      m/s^2
    96      total_bytes        u64         the file's length, checksum included
    104     nodes              f64[3N]     rest positions x y z per node, m
            masses             f64[N]      kg
            fixed              u32[F]      node indices
            spring_i           u32[S]
            spring_j           u32[S]
            rest_lengths       f64[S]      m
            stiffness          f64[S]      N/m
            hexahedra          u32[8H]     corners in fpm.runtime.NATURAL order
            volume_stiffness   f64[H]      kappa, Pa
            rest_volumes       f64[H]      m^3
            case_offsets       u32[L+1]    case c's entries are case_offsets[c]..[c+1]
            case_nodes         u32[E]
            case_forces        f64[3E]     N
            share_nodes        u32[R]      row r's shares spread a force on share_nodes[r]
            share_offsets      u32[R+1]    over share_indices[share_offsets[r]..[r+1]]
            share_indices      u32[Z]
            share_weights      f64[Z]
            crc32              u32         CRC-32 (zlib's) of every byte before it

The springs and hexahedra are structure-of-arrays: a reader takes each array with one copy.
``d`` and ``dt`` are those of the step a reader runs (every node at once): the JSON's
``parameters.engine`` where it has that block, else its ``parameters.d`` and ``dt`` (the
calibration kernel's).
"""

from __future__ import annotations

import struct
import zlib
from collections.abc import Sequence
from typing import Any

import numpy as np

from .errors import ExportError

MAGIC = b"FPMB"
VERSION = 1
HEADER = struct.Struct("<4s9I4d3dQ")
"""The header: magic, version, the 8 counts, d, dt, settle_tolerance, settle_stiffness,
gravity, total_bytes (104 bytes)."""


def _u32(values: Any, name: str) -> bytes:
    a = np.asarray(values, dtype=np.int64).ravel()
    if a.size and (a.min() < 0 or a.max() > 0xFFFFFFFF):
        raise ExportError(f"{name}: indices outside 0..2^32-1 do not fit the binary export")
    return a.astype("<u4").tobytes()


def _f64(values: Any) -> bytes:
    return np.asarray(values, dtype=float).ravel().astype("<f8").tobytes()


def pack(
    *,
    nodes: np.ndarray,
    masses: np.ndarray,
    fixed: np.ndarray,
    springs: np.ndarray,
    rest_lengths: np.ndarray,
    stiffness: np.ndarray,
    hexahedra: np.ndarray,
    volume_stiffness: np.ndarray,
    rest_volumes: np.ndarray,
    d: float,
    dt: float,
    settle_tolerance: float,
    settle_stiffness: float,
    gravity: Sequence[float],
    cases: Sequence[tuple[np.ndarray, np.ndarray]] = (),
    shares: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None = None,
) -> bytes:
    """The binary layout of these arrays (shapes as :class:`fpm.runtime.Runtime`'s: nodes
    (N, 3), springs (S, 2), hexahedra (H, 8), fixed the indices (F,)); ``cases``: per load case
    its nodes (M,) and forces (M, 3); ``shares``: (share_nodes, share_offsets, share_indices,
    share_weights) of the module docstring. Values are written as given: the reader checks
    them."""
    springs = np.asarray(springs).reshape(-1, 2)
    hexahedra = np.asarray(hexahedra).reshape(-1, 8)
    case_nodes = [np.asarray(n, dtype=np.int64).ravel() for n, _ in cases]
    offsets = np.concatenate([[0], np.cumsum([len(n) for n in case_nodes])]).astype(np.int64)
    share = shares or (np.zeros(0), np.zeros(1), np.zeros(0), np.zeros(0))
    body = b"".join(
        [
            _f64(nodes),
            _f64(masses),
            _u32(fixed, "fixed"),
            _u32(springs[:, 0], "spring_i"),
            _u32(springs[:, 1], "spring_j"),
            _f64(rest_lengths),
            _f64(stiffness),
            _u32(hexahedra, "hexahedra"),
            _f64(volume_stiffness),
            _f64(rest_volumes),
            _u32(offsets, "case_offsets"),
            _u32(np.concatenate(case_nodes) if case_nodes else [], "case_nodes"),
            _f64([v for _, f in cases for v in np.asarray(f, float).ravel()]),
            _u32(share[0], "share_nodes"),
            _u32(share[1], "share_offsets"),
            _u32(share[2], "share_indices"),
            _f64(share[3]),
        ]
    )
    counts = (
        len(np.asarray(masses).ravel()),
        len(springs),
        len(hexahedra),
        len(np.asarray(fixed).ravel()),
        len(cases),
        int(offsets[-1]),
        len(np.asarray(share[0]).ravel()),
        len(np.asarray(share[2]).ravel()),
    )
    total = HEADER.size + len(body) + 4
    header = HEADER.pack(
        MAGIC, VERSION, *counts, d, dt, settle_tolerance, settle_stiffness, *gravity, total
    )
    data = header + body
    return data + struct.pack("<I", zlib.crc32(data))


def from_json(doc: dict[str, Any]) -> bytes:
    """The binary export of a parsed JSON export (``to_json``'s document)."""
    if doc.get("format") != "fpm-lattice":
        raise ExportError("not an FPM lattice export (its format is not 'fpm-lattice')")
    p = doc["parameters"]
    step = p.get("engine") or p  # the all-at-once step's d and dt where the export has them
    springs = np.asarray(doc["springs"], dtype=float).reshape(-1, 4)
    volume = doc.get("volume_stiffness") is not None
    table = doc.get("load_shares")
    shares = None
    if table is not None:
        shares = tuple(np.asarray(table[k]) for k in ("nodes", "indptr", "indices", "weights"))
    return pack(
        nodes=np.asarray(doc["nodes"], dtype=float),
        masses=np.asarray(doc["masses"], dtype=float),
        fixed=np.asarray(doc["fixed"], dtype=np.int64),
        springs=springs[:, :2].astype(np.int64),
        rest_lengths=springs[:, 2],
        stiffness=springs[:, 3],
        hexahedra=np.asarray(doc["hexahedra"] if volume else [], dtype=np.int64),
        volume_stiffness=np.asarray(doc["volume_stiffness"] if volume else [], dtype=float),
        rest_volumes=np.asarray(doc["rest_volumes"] if volume else [], dtype=float),
        d=float(step["d"]),
        dt=float(step["dt"]),
        settle_tolerance=float(p["settle_tolerance"]),
        settle_stiffness=float(p.get("settle_stiffness", 0.0)),
        gravity=[float(g) for g in p.get("gravity", (0.0, 0.0, 0.0))],
        cases=[(c["nodes"], c["forces"]) for c in doc["load_cases"]],
        shares=shares,  # type: ignore[arg-type]
    )
