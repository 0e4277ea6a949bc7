"""``fpmcal spec from-mesh``: a problem spec from a mesh file, within the service's limits."""

from __future__ import annotations

import argparse
import sys

from .inputs import _emit, _positive


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
