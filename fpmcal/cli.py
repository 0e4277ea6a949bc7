"""`fpmcal`: the numerical core from the command line (simulate, fem, calibrate, spec from-mesh,
export, up).

Errors are one line each on stderr, never a traceback (see :func:`main` for exit statuses);
notes on the spec (e.g. which node a ``nearest`` selector took) and warnings (e.g. a reference
outside small strain) go to stderr too, so stdout holds only the result.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from functools import partial
from pathlib import Path
from typing import TYPE_CHECKING, Any, get_args

from pydantic import ValidationError

if TYPE_CHECKING:
    from fpm.fitting.result import CalibrationResult

MAX_FIELD_ERRORS = 20
"""Field errors printed for a bad spec (the rest are counted)."""


class SpecFileError(Exception):
    """The SPEC argument is not a readable JSON file (exit status 2)."""


class ServiceError(RuntimeError):
    """The service did not answer what was asked (exit status 1)."""


def _read_spec(path: str) -> Any:
    """The parsed JSON of the spec file ``path``; :class:`SpecFileError` if there is none."""
    not_json = f"SPEC must be a JSON problem spec (got {path}, not JSON: "
    try:
        text = Path(path).read_text(encoding="utf-8")
    except FileNotFoundError:
        raise SpecFileError(
            f"SPEC {path}: no such file (give the path of a JSON problem spec, e.g. "
            "examples/small-box.json)"
        ) from None
    except IsADirectoryError:
        raise SpecFileError(f"SPEC {path} is a directory: give a JSON problem spec file") from None
    except UnicodeDecodeError:
        raise SpecFileError(not_json + "not UTF-8 text)" + _mesh_hint(path)) from None
    except OSError as e:
        raise SpecFileError(f"cannot read SPEC {path}: {e.strerror}") from None
    try:
        return json.loads(text)
    except json.JSONDecodeError as e:
        raise SpecFileError(not_json + f"{e})" + _mesh_hint(path)) from None


def _mesh_hint(path: str) -> str:
    """For a mesh file given as SPEC: how to make a spec of it."""
    from fpm.io.meshes import mesh_suffix

    if mesh_suffix(path) is None:
        return ""
    return (
        f"; {path} looks like a mesh: make a spec of it first with fpmcal spec from-mesh "
        f"{path} --spacing H --fix face:z- --force 'nearest:X,Y,Z:FX,FY,FZ' --E PA --nu NU"
    )


def _load(path: str, reference: str | None = None) -> Any:
    """The problem of the spec file ``path``; its notes go to stderr. ``reference``: a file
    whose displacement field becomes the spec's ``reference.displacements``
    (:func:`fpm.io.meshes.read_reference`). The service's size limits apply before it is built
    (:func:`fpm.limits.check_size`, then the memory a calibration of it needs:
    :func:`worker.memory.check`)."""
    from fpm.limits import check_size
    from fpm.model.problem import load_problem
    from fpm.model.spec import ProblemSpec
    from worker import memory

    spec = _read_spec(path)
    if reference is not None:
        from fpm.io.meshes import read_reference

        try:
            field = read_reference(reference, len(spec.get("load_cases") or []))
        except (OSError, ValueError) as e:
            raise SpecFileError(f"--reference {reference}: {e}") from None
        spec["reference"] = {**(spec.get("reference") or {}), "displacements": field}
    spec = ProblemSpec.model_validate(spec)
    memory.check(check_size(spec), machine=True)
    problem = load_problem(spec)
    for note in problem.notes:
        print(f"note: {note}", file=sys.stderr)
    return problem


def _warn(messages: list[str]) -> None:
    for message in messages:
        print(f"warning: {_one_line(message)}", file=sys.stderr)


def _one_line(message: object) -> str:
    return " ".join(str(message).split())


def _emit(data: dict[str, Any], out: str | None) -> None:
    text = json.dumps(data)
    if out:
        Path(out).write_text(text)
        print(f"wrote {out}", file=sys.stderr)
    else:
        print(text)


def cmd_simulate(args: argparse.Namespace) -> None:
    from fpm.dynamics.simulation import simulate
    from fpm.dynamics.stability import auto_time_step, stable_time_step
    from fpm.model.stiffness import model_stiffness

    problem = _load(args.spec)
    k = args.k[0] if len(args.k) == 1 else args.k
    stiffness = model_stiffness(problem, k)
    dt = args.dt if args.dt is not None else problem.spec.fpm.dt
    dt = auto_time_step(problem, stiffness) if dt == "auto" else float(dt)
    limit = stable_time_step(problem, stiffness)
    given = " ".join(f"{v:g}" for v in args.k)
    advice = f"the lattice's stability estimate for k = {given} is dt <= {limit:.3g} s"
    if dt > limit:
        _warn([f"dt = {dt:.3g} s: {advice}; the run may diverge (lower --dt)"])
    result = simulate(
        problem,
        k=k,
        d=args.d,
        depth=args.depth,
        load_case=args.load_case,
        dt=dt,
        max_steps=args.max_steps,
    )
    if result.diverged:
        _warn(
            [
                result.message
                + f" (dt = {dt:.3g} s: {advice}, and the node-by-node step needs some damping: "
                "lower --dt or raise --d)"
            ]
        )
    _emit(result.to_dict(), args.output)


def cmd_equilibrium(args: argparse.Namespace) -> None:
    from dataclasses import asdict

    from fpm.dynamics.equilibrium import static_equilibrium

    k = args.k[0] if len(args.k) == 1 else args.k
    result = static_equilibrium(
        _load(args.spec), k=k, depth=args.depth, load_case=args.load_case
    ).check()
    data = asdict(result)
    data["displacements"] = result.displacements.tolist()
    _emit(data, args.output)


def cmd_fem(args: argparse.Namespace) -> None:
    from fpm.fem.reference import solve_fem
    from fpm.fitting.damping.validation import resolution_notes
    from fpm.fitting.diagnosis import UnitsError, check_reference

    problem = _load(args.spec)
    result = solve_fem(problem, progress=_fem_levels)
    if result.element == "tet10":
        mesh = problem.spec.reference.mesh
        size = f" ({len(mesh.tetrahedra)} tetrahedra)" if mesh is not None else ""
        print(
            f"{problem.spec.name}: the reference solved on reference.mesh{size} with 10-node "
            f"tetrahedra, read at the {problem.n_nodes} lattice nodes (what the fit compares)",
            file=sys.stderr,
        )
    try:
        _warn(check_reference(problem, result.displacements))
    except UnitsError as e:
        _warn([str(e)])
    if result.estimated_error is not None:
        names = [case.name for case in problem.all_cases]
        print(
            f"{problem.spec.name}: the reference's estimated error per case, % ("
            + (
                f"change from its last refinement, {result.refinements} in all"
                if result.refinements
                else "its change under one refinement with the forces spread"
            )
            + "): "
            + ", ".join(f"{n} {e:.2f}" for n, e in zip(names, result.estimated_error, strict=True)),
            file=sys.stderr,
        )
    _warn(resolution_notes(problem, result))
    _emit(result.to_dict(), args.output)


class _Bar:
    """A one-line progress bar on stderr for in-process calibration (chains share the bar; its
    best cost is the best so far over all of them, so a chain starting later never raises it)."""

    def __init__(self, chains: int, moves: int):
        self.done = [0] * chains
        self.best = float("inf")
        self.total = chains * moves
        self.tty = sys.stderr.isatty()
        self.last_tenth = -1
        self.phase: Any = None

    def __call__(self, info: dict[str, Any]) -> None:
        if info.get("phase") != "annealing":
            if info.get("phase") != self.phase:  # once per phase, not per report
                print(f"  {info.get('phase')} ...", file=sys.stderr, flush=True)
            self.phase = info.get("phase")
            if info.get("phase") == "damping" and "d" in info:  # a line per d tried
                total = info.get("total_steps")
                steps = "not settled (or slower)" if total is None else f"{total:,} steps"
                print(f"    d = {info['d']:.4g} N s/m: {steps}", file=sys.stderr, flush=True)
            return
        if "best_cost" not in info:  # still drawing the chain's starting point
            return
        self.done[info["chain"]] = info["move"]
        self.best = min(self.best, info["best_cost"])
        frac = sum(self.done) / self.total
        if not self.tty and int(frac * 10) == self.last_tenth:
            return
        self.last_tenth = int(frac * 10)
        bar = "#" * round(30 * frac)
        line = f"  annealing [{bar:<30}] {frac:4.0%}  T={info['temperature']:.2e}"
        line += f"  best cost {self.best:.4f}"
        print(("\r" if self.tty else "") + line, end="" if self.tty else "\n", file=sys.stderr)
        if self.tty and frac >= 1:
            print(file=sys.stderr)


def _fem_levels(info: dict[str, Any]) -> None:
    """A line on stderr per level of a refined FEM reference as it starts (it can take
    minutes on an organ)."""
    change = info.get("last_change")
    after = f" (the last two levels differ by {change:.2g}%)" if change is not None else ""
    print(
        f"FEM reference: refinement level {info['level']}, {info['fem_nodes']:,} FEM nodes{after}",
        file=sys.stderr,
    )


def cmd_calibrate(args: argparse.Namespace) -> None:
    from fpm.fem.reference import reference_for
    from fpm.fitting.calibration import calibrate
    from fpm.fitting.diagnosis import check_reference

    from . import cache as stored

    problem = _load(args.spec, args.reference)
    a = problem.spec.annealing
    chains = args.chains or a.chains
    print(f"{problem.spec.name}: {problem.n_nodes} nodes, h = {problem.h:.4g} m", file=sys.stderr)
    # the supplied field, if any: then no FEM; else the stored one beside the spec
    cache = None if args.no_cache else stored.Cache(stored.cache_dir(args.spec))
    levels = None if args.quiet else _fem_levels
    say = partial(print, file=sys.stderr)
    solve = partial(reference_for, problem, progress=levels)
    reference = stored.reference(cache, problem, solve, say)
    warned = check_reference(problem, reference.displacements)  # a UnitsError stops here
    _warn(warned)
    progress = None if args.quiet else _Bar(chains, a.moves)
    done, keep = stored.chains(cache, problem, reference, chains, say)
    result = calibrate(
        problem, chains=chains, progress=progress, reference=reference, stored_chains=done,
        keep_chains=keep,
    )  # fmt: skip
    _warn([w for w in result.warnings if w not in warned])
    if args.json:  # the table still for the person watching: on stderr
        print(result_table(problem, result), file=sys.stderr)
        print(json.dumps(result.to_dict()))
    else:
        print(result_table(problem, result))
    if args.plot:
        from fpm.io.plot import plot_calibration

        plot_calibration(problem, reference.displacements, result, args.plot)
        print(f"wrote {args.plot}", file=sys.stderr)


def cmd_spec_from_mesh(args: argparse.Namespace) -> None:
    from fpm.io.meshes import spec_from_mesh
    from fpm.limits import Limits, node_count
    from fpm.model.spec import ProblemSpec

    limits = Limits.from_environ()  # the service's: a spec it would refuse is not made
    if args.nodes is not None:
        limits.check_nodes(args.nodes, "--nodes")
    dt: float | str = args.dt if args.dt == "auto" else _positive(args.dt, "--dt")
    spec, notes = spec_from_mesh(
        args.spec,
        fix=args.fix,
        forces=args.force,
        youngs_modulus=args.E,
        poisson_ratio=args.nu,
        density=args.density,
        spacing=args.spacing,
        nodes=args.nodes,
        connectivity=args.connectivity,
        scale=args.scale,
        voxelise=args.voxelise,
        name=args.name,
        dt=dt,
        voxel_reference=args.voxel_reference,
        conform=args.conform,
        lattice=args.lattice,
        stiffness=args.stiffness,
        loads=args.loads,
        validation=args.validate,
    )
    nodes = node_count(ProblemSpec.model_validate(spec))
    limits.check_nodes(nodes, "--nodes" if args.nodes is not None else "--spacing")
    for note in notes:
        print(f"note: {note}", file=sys.stderr)
    _emit(spec, args.output)


def _positive(text: str, flag: str) -> float:
    try:
        value = float(text)
    except ValueError:
        value = float("nan")
    if not value > 0 or value == float("inf"):
        raise ValueError(f"{flag} must be a number > 0 or 'auto' (got {text!r})")
    return value


def _store_redis() -> Any:
    import os

    from redis import Redis

    url = os.environ.get("FPM_REDIS_URL") or os.environ.get("REDIS_URL")
    return Redis.from_url(url or "redis://localhost:6379/0", socket_timeout=10)


def cmd_store(args: argparse.Namespace) -> None:
    from redis.exceptions import RedisError

    from store.backup import DumpError, dump, restore

    try:
        redis = _store_redis()
        if args.store_command == "dump":
            count = 0
            with open(args.output, "w", encoding="utf-8") as out:
                for line in dump(redis):
                    out.write(line + "\n")
                    count += 1
            print(f"wrote {args.output}: {count - 1} records", file=sys.stderr)
            return
        try:
            with open(args.file, encoding="utf-8") as lines:
                written = restore(redis, (line.rstrip("\n") for line in lines))
        except OSError as e:
            raise SpecFileError(f"{args.file}: {_one_line(e)}") from None
        except DumpError as e:
            raise ValueError(f"{args.file}: {e}") from None
        summary = ", ".join(f"{n} {kind.replace('_', ' ')}s" for kind, n in written.items())
        print(
            f"restored from {args.file}: {summary} (records already stored kept)", file=sys.stderr
        )
    except RedisError as e:
        raise ServiceError(f"Redis: {_one_line(e)}") from None


def cmd_export(args: argparse.Namespace) -> None:
    if args.parameter_set:
        if args.spec or args.params:
            raise ValueError("give SPEC and PARAMS, or --parameter-set ID, not both")
        import httpx

        from client.sdk import ApiError, Client

        fmt = "json" if args.format == "binary" else args.format  # binary: packed here
        try:
            with Client(args.url, api_key=args.api_key) as client:
                body = client.export_bytes(args.parameter_set, fmt, timeout=args.timeout or None)
        except (ApiError, httpx.HTTPError, TimeoutError) as e:
            raise ServiceError(f"the service at {args.url}: {_one_line(e)}") from None
    else:
        if not (args.spec and args.params):
            raise ValueError(
                "give the spec and the parameters fitted on it (SPEC PARAMS: a result of "
                "fpmcal calibrate --json, or a parameter set), or --parameter-set ID"
            )
        from fpm.io.export import export, export_warnings

        if args.output and any(
            Path(args.output).resolve() == Path(f).resolve() for f in (args.spec, args.params)
        ):
            raise ValueError(f"-o {args.output} would overwrite an input: write elsewhere")
        problem = _load(args.spec)
        params = _read_json(args.params, "PARAMS")
        if isinstance(params.get("result"), dict):  # a calibration as the service shows it
            params = params["result"]
        fem = None
        if args.format == "vtu":  # the FEM reference as calibrate stored it beside the spec
            from fpm.fem.reference import reference_for

            from . import cache as stored

            where = stored.Cache(stored.cache_dir(args.spec))
            solve = partial(reference_for, problem, progress=_fem_levels)
            say = partial(print, file=sys.stderr)
            fem = stored.reference(where, problem, solve, say).displacements
        fmt = "json" if args.format == "binary" else args.format
        body = export(problem, params, fmt, fem=fem)
        _warn(export_warnings(problem, args.format))
    if args.format == "binary":
        from fpm.io.export_binary import from_json

        body = from_json(json.loads(body))
        if not args.output and sys.stdout.isatty():
            raise ValueError("--format binary: give -o FILE (or redirect stdout to a file)")
    if args.output:
        Path(args.output).write_bytes(body)
        print(f"wrote {args.output}", file=sys.stderr)
    elif args.format == "binary":
        sys.stdout.buffer.write(body)
        sys.stdout.flush()
    else:
        sys.stdout.write(body.decode())
        sys.stdout.flush()


def _read_json(path: str, what: str) -> Any:
    try:
        data = json.loads(Path(path).read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise SpecFileError(f"{what} {path}: not a readable JSON file ({_one_line(e)})") from None
    if not isinstance(data, dict):
        raise SpecFileError(f"{what} {path}: expected a JSON object")
    return data


def result_table(problem: Any, result: CalibrationResult) -> str:
    """The calibration result as a readable table: the verdict first, the parameters, then per
    case the relative discrepancy beside % of h and the load compliance ratio."""
    from client.table import verdict_lines

    fitted, fit, settle = result.parameters, result.fit, result.settle
    stiffness = fitted.stiffness
    verdict = fit.verdict
    lines = verdict_lines(None if verdict is None else verdict.model_dump())
    lines += [""] if lines else []
    lines.append(f"model  {fitted.stiffness_mode:>12}")
    regions = fitted.regions
    if isinstance(stiffness, dict) and ("axial_scale" in stiffness or regions):
        # material regions, transversely isotropic: the base's families here, the rest below
        lines += [
            f"k {name:<5}{value:12.5g} N/m" for name, value in stiffness.items() if "[" not in name
        ]
        lines = [line.replace(" N/m", "") if "axial_scale" in line else line for line in lines]
        for r in [r for r in regions or [] if r["name"] != "base"]:
            ks = ", ".join(f"{n} {v:.5g}" for n, v in r["stiffness"].items())
            lines.append(
                f"region {r['name']} ({r['cells']} cells, E {r['youngs_modulus']:.4g} Pa): k "
                f"{ks} N/m, kappa {r['volume_stiffness']:.5g} Pa"
            )
    elif isinstance(stiffness, dict) and len(set(stiffness.values())) > 1:
        lines += [f"k {name:<5}{value:12.5g} N/m" for name, value in stiffness.items()]
    else:
        lines += [f"k      {fitted.k:12.5g} N/m"]
    kappa = fitted.volume_stiffness
    if kappa is not None:
        whose = "of the base's cells" if regions else "of every cell"
        lines.append(f"kappa  {kappa:12.5g} Pa (volume stiffness {whose})")
    lines.append(f"d      {fitted.d:12.5g} N s/m")
    dt = settle.dt
    if dt is not None:
        lines.append(f"dt     {dt:12.5g} s (d and the settle steps belong to it)")
    d_min = settle.d_min
    if d_min is not None:
        lines.append(f"d_min  {d_min:12.5g} N s/m (smallest d that settles)")
    lines += [f"depth  {fitted.depth:12d} layers", f"cost   {fit.cost:12.5g} m (Eq. 2)", ""]
    relative = list(fit.relative_discrepancy)
    h_percent = fit.discrepancy_h
    ratios = list(fit.compliance_ratio or [None] * len(problem.load_cases))
    lines.append(
        f"{'load case':<16}{'relative discrepancy %':>24}{'% of h':>10}{'settle steps':>14}"
        f"{'compliance':>12}"
    )
    for case, rel, disc, steps, ratio in zip(
        problem.load_cases, relative, h_percent, settle.steps, ratios, strict=True
    ):
        lines.append(f"{case.name:<16}{rel:>24.3f}{disc:>10.3f}{steps:>14d}{_ratio(ratio):>12}")
    lines.append(f"{'mean':<16}{_mean(relative):>24.3f}{_mean(h_percent):>10.3f}")
    validation = list(fit.validation_relative_discrepancy)
    if validation:
        lines += [
            "",
            f"{'validation case':<16}{'relative discrepancy %':>24}{'% of h':>10}{'':>14}"
            f"{'compliance':>12}",
        ]
        names = fit.validation_cases or [""] * len(validation)
        unseen = list(fit.validation_compliance_ratio or [None] * len(names))
        for name, rel, disc, ratio in zip(
            names, validation, fit.validation_discrepancy_h, unseen, strict=True
        ):
            lines.append(f"{name:<16}{rel:>24.3f}{disc:>10.3f}{'':>14}{_ratio(ratio):>12}")
        lines.append(
            f"{'mean':<16}{_mean(validation):>24.3f}{_mean(fit.validation_discrepancy_h):>10.3f}"
            "  (never fitted: the honest figure)"
        )
    lines += _field_lines(fitted.field)
    error = result.reference.error
    if error is not None:
        every = list(error) + list(result.reference.validation_error or [])
        refined = result.reference.refinements or 0
        lines += [
            "",
            "reference's estimated error %: "
            + " / ".join(f"{e:.2f}" for e in every)
            + (f" (change from its last refinement, {refined} in all" if refined else " (check")
            + ("; ABOVE 5%: not resolved)" if max(every) > 5 else ")"),
        ]
    total = sum(result.run.seconds.values())
    lines.append("")
    lines.append(
        f"settled: {'yes' if settle.settled else 'NO'}; {result.run.evaluations} cost evaluations "
        f"in {total:.1f} s"
    )
    return "\n".join(lines)


def _field_lines(field: Any) -> list[str]:
    """fpm.stiffness 'field': the four parameters and the field side by side (fitted, never
    fitted, left out) and the smoothness weights tried."""
    if field is None:
        return []

    def figures(values: list[float]) -> str:
        return " / ".join(f"{v:.2f}" for v in values) or "-"

    lines = ["", f"{'model, relative %':<18}{'fit':>24}{'validation':>22}{'left out':>10}"]
    for name, m, returned in (
        ("four parameters", field.four_parameter, not field.returned),
        ("field", field.field, field.returned),
    ):
        lines.append(
            f"{name + (' *' if returned else ''):<18}{figures(m.relative_discrepancy):>24}"
            f"{figures(m.validation_relative_discrepancy):>22}{m.cv_error:>10.2f}"
        )
    tried = ", ".join(
        f"{w:g}: {e:.2f}%" for w, e in zip(field.cv_weights, field.cv_error, strict=True)
    )
    lines.append(f"(* returned) smoothness weight {field.smoothness_weight:g}; left out: {tried}")
    return lines


def _ratio(value: float | None) -> str:
    """A load compliance ratio to 3 decimals, '-' where there is none."""
    return "-" if value is None else f"{value:.3f}"


def _mean(values: Any) -> float:
    values = [float(v) for v in values]
    return sum(values) / len(values) if values else float("nan")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="fpmcal", description=(__doc__ or "").split("\n\n")[0])
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("simulate", help="run the FPM for one load case, print JSON")
    p.add_argument("spec", help="problem spec JSON file")
    p.add_argument(
        "--k", type=float, nargs="+", required=True,
        help="the stiffness parameters: one k (N/m), one per family (axis face body), or for "
        "families+volume the families then kappa (Pa)",
    )  # fmt: skip
    p.add_argument("--d", type=float, required=True, help="nodal damping, N s/m")
    p.add_argument("--depth", type=int, default=None, help="penetration depth (layers)")
    p.add_argument("--load-case", type=int, default=0)
    p.add_argument("--dt", type=float, default=None, help="time step, s")
    p.add_argument("--max-steps", type=int, default=None)
    p.add_argument("-o", "--output", default=None, help="write JSON here instead of stdout")
    p.set_defaults(func=cmd_simulate)

    p = sub.add_parser(
        "equilibrium", help="the settled FPM state of one load case, solved directly (JSON)"
    )
    p.add_argument("spec", help="problem spec JSON file")
    p.add_argument(
        "--k", type=float, nargs="+", required=True,
        help="spring stiffness, N/m: one value, or one per family (axis face body)",
    )  # fmt: skip
    p.add_argument("--depth", type=int, default=None, help="penetration depth (layers)")
    p.add_argument("--load-case", type=int, default=0)
    p.add_argument("-o", "--output", default=None, help="write JSON here instead of stdout")
    p.set_defaults(func=cmd_equilibrium)

    p = sub.add_parser("fem", help="solve the FEM reference, write JSON")
    p.add_argument("spec", help="problem spec JSON file")
    p.add_argument("-o", "--output", default=None, help="write JSON here instead of stdout")
    p.set_defaults(func=cmd_fem)

    p = sub.add_parser("calibrate", help="fit k, d, depth in-process (progress on stderr)")
    p.add_argument("spec", help="problem spec JSON file")
    p.add_argument("--chains", type=int, default=None, help="annealing chains (default: spec)")
    p.add_argument("--plot", default=None, metavar="OUT.png", help="save profiles + cost history")
    p.add_argument(
        "--json", action="store_true", help="print the result as JSON (the table goes to stderr)"
    )
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    p.add_argument(
        "--no-cache",
        action="store_true",
        help="neither reuse nor keep the FEM reference and stage 1's chains in SPEC.fpmcache/ "
        "beside the spec (kept by default before the next stage starts, reused when they are "
        "still valid: a rerun after a failure or with another damping setting, or a press "
        "scaled by a factor, starts from them)",
    )
    p.add_argument(
        "--reference",
        default=None,
        metavar="FILE",
        help="fit to this displacement field instead of the FEM (JSON: a list per load case of "
        "[ux, uy, uz] per node, m; VTU: point data displacement_1..L); sets the spec's "
        "reference.displacements",
    )
    p.set_defaults(func=cmd_calibrate)

    from fpm.io.meshes import FORCE_HELP, SELECTOR_HELP
    from fpm.model.spec.base import StiffnessMode

    p = sub.add_parser("spec", help="make a problem spec (spec from-mesh FILE ...)")
    spec_sub = p.add_subparsers(dest="spec_command", required=True)
    p = spec_sub.add_parser(
        "from-mesh",
        help="a spec JSON from a mesh file (Gmsh .msh, VTK .vtu/.vtk, Abaqus .inp, STL, ...)",
        description="Hexahedral meshes are used as they are; tetrahedral meshes and closed "
        "triangle surfaces are voxelised at --spacing, or at the spacing that gives about --nodes "
        "nodes (a cell is solid when its centre lies "
        "inside), and for tetrahedra the lattice's surface then follows the mesh's (--lattice). "
        "A tetrahedral mesh is also kept in the spec (reference.mesh): the FEM "
        "reference is solved on it with 10-node tetrahedra and read at the lattice nodes "
        "(--voxel-reference: on the voxels instead). Lengths in m (see --scale), forces in N, "
        "E in Pa.",
    )
    p.add_argument("spec", metavar="MESH", help="mesh file")
    p.add_argument("--spacing", type=float, default=None, help="lattice spacing h, m")
    p.add_argument(
        "--nodes",
        type=int,
        default=None,
        help="instead of --spacing: about how many lattice nodes (a real-time budget); the "
        "spacing is chosen for it and printed in a note",
    )
    p.add_argument(
        "--fix", action="append", default=[], metavar="SELECTOR",
        help=f"fixed nodes (repeatable): {SELECTOR_HELP}",
    )  # fmt: skip
    p.add_argument(
        "--force", action="append", default=[], metavar="FORCE",
        help=f"one load case (repeatable): {FORCE_HELP}",
    )  # fmt: skip
    p.add_argument(
        "--validate", action="append", default=[], metavar="FORCE",
        help="one validation case (repeatable), in --force's form: a load the fit never sees, "
        "reported beside the fit at the fitted parameters (the figure to quote)",
    )  # fmt: skip
    p.add_argument("--E", type=float, required=True, help="Young's modulus, Pa (5 kPa = 5000)")
    p.add_argument("--nu", type=float, required=True, help="Poisson's ratio")
    p.add_argument("--density", type=float, default=1000.0, help="kg/m^3 (default 1000)")
    p.add_argument("--connectivity", choices=["axis", "axis+face", "full"], default="full")
    p.add_argument("--scale", type=float, default=1.0, help="coordinate factor (0.001: mm)")
    p.add_argument("--voxelise", action="store_true", help="voxelise a hexahedral mesh too")
    p.add_argument(
        "--voxel-reference", action="store_true",
        help="tetrahedral meshes: solve the FEM reference on the voxel lattice (hexahedra) "
        "instead of on the tetrahedra, and leave the mesh out of the spec",
    )  # fmt: skip
    p.add_argument(
        "--lattice", choices=["conforming", "voxels"], default=None,
        help="tetrahedral meshes: 'conforming' (the default) moves the voxel lattice's surface "
        "nodes onto the mesh's surface (a hexahedral mesh geometry that is the mesh's solid, not "
        "its staircase; face selectors become the boxes of the nodes within h/2 of the face); "
        "'voxels' keeps the voxels (the default of --voxel-reference)",
    )  # fmt: skip
    p.add_argument(
        "--conform", action="store_true", help="the same as --lattice conforming (the default)"
    )  # fmt: skip
    p.add_argument(
        "--stiffness", choices=list(get_args(StiffnessMode)), default=None,
        help="fpm.stiffness; default: 'field' (a stiffness factor per cell, returned only where "
        "it predicts a left-out load better) for a tetrahedral organ loaded in two force "
        "patterns or more, else the schema's default (families+volume)",
    )  # fmt: skip
    p.add_argument(
        "--loads", choices=["node", "hat"], default=None,
        help="fpm.loads; default: 'hat' (a force acts over its node's share of the surface, as "
        "the reference applies it) where the reference is the mesh's tetrahedra, else 'node'",
    )  # fmt: skip
    p.add_argument("--name", default=None, help="the spec's name (default: the file name)")
    p.add_argument(
        "--dt", default="auto",
        help="FPM time step, s, or 'auto' (half the lattice's stability estimate at "
        "k = 1.05 E h, at most 1 ms)",
    )  # fmt: skip
    p.add_argument("-o", "--output", default=None, help="write the spec here instead of stdout")
    p.set_defaults(func=cmd_spec_from_mesh)

    p = sub.add_parser(
        "export",
        help="a fitted parameter set with its lattice: json, vtu (ParaView), sofa (.scn, springs "
        "only), sofa-python (SofaPython3 scene with the volume term) or binary (the JSON's step "
        "data packed for the native step, fpm/native/fpm_step.h)",
        description="From SPEC and PARAMS (the result of fpmcal calibrate --json on SPEC, or a "
        "parameter set of the service), or from the service's stored parameter set "
        "(--parameter-set ID).",
    )
    p.add_argument("spec", nargs="?", help="problem spec JSON file the parameters were fitted on")
    p.add_argument("params", nargs="?", help="calibration result or parameter set (JSON)")
    p.add_argument(
        "--format", choices=["json", "vtu", "sofa", "sofa-python", "binary"], default="json"
    )
    p.add_argument("--parameter-set", default=None, metavar="ID", help="a stored parameter set")
    p.add_argument(
        "--url", default=os.environ.get("FPM_URL", "http://127.0.0.1:8000"),
        help="the service (with --parameter-set; default $FPM_URL or http://127.0.0.1:8000)",
    )  # fmt: skip
    p.add_argument("--api-key", default=os.environ.get("FPM_API_KEY"), help="X-API-Key")
    p.add_argument(
        "--timeout", type=float, default=600.0, metavar="S",
        help="with --parameter-set: seconds to wait while a worker makes the export (the "
        "first request of one; 0 = no limit; default 600)",
    )  # fmt: skip
    p.add_argument("-o", "--output", default=None, help="write here instead of stdout")
    p.set_defaults(func=cmd_export)

    # `up` hands its arguments to stack.local (see main); listed here for --help.
    sub.add_parser("up", help="run the local stack: Redis, API, workers (Ctrl-C stops)")

    p = sub.add_parser(
        "store",
        help="back up or migrate the store: parameter sets, FEM references, finished "
        "calibrations (Redis from FPM_REDIS_URL / REDIS_URL)",
    )
    store_sub = p.add_subparsers(dest="store_command", required=True)
    p = store_sub.add_parser("dump", help="write the store as JSON lines")
    p.add_argument("-o", "--output", required=True, help="the dump file to write")
    p.set_defaults(func=cmd_store)
    p = store_sub.add_parser("restore", help="write a dump's records the store lacks")
    p.add_argument("file", help="a dump written by fpmcal store dump")
    p.set_defaults(func=cmd_store)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Run ``fpmcal``; every error is reported on stderr without a traceback.

    Exit status: 0 done; 2 a bad command line, spec file or spec (each field error on a line
    ``SPEC: field.path: message``) or a spec the FEM cannot solve; 1 a calibration that cannot
    proceed (units, annealing start, damping search) or any other failure; 130 interrupted.
    """
    argv = sys.argv[1:] if argv is None else argv
    if argv[:1] == ["up"]:
        from stack.local import main as stack_main

        stack_main(argv[1:])
        return 0
    args = build_parser().parse_args(argv)
    try:
        args.func(args)
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130
    except Exception as e:
        lines, status = error_report(e, getattr(args, "spec", "SPEC"))
        for line in lines:
            print(line, file=sys.stderr)
        return status
    return 0


