"""``fpmcal calibrate``: the calibration in-process, with the FEM reference and stage 1's chains
kept beside the spec (:mod:`fpmcal.cache`)."""

from __future__ import annotations

import argparse
import json
import sys
from functools import partial

from .inputs import _load, _warn
from .progress import _Bar, _fem_levels
from .result_table import result_table


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
