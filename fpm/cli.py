"""`fpmcal`: the numerical core from the command line (simulate, fem, calibrate, up)."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

from pydantic import ValidationError


def _load(path: str) -> Any:
    from .problem import load_problem

    return load_problem(Path(path))


def _emit(data: dict[str, Any], out: str | None) -> None:
    text = json.dumps(data)
    if out:
        Path(out).write_text(text)
        print(f"wrote {out}", file=sys.stderr)
    else:
        print(text)


def cmd_simulate(args: argparse.Namespace) -> None:
    from .simulation import simulate

    result = simulate(
        _load(args.spec),
        k=args.k,
        d=args.d,
        depth=args.depth,
        load_case=args.load_case,
        dt=args.dt,
        max_steps=args.max_steps,
    )
    _emit(result.to_dict(), args.output)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="fpmcal", description=__doc__)
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("simulate", help="run the FPM for one load case, print JSON")
    p.add_argument("spec", help="problem spec JSON file")
    p.add_argument("--k", type=float, required=True, help="spring stiffness, N/m")
    p.add_argument("--d", type=float, required=True, help="nodal damping, N s/m")
    p.add_argument("--depth", type=int, default=None, help="penetration depth (layers)")
    p.add_argument("--load-case", type=int, default=0)
    p.add_argument("--dt", type=float, default=None, help="time step, s")
    p.add_argument("--max-steps", type=int, default=None)
    p.add_argument("-o", "--output", default=None, help="write JSON here instead of stdout")
    p.set_defaults(func=cmd_simulate)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        args.func(args)
    except ValidationError as e:
        print(f"invalid spec {getattr(args, 'spec', '')}:", file=sys.stderr)
        for err in e.errors():
            loc = ".".join(str(p) for p in err["loc"])
            print(f"  {loc}: {err['msg']}", file=sys.stderr)
        return 2
    except (ValueError, FileNotFoundError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
