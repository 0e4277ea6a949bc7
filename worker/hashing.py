"""Content hashes: the identity of a spec and of the FEM reference it needs.

Both hash the canonical JSON (sorted keys, no whitespace) of the spec *after* validation with
every default filled in, so two specs that differ only in spelt-out defaults are the same.
"""

import hashlib
import json
from typing import Any

from fpm.spec import MODEL_VERSION

FEM_FIELDS = ("geometry", "material", "fixed", "load_cases")
"""The spec fields the FEM reference depends on."""


def canonical(data: Any) -> bytes:
    """Canonical JSON bytes of ``data``."""
    return json.dumps(data, sort_keys=True, separators=(",", ":")).encode()


def spec_hash(spec: dict[str, Any]) -> str:
    """sha256 of the whole validated spec (a dumped :class:`fpm.spec.ProblemSpec`) and of
    :data:`fpm.spec.MODEL_VERSION`, so results of older numerics are not handed out again."""
    return hashlib.sha256(canonical({"model": MODEL_VERSION, "spec": spec})).hexdigest()


def fem_spec(spec: dict[str, Any]) -> dict[str, Any]:
    """The part of ``spec`` the FEM reference depends on (itself a loadable spec)."""
    return {name: spec[name] for name in FEM_FIELDS}


def fem_hash(spec: dict[str, Any]) -> str:
    """sha256 of geometry + material + fixed + load cases: the FEM reference's identity."""
    return hashlib.sha256(canonical(fem_spec(spec))).hexdigest()
