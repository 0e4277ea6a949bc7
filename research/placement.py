"""How much the lattice's placement moves an organ's figures.

``python -m research.placement ORGAN H DX DY`` (an organ of :data:`bench.tet_organ.ORGANS`, h in
m, DX and DY fractions of h): the row of ``python -m bench.bench_refine organ-case ORGAN H``
(the organ as ``spec from-mesh`` makes it with the defaults, its refine-auto reference, the
calibration, the export solved on its own), with the voxel lattice's origin moved by
(-DX h, -DY h) along x and y and one more cell along each moved axis, so that it still covers
the mesh. Along z the lattice keeps its plane of nodes on the held plane
(:func:`fpm.io.meshes.voxelise.support_planes`). ``0 0`` is the product's lattice (centred on
the mesh along x and y). Prints the row as JSON. About 4 minutes at 2,000 nodes (the
reference), 10 on the kidney.
"""

from __future__ import annotations

import json
import sys
from collections.abc import Iterator
from contextlib import contextmanager


@contextmanager
def shifted_lattice(dx: float, dy: float) -> Iterator[None]:
    """Within it, :func:`fpm.io.meshes.voxelise.lattice` puts its origin ``dx``, ``dy`` cells
    (fractions of h) lower along x and y, with one more cell along each axis it moves."""
    import fpm.io.meshes.voxelise as voxelise

    product = voxelise.lattice

    def lattice(lo, hi, spacing, planes=None):  # type: ignore[no-untyped-def]
        origin, cells = product(lo, hi, spacing, planes)
        origin, cells = origin.copy(), cells.copy()
        for axis, shift in enumerate((dx, dy)):
            if shift:
                origin[axis] -= shift * spacing
                cells[axis] += 1
        return origin, cells

    voxelise.lattice = lattice
    try:
        yield
    finally:
        voxelise.lattice = product


def main() -> None:
    from bench.bench_refine import run_organ

    organ, spacing, dx, dy = sys.argv[1], float(sys.argv[2]), *map(float, sys.argv[3:5])
    with shifted_lattice(dx, dy):
        row = run_organ(organ, spacing)
    row["shift"] = [dx, dy]
    print(json.dumps(row))


if __name__ == "__main__":
    main()
