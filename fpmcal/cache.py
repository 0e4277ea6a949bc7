"""The work of ``fpmcal calibrate`` kept beside its spec, ``SPEC.fpmcache/``, so that a run that
failed later (the damping stage), or a rerun with another setting, starts from it.

Two kinds of entries, each written before the stage after it starts:

- ``reference/<fem hash>.json`` and ``.f64``: the FEM reference (:meth:`FemResult.to_stored`,
  with the spec part it was solved for and its wall time, s), keyed by
  :func:`store.hashing.fem_hash` (geometry, material, supports, loads, validation cases,
  reference settings), as the service keys its stored references;
- ``chains/<key>.json``: stage 1's chain results (:class:`ChainResult`), keyed by the spec
  without the settings only the damping stage reads (:func:`store.hashing.stiffness_spec`), the
  chain count and the digest of the load cases' reference displacements they were fitted to.

A reference is reused as stored when its hash matches. The linear FEM (no gravity) is linear
in its loads, so a spec whose load and validation cases are, case by case in the same order,
another stored spec's forces times a factor (a smaller press) is answered with that
reference's displacements times each case's factor (:func:`scaled_factors`): its refinement
levels stop at the same level (their change is relative per case), and the displacements are
those of a new solve to within the solver's tolerance. Anything else (another mesh, material,
support, force point or direction, a neo-Hookean or supplied reference) is solved anew.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from fpm.fem.solution import FemResult
from fpm.fitting.reference import reference_displacements
from fpm.fitting.stiffness_stage import ChainResult
from fpm.model.spec import MODEL_VERSION
from store.hashing import canonical, fem_hash, fem_spec, stiffness_spec

SUFFIX = ".fpmcache"
"""The cache of ``organ.json`` is the directory ``organ.json.fpmcache`` beside it."""

SAME_FACTOR = 1e-12
"""Relative tolerance of :func:`scaled_factors`: a case is a scaled copy of another when its
force vectors are the other's times one factor to this precision."""


@dataclass
class Reused:
    """A stored reference handed back: ``factors`` (one per load case, then validation case;
    all 1 when the spec is the stored one) and the wall time its solve took, s."""

    reference: FemResult
    factors: list[float]
    seconds: float

    @property
    def scaled(self) -> bool:
        return any(f != 1.0 for f in self.factors)


def cache_dir(spec_path: str | os.PathLike[str]) -> Path:
    """``SPEC.fpmcache`` beside the spec file."""
    path = Path(spec_path)
    return path.with_name(path.name + SUFFIX)


def _digest(data: Any) -> str:
    return hashlib.sha256(canonical(data)).hexdigest()


