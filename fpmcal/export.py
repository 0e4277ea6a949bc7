"""``fpmcal export``: a fitted parameter set with its lattice, made here from SPEC and PARAMS or
fetched from the service."""

from __future__ import annotations

import argparse
import json
import sys
from functools import partial
from pathlib import Path

from .inputs import ServiceError, _load, _one_line, _read_json, _warn
from .progress import _fem_levels


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
