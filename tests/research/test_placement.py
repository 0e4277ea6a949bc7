"""research.placement: the lattice moved by a fraction of a cell, and the product's lattice back."""

import numpy as np
import pytest

from bench.tet_organ import organ_mesh
from research.placement import shifted_lattice


def test_the_shifted_lattice_moves_by_the_fraction_asked_and_the_product_s_comes_back():
    meshio = pytest.importorskip("meshio")
    import fpm.io.meshes.voxelise as voxelise
    from fpm.io.meshes import spec_from_mesh

    nodes, tets = organ_mesh((5, 4, 4))
    given = dict(
        fix=["box:-1,-1,-1:1,1,0"], forces=["nearest:0,0,0.04:0,0,-0.01"], youngs_modulus=5e3,
        poisson_ratio=0.45, spacing=0.012, lattice="voxels",
    )  # fmt: skip

    product = voxelise.lattice
    before = spec_from_mesh(meshio.Mesh(nodes, [("tetra", tets)]), **given)[0]["geometry"]
    with shifted_lattice(0.5, 0.25):
        moved = spec_from_mesh(meshio.Mesh(nodes, [("tetra", tets)]), **given)[0]["geometry"]
    after = spec_from_mesh(meshio.Mesh(nodes, [("tetra", tets)]), **given)[0]["geometry"]
    assert voxelise.lattice is product
    assert after == before
    h = before["spacing"][0]
    # modulo whole cells: the voxeliser crops empty layers off the lattice
    shift = np.mod(np.subtract(before["origin"], moved["origin"]) / h + 1e-9, 1.0) - 1e-9
    assert shift == pytest.approx([0.5, 0.25, 0.0], abs=1e-6)  # z keeps the held plane's nodes
    assert moved["occupancy"] != before["occupancy"]
