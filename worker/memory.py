"""How much memory a calibration job needs, and whether this worker can give it.

A job that its worker's memory cannot hold must be refused before it starts, with the reason,
instead of being killed by the kernel's OOM killer halfway (which looks like a crash and is
retried on the same kind of worker). The estimate is linear in the lattice's nodes, fitted to
peaks measured on this project's organs (docs/notes/2026-11-28-calibration-measured.md: the
default model calibrated in one process, both stage-1 chains at once, which bounds every single
job of it):

    bytes = BASE + PER_NODE * nodes:  0.90 GB at 19,692 nodes (3 mm), 2.90 GB at 93,705 (1.75 mm)

The limit is ``FPM_WORKER_MEMORY`` (bytes, or with a K/M/G suffix: ``3G``) when set, else the
worker's control group (cgroup v2 ``memory.max``, v1 ``memory.limit_in_bytes``; a container's
``mem_limit``), else none (no refusal).
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from pathlib import Path

BASE = 0.36e9
"""Bytes a worker holds before a lattice: Python, NumPy, SciPy, numba and the job's code."""
PER_NODE = 27_100.0
"""Bytes per lattice node at the peak of a default-model calibration (measured, see above)."""
NO_LIMIT = 1 << 60
"""cgroup v1 writes a number this large (about 2^63) when there is no limit."""

CGROUP_FILES = ("/sys/fs/cgroup/memory.max", "/sys/fs/cgroup/memory/memory.limit_in_bytes")


class MemoryRefused(RuntimeError):
    """The job needs more memory than this worker may use."""


def parse_bytes(text: str) -> int:
    """``"3G"`` -> 3 * 2**30, ``"512M"``, ``"1000000"``; ValueError if it is not a size."""
    text = text.strip().upper().removesuffix("B")
    scale = {"K": 1 << 10, "M": 1 << 20, "G": 1 << 30, "T": 1 << 40}.get(text[-1:], 1)
    number = float(text[:-1] if scale > 1 else text)
    if number <= 0:
        raise ValueError(f"not a positive size: {text!r}")
    return int(number * scale)


def memory_limit(
    environ: Mapping[str, str] | None = None,
    files: tuple[str, ...] = CGROUP_FILES,
    machine: bool = False,
) -> tuple[int, str] | None:
    """(bytes, where it came from) of this worker's memory limit, or None when it has none.
    ``machine``: a process of its own (``fpmcal``), whose limit without one set is the
    machine's memory."""
    env: Mapping[str, str] = os.environ if environ is None else environ
    if env.get("FPM_WORKER_MEMORY"):
        return parse_bytes(env["FPM_WORKER_MEMORY"]), "FPM_WORKER_MEMORY"
    for name in files:
        try:
            text = Path(name).read_text().strip()
        except OSError:
            continue
        if text.isdigit() and int(text) < NO_LIMIT:
            return int(text), name
    if machine and hasattr(os, "sysconf"):
        try:
            return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES"), "the machine's memory"
        except (ValueError, OSError):
            return None
    return None


def estimated_bytes(nodes: int) -> float:
    """The peak memory of a calibration job on a lattice of ``nodes`` nodes, bytes."""
    return BASE + PER_NODE * nodes


def check(nodes: int, limit: tuple[int, str] | None = None, machine: bool = False) -> None:
    """Raise :class:`MemoryRefused` when a job on ``nodes`` nodes cannot fit in ``limit``
    (default: :func:`memory_limit`). ``machine``: the check of ``fpmcal``, a calibration in a
    process of its own (the limit defaults to the machine's memory; the message names the
    machine, not a worker)."""
    limit = memory_limit(machine=machine) if limit is None else limit
    if limit is None:
        return
    need, (have, source) = estimated_bytes(nodes), limit
    if need > have:
        where = (
            "this machine may use {} ({}): use a coarser spacing"
            if machine
            else "this worker may use {} ({}): run it on a worker with more memory "
            "(FPM_WORKER_MEMORY or the container's limit) or use a coarser spacing"
        )
        raise MemoryRefused(
            f"this job needs about {need / 1e9:.2f} GB for {nodes:,} lattice nodes and "
            + where.format(f"{have / 1e9:.2f} GB", source)
        )
