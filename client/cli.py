"""``fpm-client``: the service from the command line.

    fpm-client submit examples/paper-material-a.json --wait
    fpm-client status 3f2a9c...
    fpm-client params --E 10000
    fpm-client --json list --status running

The service URL comes from --url, else $FPM_URL, else http://127.0.0.1:8000; the API key
from --api-key, else $FPM_API_KEY.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from typing import Any

import httpx

from .sdk import ApiError, Client
from .table import printable, table, verdict_lines

DEFAULT_URL = "http://127.0.0.1:8000"
STATUSES = ["queued", "running", "succeeded", "failed", "canceled"]
UNSUCCESSFUL = ("failed", "canceled")
"""How a calibration may end without a result (``submit --wait`` then exits 2)."""


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(prog="fpm-client", description="FPM calibration client")
    parser.add_argument("--url", default=os.environ.get("FPM_URL", DEFAULT_URL))
    parser.add_argument("--api-key", default=os.environ.get("FPM_API_KEY"))
    parser.add_argument("--json", action="store_true", help="print the raw JSON answer")
    sub = parser.add_subparsers(dest="command", required=True)
    submit = sub.add_parser("submit", help="submit a calibration")
    submit.add_argument("spec", help="problem spec JSON file")
    submit.add_argument(
        "--wait",
        action="store_true",
        help="wait, with a progress bar on stderr; exit 2 if it fails or is canceled",
    )
    sub.add_parser("status", help="show a calibration").add_argument("id")
    sub.add_parser("cancel", help="cancel a calibration").add_argument("id")
    listing = sub.add_parser("list", help="list calibrations, newest first")
    listing.add_argument("--status", choices=STATUSES)
    listing.add_argument("--limit", type=int, default=20)
    params = sub.add_parser("params", help="stored parameter sets, filtered by material")
    params.add_argument("--E", dest="youngs_modulus", type=float, help="Young's modulus, Pa")
    params.add_argument("--nu", dest="poisson_ratio", type=float, help="Poisson's ratio")
    params.add_argument("--rho", dest="density", type=float, help="density, kg/m^3")
    params.add_argument("--connectivity", choices=["axis", "axis+face", "full"])
    params.add_argument("--name", help="substring of the spec name")
    sub.add_parser("health", help="Redis, workers, queue depth")
    return parser.parse_args(argv)


def mean(values: list[float]) -> float | None:
    """The mean, or None for no values."""
    return sum(values) / len(values) if values else None


def stiffness_text(stiffness: dict[str, float], mode: str | None = None, unit: str = "") -> str:
    """Each family's k: '29.1 (all springs)' for one k, else 'axis 30.2, face 12.1, ...'."""
    values = list(stiffness.values())
    if not values:
        return "-"
    if mode == "single" or (mode is None and len(set(values)) == 1):
        return f"{values[0]:.5g}{unit} (all springs)"
    return ", ".join(f"{name} {k:.5g}" for name, k in stiffness.items()) + unit


def stage_line(c: dict[str, Any]) -> str:
    """Where the calibration is: its stage in words, and the phases it goes through."""
    p = c["progress"]
    stages = " > ".join(p.get("stages") or [])
    return f"{p.get('stage') or p['phase']}" + (f"  [{stages}]" if stages else "")


def discrepancy_rows(
    result: dict[str, Any], names: list[str] | None = None, *, compliance: bool = False
) -> list[list[Any]]:
    """Per load case: relative % (the headline), loaded nodes %, % of h, settle steps, and with
    ``compliance`` the load compliance ratio (:data:`COMPLIANCE_HEADER`; '-' in a result
    stored before it); then the mean. % of h is never shown without the relative figure beside
    it."""
    relative = result["relative_discrepancy"]
    names = names or [f"load case {i + 1}" for i in range(len(relative))]
    columns = (
        relative,
        result["loaded_discrepancy"],
        result["discrepancy_h"],
        result["settle_steps"],
    )
    rows: list[list[Any]] = [[name, *values] for name, *values in zip(names, *columns, strict=True)]
    if len(rows) > 1:
        rows.append(["mean", *(mean(list(v)) for v in columns[:3]), None])
    if compliance:
        ratios = result.get("compliance_ratio") or [None] * len(relative)
        for row, c in zip(rows, [*ratios, None][: len(rows)], strict=True):
            row.append(None if c is None else round(c, 3))
    return rows


