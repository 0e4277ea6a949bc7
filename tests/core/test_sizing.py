"""A lattice asked for by its node count (``spec from-mesh --nodes``): the spacing is found for
it, the spec's lattice has about that many nodes, and a bad request is one clear line."""

from __future__ import annotations

from pathlib import Path

import meshio
import numpy as np
import pytest

import fpm
from client import spec_from_mesh as sdk_spec_from_mesh
from fpm.io.meshes import MeshError, lattice_nodes, spacing_for_nodes, spec_from_mesh
from fpmcal.cli import main
from tests.core.test_real_organs import MATERIAL, organ


def test_lattice_nodes_counts_the_corners_of_the_occupied_cells():
    assert lattice_nodes(np.ones((1, 1, 1))) == 8
    assert lattice_nodes(np.ones((2, 1, 1))) == 12
    assert lattice_nodes(np.ones((3, 4, 5))) == 4 * 5 * 6
    ell = np.zeros((2, 2, 1), dtype=bool)
    ell[0, 0] = ell[1, 0] = ell[0, 1] = True  # three cells in an L: 3 x 3 corners less one
    assert lattice_nodes(ell) == 2 * (9 - 1)
    diagonal = np.zeros((2, 2, 2), dtype=bool)
    diagonal[0, 0, 0] = diagonal[1, 1, 1] = True  # two cells sharing one corner
    assert lattice_nodes(diagonal) == 15


@pytest.mark.parametrize("asked", [300, 1500])
def test_the_spacing_is_found_for_the_node_count(asked: int):
    given = dict(fix=["face:z-"], forces=["nearest:0,0,0.035:0,0,-0.01"], **MATERIAL)
    spec, notes = spec_from_mesh(organ(), nodes=asked, **given)
    found = fpm.load_problem(spec).n_nodes
    assert abs(found / asked - 1) < 0.1
    assert f"for about {asked:,} nodes: the lattice has {found:,}" in notes[0]
    h = float(notes[0].split("h = ")[1].split(" m")[0])
    again, _ = spec_from_mesh(organ(), spacing=h, **given)
    assert again == spec  # the spacing found, given as such, makes the same spec


def test_more_nodes_ask_for_a_finer_spacing():
    coarse, _ = spacing_for_nodes(organ(), 400)
    fine, _ = spacing_for_nodes(organ(), 3200)
    assert fine == pytest.approx(coarse / 2, rel=0.15)  # 8 times the nodes: half the spacing


def test_bad_node_requests_are_refused(tmp_path: Path, capsys):
    given = dict(fix=["face:z-"], forces=["face:z+:0,0,-1"], **MATERIAL)
    with pytest.raises(ValueError, match="not both"):
        spec_from_mesh(organ(), nodes=1000, spacing=0.01, **given)
    with pytest.raises(ValueError, match="at least 8"):
        spec_from_mesh(organ(), nodes=3, **given)
    hexahedra = meshio.Mesh(
        np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0, 0, 1], [1, 0, 1], [1, 1, 1],
                  [0, 1, 1]], dtype=float) * 0.01,
        [("hexahedron", np.arange(8)[None])],
    )  # fmt: skip
    with pytest.raises(MeshError, match="used as it is"):
        spec_from_mesh(hexahedra, nodes=100, **given)
    path = tmp_path / "organ.vtu"
    meshio.write(path, organ())
    argv = ["spec", "from-mesh", str(path), "--nodes", "500", "--spacing", "0.01", "--fix",
            "face:z-", "--force", "face:z+:0,0,-1", "--E", "5000", "--nu", "0.45"]  # fmt: skip
    assert main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "not both" in err[0]
    argv = [a for a in argv if a not in ("--spacing", "0.01")] + ["-o", str(tmp_path / "s.json")]
    assert main(argv) == 0
    assert "for about 500 nodes" in capsys.readouterr().err
    sdk = sdk_spec_from_mesh(path, nodes=500, fix=["face:z-"], forces=["face:z+:0,0,-1"],
                             youngs_modulus=5e3, poisson_ratio=0.45)  # fmt: skip
    assert abs(fpm.load_problem(sdk).n_nodes / 500 - 1) < 0.1