def _write(path: Path, data: bytes) -> None:
    """Write ``data`` to ``path`` at once (a temporary file renamed): an interrupted write
    leaves no half entry."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + f".{os.getpid()}.tmp")
    tmp.write_bytes(data)
    tmp.replace(path)


def _cases(part: dict[str, Any]) -> list[dict[str, Any]]:
    """The load cases then validation cases of a :func:`fem_spec` part."""
    return list(part.get("load_cases") or []) + list(part.get("validation_cases") or [])


def _without_loads(part: dict[str, Any]) -> dict[str, Any]:
    """A :func:`fem_spec` part with each case's force vectors and names left out (what must be
    equal for one case to be a scaled copy of another)."""
    out = {k: v for k, v in part.items() if k not in ("load_cases", "validation_cases")}
    shapes = []
    for case in _cases(part):
        forces = [{k: v for k, v in f.items() if k != "vector"} for f in case["forces"]]
        shapes.append(
            {k: v for k, v in case.items() if k not in ("name", "forces")} | {"forces": forces}
        )
    out["cases"] = shapes
    out["validation_count"] = len(part.get("validation_cases") or [])
    return out


def scaled_factors(new: dict[str, Any], old: dict[str, Any]) -> list[float] | None:
    """Per case (load cases, then validation cases), the factor that makes ``old``'s forces
    ``new``'s, for two :func:`fem_spec` parts equal in everything but their force vectors and
    case names; None when they differ elsewhere, a case is not a scaled copy (to
    :data:`SAME_FACTOR`), or gravity loads them (the weight does not scale with the forces)."""
    if new.get("fpm") or old.get("fpm") or _without_loads(new) != _without_loads(old):
        return None
    factors = []
    for a, b in zip(_cases(new), _cases(old), strict=True):
        u = np.array([f["vector"] for f in a["forces"]], dtype=float).ravel()
        v = np.array([f["vector"] for f in b["forces"]], dtype=float).ravel()
        size = float(v @ v)
        if not size > 0:
            return None
        factor = float(u @ v) / size
        if factor == 0 or not np.allclose(
            u, factor * v, rtol=0, atol=SAME_FACTOR * np.abs(u).max()
        ):
            return None
        factors.append(1.0 if math.isclose(factor, 1.0, rel_tol=SAME_FACTOR) else factor)
    return factors


class Cache:
    """The entries of one spec's cache directory ``root``."""

    def __init__(self, root: Path):
        self.root = root

    def _reference_files(self, key: str) -> tuple[Path, Path]:
        base = self.root / "reference" / key
        return base.with_suffix(".json"), base.with_suffix(".f64")

    def reference(self, spec: dict[str, Any]) -> Reused | None:
        """The stored reference for the validated spec dump ``spec``: the one stored under its
        :func:`fem_hash`, else a linear reference of the same solid whose cases are scaled
        copies of ``spec``'s (:func:`scaled_factors`), scaled; None when there is none."""
        part = fem_spec(spec)
        found = self._read(fem_hash(spec))
        if found is not None:
            layout, raw = found
            return Reused(self._result(layout, raw, part, None), [1.0] * len(_cases(part)),
                          float(layout.get("seconds", 0.0)))  # fmt: skip
        folder = self.root / "reference"
        for path in sorted(folder.glob("*.json")) if folder.is_dir() else []:
            stored = self._read(path.stem)
            if stored is None or stored[0].get("model") != "linear":
                continue
            factors = scaled_factors(part, stored[0].get("spec") or {})
            if factors is not None:
                result = self._result(stored[0], stored[1], part, factors)
                return Reused(result, factors, float(stored[0].get("seconds", 0.0)))
        return None

    def _read(self, key: str) -> tuple[dict[str, Any], bytes] | None:
        layout_path, raw_path = self._reference_files(key)
        try:
            return json.loads(layout_path.read_text()), raw_path.read_bytes()
        except (OSError, ValueError):  # absent, or left half written by another program
            return None

    @staticmethod
    def _result(
        layout: dict[str, Any], raw: bytes, part: dict[str, Any], factors: list[float] | None
    ) -> FemResult:
        """The stored reference, its cases named as ``part``'s, scaled by ``factors``."""
        result = FemResult.from_stored(layout, raw)
        result.load_cases = [c["name"] for c in _cases(part)]
        if factors is not None:
            result.displacements = result.displacements * np.asarray(factors)[:, None, None]
        return result

    def save_reference(self, spec: dict[str, Any], result: FemResult, seconds: float) -> None:
        """Store ``result``, solved for the spec dump ``spec`` in ``seconds`` s."""
        layout, raw = result.to_stored()
        layout.update(spec=fem_spec(spec), seconds=float(seconds))
        layout_path, raw_path = self._reference_files(fem_hash(spec))
        _write(raw_path, raw)  # the layout last: it is what a reader looks for
        _write(layout_path, json.dumps(layout).encode())

    @staticmethod
    def chains_key(spec: dict[str, Any], chains: int, reference: Any) -> str:
        """The identity of stage 1's chains: :func:`store.hashing.stiffness_spec` of the spec
        dump, the chain count, the load cases' reference displacements (their float64
        bytes)."""
        n = len(spec["load_cases"])
        u = np.ascontiguousarray(reference_displacements(reference)[:n], dtype="<f8")
        identity = {
            "model": MODEL_VERSION,
            "spec": stiffness_spec(spec),
            "chains": int(chains),
            "reference": hashlib.sha256(u.tobytes()).hexdigest(),
        }
        return _digest(identity)

    def chains(self, key: str) -> tuple[list[ChainResult], float] | None:
        """Stored chain results under ``key`` and the wall time they took, s; None if none."""
        try:
            data = json.loads((self.root / "chains" / f"{key}.json").read_text())
            return [ChainResult.from_dict(c) for c in data["chains"]], float(data["seconds"])
        except (OSError, ValueError, KeyError, TypeError):
            return None

    def save_chains(self, key: str, chains: list[ChainResult], seconds: float) -> None:
        """Store stage 1's ``chains`` under ``key`` (they took ``seconds`` s)."""
        data = {"chains": [c.to_dict() for c in chains], "seconds": float(seconds)}
        _write(self.root / "chains" / f"{key}.json", json.dumps(data).encode())


def _spec_dump(problem: Any) -> dict[str, Any]:
    return problem.spec.model_dump(mode="json")


def reference(
    cache: Cache | None, problem: Any, solve: Callable[[], FemResult], say: Callable[[str], None]
) -> FemResult:
    """The reference of ``problem``: stored (``say`` tells which, and the time it saves), or
    ``solve()``, then stored before the calibration goes on. A supplied reference
    (``reference.displacements``) is not stored: nothing is solved for it."""
    spec = _spec_dump(problem)
    if cache is None or spec["reference"].get("displacements") is not None:
        return solve()
    found = cache.reference(spec)
    if found is not None:
        how = "as stored"
        if found.scaled:
            factors = ", ".join(f"{f:.4g}" for f in found.factors)
            how = f"scaled per case by {factors} (the linear FEM under the same forces scaled)"
        say(f"FEM reference: reused from {cache.root} {how}, saving {found.seconds:.1f} s")
        return found.reference
    t0 = time.perf_counter()
    result = solve()
    cache.save_reference(spec, result, time.perf_counter() - t0)
    return result


def chains(
    cache: Cache | None,
    problem: Any,
    reference: Any,
    count: int,
    say: Callable[[str], None],
) -> tuple[list[ChainResult] | None, Callable[[list[ChainResult]], None] | None]:
    """(stage 1's stored chain results or None, where to store new ones or None): what
    :func:`fpm.fitting.calibration.calibrate` takes as ``stored_chains`` and ``keep_chains``;
    ``say`` tells when they are reused and the time that saves."""
    if cache is None:
        return None, None
    key = Cache.chains_key(_spec_dump(problem), count, reference)
    found = cache.chains(key)
    if found is not None:
        where, saved = cache.root, found[1]
        say(f"stiffness: stage 1's {count} chain(s) reused from {where}, saving {saved:.1f} s")
        return found[0], None
    t0 = time.perf_counter()

    def keep(results: list[ChainResult]) -> None:
        cache.save_chains(key, results, time.perf_counter() - t0)

    return None, keep