def error_report(error: Exception, spec: str) -> tuple[list[str], int]:
    """What ``fpmcal`` prints for ``error`` (one line, or one per field error) and its exit
    status."""
    from fpm.fitting.annealing import AnnealingError
    from fpm.fitting.diagnosis import UnitsError
    from fpm.limits import LimitError
    from worker.memory import MemoryRefused

    if isinstance(error, SpecFileError):
        return [str(error)], 2
    if isinstance(error, LimitError):  # as the service refuses it: the field, or the flag
        where = "error" if error.field.startswith(("-", "FPM_")) else spec
        return [f"{where}: {error.field}: {_one_line(error.message)}"], 2
    if isinstance(error, MemoryRefused):
        return [f"error: {_one_line(error)}"], 1
    if isinstance(error, MemoryError):  # past the estimate: still the reason, not a traceback
        return [
            "error: out of memory: the problem is too large for this machine (fewer lattice "
            "nodes: a coarser spacing, or spec from-mesh --nodes)"
        ], 1
    if isinstance(error, ValidationError):
        errors = error.errors()
        lines = []
        for e in errors[:MAX_FIELD_ERRORS]:
            loc = ".".join(str(p) for p in e["loc"]) or "spec"
            lines.append(f"{spec}: {loc}: {_one_line(e['msg']).removeprefix('Value error, ')}")
        if len(errors) > MAX_FIELD_ERRORS:
            lines.append(f"{spec}: ... and {len(errors) - MAX_FIELD_ERRORS} more field errors")
        return lines, 2
    ours = type(error).__module__.startswith("fpm.")
    if isinstance(error, UnitsError | AnnealingError) or (ours and isinstance(error, RuntimeError)):
        return [f"error: {_one_line(error)}"], 1  # cannot proceed: units, start, damping search
    if isinstance(error, ValueError):  # a spec the FEM cannot solve, an override out of range
        return [f"error: {_one_line(error)}"], 2
    if isinstance(error, OSError):  # e.g. an output file that cannot be written
        return [f"error: {_one_line(error)}"], 1
    return [
        f"internal error ({type(error).__name__}): {_one_line(error)}; please report it with "
        "the spec and the command"
    ], 1


if __name__ == "__main__":
    sys.exit(main())