DISCREPANCY_HEADERS = ["load case", "relative %", "loaded nodes %", "% of h", "settle steps"]
"""Headers of :func:`discrepancy_rows`: the relative figure first."""

COMPLIANCE_HEADER = "compliance"
"""The load compliance ratio's column: the model's work of the load over the reference's (1.0
feels the reference's stiffness, 1.5 is 1.5 times too soft)."""

VALIDATION_HEADERS = ["validation case (never fitted)", "relative %", "% of h", COMPLIANCE_HEADER]
"""Headers of :func:`validation_rows`."""


def validation_rows(result: dict[str, Any]) -> list[list[Any]]:
    """Per validation case: relative % (the honest figure), % of h and the load compliance
    ratio; then the mean."""
    relative = result.get("validation_relative_discrepancy") or []
    h_percent = result.get("validation_discrepancy_h") or []
    names = result.get("validation_cases") or [f"case {i + 1}" for i in range(len(relative))]
    ratios = result.get("validation_compliance_ratio") or [None] * len(relative)
    rows: list[list[Any]] = [
        [name, rel, h, None if c is None else round(c, 3)]
        for name, rel, h, c in zip(names, relative, h_percent, ratios, strict=True)
    ]
    if len(rows) > 1:
        rows.append(["mean", mean(relative), mean(h_percent), None])
    return rows


def reference_line(result: dict[str, Any]) -> str | None:
    """The reference's estimated error per load case (and validation case), % (None when the
    result has none: not estimated, or stored before the estimate existed)."""
    error = result.get("reference_error")
    if error is None:
        return None
    text = " / ".join(f"{e:.2f}" for e in error)
    validation = result.get("validation_reference_error") or []
    if validation:
        text += "; validation " + " / ".join(f"{e:.2f}" for e in validation)
    refined = result.get("reference_refinements")
    how = (
        f"change from its last refinement ({refined} in all)" if refined else "one-refinement check"
    )
    flag = "  ABOVE 5%: not resolved" if max([*error, *validation]) > 5 else ""
    return f"reference   estimated error {text} % ({how}){flag}"


def show_calibration(c: dict[str, Any]) -> str:
    """A calibration as a short report: status and stage, then the fit with the relative
    discrepancy per load case first."""
    p = c["progress"]
    lines = [
        f"calibration {c['id']}  {printable(c['name'])}",
        f"status      {c['status']} ({p['phase']})",
        f"method      {p.get('method', '-')}",
        f"stage       {stage_line(c)}",
        f"moves       {p['iterations']} of {p['total_iterations']}",
    ]
    if p.get("best_cost") is not None:
        t = p.get("temperature")
        lines.append(
            f"best cost   {p['best_cost']:.5g}" + (f" (T = {t:.3g})" if t is not None else "")
        )
    damping = p.get("damping")
    if damping and c["status"] != "succeeded":
        best = damping.get("best_d")
        lines.append(
            f"damping     {damping.get('step') or 'starting'}: {damping.get('runs', 0)} d tried"
            + (f", fastest so far d = {best:.5g} N s/m" if best is not None else "")
        )
    if c.get("error"):
        lines.append(f"error       {c['error']}")
    r = c.get("result")
    if r:
        d_min = r.get("d_min")
        kappa = r.get("volume_stiffness")
        lines += [
            f"model       {r.get('stiffness_mode', 'single')}",
            f"stiffness   {stiffness_text(r['stiffness'], unit=' N/m')}"
            + (f"; kappa {kappa:.5g} Pa" if kappa is not None else ""),
            f"d           {r.get('damping', r.get('d')):.5g} N s/m"
            + (f" (smallest that settles: {d_min:.5g})" if d_min is not None else "")
            + (f" at dt {r['dt']:.4g} s" if r.get("dt") else ""),
            f"depth       {r['depth']} layers (full depth {r['full_depth']})",
            f"h           {r['h']:.5g} m",
            f"param set   {c['parameter_set_id']}",
            "",
            *verdict_lines(r.get("verdict")),
            "",
            table(
                [*DISCREPANCY_HEADERS, COMPLIANCE_HEADER],
                discrepancy_rows(r, c.get("load_cases"), compliance=True),
            ),
        ]
        validation = validation_rows(r)
        if validation:
            lines += ["", table(VALIDATION_HEADERS, validation)]
        reference = reference_line(r)
        if reference:
            lines += ["", reference]
        lines += [f"warning     {w}" for w in r.get("warnings", [])]
    return "\n".join(lines)


