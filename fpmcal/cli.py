"""`fpmcal`: the numerical core from the command line (simulate, fem, calibrate, spec from-mesh,
export, up).

Errors are one line each on stderr, never a traceback (see :func:`main` for exit statuses);
notes on the spec (e.g. which node a ``nearest`` selector took) and warnings (e.g. a reference
outside small strain) go to stderr too, so stdout holds only the result.
"""

from __future__ import annotations

import argparse
import os
import sys
from typing import get_args

from pydantic import ValidationError

from .backup import cmd_store
from .calibrate import cmd_calibrate
from .export import cmd_export
from .inputs import SpecFileError, _one_line
from .runs import cmd_equilibrium, cmd_fem, cmd_simulate
from .spec_from_mesh import cmd_spec_from_mesh

MAX_FIELD_ERRORS = 20
"""Field errors printed for a bad spec (the rest are counted)."""


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
