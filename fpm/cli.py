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


def cmd_fem(args: argparse.Namespace) -> None:
    from .fem import solve_fem

    _emit(solve_fem(_load(args.spec)).to_dict(), args.output)


class _Bar:
    """A one-line progress bar on stderr for in-process calibration (chains share the bar)."""

    def __init__(self, chains: int, moves: int):
        self.done = [0] * chains
        self.total = chains * moves
        self.tty = sys.stderr.isatty()
        self.last_tenth = -1

    def __call__(self, info: dict[str, Any]) -> None:
        if info.get("phase") != "annealing":
            print(f"  {info.get('phase')} ...", file=sys.stderr, flush=True)
            return
        if "best_cost" not in info:  # still drawing the chain's starting point
            return
        self.done[info["chain"]] = info["move"]
        frac = sum(self.done) / self.total
        if not self.tty and int(frac * 10) == self.last_tenth:
            return
        self.last_tenth = int(frac * 10)
        bar = "#" * round(30 * frac)
        line = f"  annealing [{bar:<30}] {frac:4.0%}  T={info['temperature']:.2e}"
        line += f"  best cost {info['best_cost']:.4f}"
        print(("\r" if self.tty else "") + line, end="" if self.tty else "\n", file=sys.stderr)
        if self.tty and frac >= 1:
            print(file=sys.stderr)


def cmd_calibrate(args: argparse.Namespace) -> None:
    from .calibration import calibrate
    from .fem import solve_fem

    problem = _load(args.spec)
    a = problem.spec.annealing
    chains = args.chains or a.chains
    print(f"{problem.spec.name}: {problem.n_nodes} nodes, h = {problem.h:.4g} m", file=sys.stderr)
    reference = solve_fem(problem)
    progress = None if args.quiet else _Bar(chains, a.moves)
    result = calibrate(problem, chains=chains, progress=progress, reference=reference)
    if args.json:
        print(json.dumps(result.to_dict()))
    else:
        print(result_table(problem, result))
    if args.plot:
        from .plot import plot_calibration

        plot_calibration(problem, reference.displacements, result, args.plot)
        print(f"wrote {args.plot}", file=sys.stderr)


def result_table(problem: Any, result: Any) -> str:
    """The calibration result as a readable table."""
    lines = [
        f"k      {result.k:12.5g} N/m",
        f"d      {result.d:12.5g} N s/m",
        f"depth  {result.depth:12d} layers",
        f"cost   {result.cost:12.5g} m (Eq. 2)",
        "",
        f"{'load case':<16}{'discrepancy % of h':>20}{'settle steps':>14}",
    ]
    for case, disc, steps in zip(
        problem.load_cases, result.discrepancy, result.settle_steps, strict=True
    ):
        lines.append(f"{case.name:<16}{disc:>20.3f}{steps:>14d}")
    lines.append(f"{'mean':<16}{result.mean_discrepancy:>20.3f}")
    lines.append("")
    lines.append(
        f"settled: {'yes' if result.settled else 'NO'}; {result.evaluations} cost evaluations "
        f"in {result.seconds:.1f} s"
    )
    return "\n".join(lines)


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

    p = sub.add_parser("fem", help="solve the FEM reference, write JSON")
    p.add_argument("spec", help="problem spec JSON file")
    p.add_argument("-o", "--output", default=None, help="write JSON here instead of stdout")
    p.set_defaults(func=cmd_fem)

    p = sub.add_parser("calibrate", help="fit k, d, depth in-process (progress on stderr)")
    p.add_argument("spec", help="problem spec JSON file")
    p.add_argument("--chains", type=int, default=None, help="annealing chains (default: spec)")
    p.add_argument("--plot", default=None, metavar="OUT.png", help="save profiles + cost history")
    p.add_argument("--json", action="store_true", help="print the result as JSON")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=cmd_calibrate)

    # `up` hands its arguments to service.stack (see main); listed here for --help.
    sub.add_parser("up", help="run the local stack: Redis, API, workers (Ctrl-C stops)")
    return parser


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if argv[:1] == ["up"]:
        from service.stack import main as stack_main

        stack_main(argv[1:])
        return 0
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