def geometry_text(geometry: dict[str, Any]) -> str:
    """The solid a set was fitted on: 'box 0.1x0.1x0.1 m, 1000 nodes, full' (a k fitted on
    one mesh is wrong on another, so sets of different meshes must not look alike)."""
    kind = geometry["type"]
    if geometry.get("size"):
        kind += " " + "x".join(f"{s:.3g}" for s in geometry["size"]) + " m"
    parts = [kind, f"{geometry['nodes']} nodes"]
    if geometry.get("connectivity"):
        parts.append(geometry["connectivity"])
    return ", ".join(parts)


def parameter_set_rows(sets: list[dict[str, Any]]) -> list[list[Any]]:
    """One row per parameter set for :data:`PARAMETER_SET_HEADERS`."""
    return [
        [
            p["id"],
            p["name"],
            # a transversely isotropic set: its in-plane constants
            p["material"].get("youngs_modulus", p["material"].get("youngs_modulus_transverse")),
            p["material"].get("poisson_ratio", p["material"].get("poisson_ratio_transverse")),
            geometry_text(p["geometry"]),
            p["geometry"]["h"],
            stiffness_text(p["stiffness"], p.get("stiffness_mode")),
            p.get("damping", p.get("d")),
            p["depth"],
            mean(p["relative_discrepancy"]),
            mean(p["loaded_discrepancy"]),
            mean(p["discrepancy_h"]),
        ]
        for p in sets
    ]


PARAMETER_SET_HEADERS = [
    "id",
    "name",
    "E Pa",
    "nu",
    "geometry",
    "h m",
    "stiffness N/m",
    "d N s/m",
    "depth",
    "relative %",
    "loaded %",
    "% of h",
]
"""The parameter-set table; the discrepancies are means over the load cases."""


def run(client: Client, args: argparse.Namespace) -> Any:
    """Do the command; returns the JSON answer and prints the readable form unless --json."""
    answer: Any
    if args.command == "submit":
        answer = client.calibrate(args.spec, wait=args.wait)
        text = show_calibration(answer)
    elif args.command == "status":
        answer = client.get(args.id)
        text = show_calibration(answer)
    elif args.command == "cancel":
        answer = client.cancel(args.id)
        text = show_calibration(answer)
    elif args.command == "list":
        answer = client.calibrations(status=args.status, limit=args.limit)
        rows = [[i["id"], i["name"], i["status"], i["parameter_set_id"]] for i in answer["items"]]
        text = table(["id", "name", "status", "parameter set"], rows)
        text += f"\n({len(rows)} of {answer['total']})"
    elif args.command == "params":
        filters = {k: getattr(args, k) for k in ("youngs_modulus", "poisson_ratio", "density")}
        answer = client.parameter_sets(**filters, connectivity=args.connectivity, name=args.name)
        text = table(PARAMETER_SET_HEADERS, parameter_set_rows(answer))
        text += "\n(discrepancies: means over the load cases; relative % is the headline)"
    else:
        answer = client.health()
        text = "\n".join(f"{k:<12}{v}" for k, v in answer.items())
    print(json.dumps(answer, indent=2) if args.json else text)
    return answer


def main(argv: list[str] | None = None) -> int:
    """Run ``fpm-client``. Exit status: 0 done; 1 the service refused the request (each field
    error on a line); 2 the service cannot be reached, or ``submit --wait`` ended in a failed
    or canceled calibration (its error on stderr)."""
    args = parse_args(argv)
    with Client(args.url, api_key=args.api_key) as client:
        try:
            answer = run(client, args)
            if args.command == "submit" and args.wait and answer["status"] in UNSUCCESSFUL:
                reason = answer.get("error") or "no reason recorded"
                print(f"error: calibration {answer['id']} {answer['status']}: {reason}",
                      file=sys.stderr)  # fmt: skip
                return 2
        except ApiError as e:
            print(f"error: {e}", file=sys.stderr)
            for err in e.errors:
                print(f"  {err['field']}: {err['message']}", file=sys.stderr)
            return 1
        except httpx.HTTPError as e:
            print(f"error: cannot reach {args.url}: {e}", file=sys.stderr)
            return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
