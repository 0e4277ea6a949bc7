"""Selectors and forces as short strings (``face:z-``, ``nearest:x,y,z:fx,fy,fz``; m, N), as
the command line and the SDK take them."""

from __future__ import annotations

import math
from typing import Any

from ...model.spec import FACES

SELECTOR_HELP = "face:z- | node:I | at:X,Y,Z | nearest:X,Y,Z | box:X0,Y0,Z0:X1,Y1,Z1 (lengths in m)"
FORCE_HELP = (
    "SELECTOR:FX,FY,FZ[:distribute] or point:X,Y,Z:FX,FY,FZ (N; e.g. point:0,0,0.05:0,0,-0.5, "
    "a force at that point of the surface spread over its cell's nodes, or "
    "face:z+:0,0,-2:distribute); several forces of one load case separated by ';'"
)


def _vector(text: str, what: str) -> list[float]:
    parts = text.split(",")
    try:
        values = [float(p) for p in parts]
    except ValueError:
        values = []
    if len(values) != 3 or not all(math.isfinite(v) for v in values):
        raise ValueError(f"{what} must be three numbers x,y,z (got {text!r})")
    return values


def _selector(parts: list[str], text: str) -> tuple[dict[str, Any], list[str]]:
    """The selector at the start of ``parts`` and the parts left over."""
    kind = parts[0].strip().lower()
    if kind == "face":
        if len(parts) < 2 or parts[1].strip() not in FACES:
            raise ValueError(f"{text!r}: a face is one of x-, x+, y-, y+, z-, z+ (e.g. face:z-)")
        return {"face": parts[1].strip()}, parts[2:]
    if kind == "node":
        try:
            node = int(parts[1])
        except (IndexError, ValueError):
            raise ValueError(f"{text!r}: give a node index, e.g. node:12") from None
        return {"node": node}, parts[2:]
    if kind in ("at", "nearest", "point"):
        if len(parts) < 2:
            raise ValueError(f"{text!r}: give a point, e.g. {kind}:0.05,0.05,0.1")
        return {kind: _vector(parts[1], f"{text!r}: the point")}, parts[2:]
    if kind == "box":
        if len(parts) < 3:
            raise ValueError(f"{text!r}: give two corners, e.g. box:0,0,0:0.1,0.1,0.01")
        lo = _vector(parts[1], f"{text!r}: the low corner")
        hi = _vector(parts[2], f"{text!r}: the high corner")
        return {"box": [lo, hi]}, parts[3:]
    raise ValueError(f"{text!r}: a selector is {SELECTOR_HELP}")


def parse_selector(text: str) -> dict[str, Any]:
    """A spec selector from its short form: ``face:z-``, ``node:12``, ``at:x,y,z``,
    ``nearest:x,y,z`` or ``box:x0,y0,z0:x1,y1,z1``."""
    selector, rest = _selector(text.split(":"), text)
    if "point" in selector:
        raise ValueError(
            f"{text!r}: 'point' places a force (--force point:X,Y,Z:FX,FY,FZ); to select nodes "
            "use at or nearest"
        )
    if rest:
        raise ValueError(f"{text!r}: unexpected {':'.join(rest)!r} after the selector")
    return selector


def parse_force(text: str) -> list[dict[str, Any]]:
    """The forces of one load case from their short form, ``SELECTOR:FX,FY,FZ[:distribute]``,
    several separated by ``;``."""
    forces = []
    for one in text.split(";"):
        one = one.strip()
        if not one:
            continue
        selector, rest = _selector(one.split(":"), one)
        if not rest:
            raise ValueError(f"{one!r}: give the force after the selector, e.g. {one}:0,0,-1")
        force = {**selector, "vector": _vector(rest[0], f"{one!r}: the force")}
        flags = [r.strip().lower() for r in rest[1:]]
        if flags and "point" in selector:
            raise ValueError(f"{one!r}: a force at a point takes no ':distribute'")
        if flags and flags != ["distribute"]:
            raise ValueError(f"{one!r}: after the force only ':distribute' may follow")
        if flags:
            force["distribute"] = True
        forces.append(force)
    if not forces:
        raise ValueError(f"{text!r}: no force given ({FORCE_HELP})")
    return forces
