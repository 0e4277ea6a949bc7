"""The organ meshes of bench/anatomy.py (with bench/frog.py and bench/shapes.py): the VTK
ImageData reader against files written here, the generated organs against their analytic
shapes, their presses in the command line's form, and the frog's organs (with the ``anatomy``
extra) as valid tetrahedra."""

from __future__ import annotations

import base64
import importlib.util
import subprocess
import zlib
from pathlib import Path

import meshio
import numpy as np
import pytest
from scipy import ndimage

from bench import anatomy, frog, shapes
from bench.anatomy import ORGANS, check
from bench.frog import read_vti
from fpm.io.meshes.selectors import parse_force, parse_selector
from fpm.model.tetrahedra import TetMesh, closest_on_triangles


def vti(values: np.ndarray, spacing, origin, *, block: int | None = 64, header: str = "UInt32"):
    """The bytes of a VTK XML ImageData file holding ``values`` (nx, ny, nz) as its point data:
    inline binary, zlib-compressed in blocks of ``block`` bytes (None: uncompressed)."""
    kind = {"u1": "UInt8", "f4": "Float32", "i2": "Int16"}[values.dtype.str[1:]]
    raw = np.ascontiguousarray(values.transpose(2, 1, 0)).astype(values.dtype.newbyteorder("<"))
    data = raw.tobytes()
    h = np.dtype("<u4" if header == "UInt32" else "<u8")
    if block is None:
        text = base64.b64encode(np.array([len(data)], h).tobytes() + data).decode()
        compressor = ""
    else:
        pieces = [data[i : i + block] for i in range(0, len(data), block)]
        packed = [zlib.compress(p) for p in pieces]
        head = [len(pieces), block, len(pieces[-1]), *map(len, packed)]
        text = (
            base64.b64encode(np.array(head, h).tobytes()).decode()
            + base64.b64encode(b"".join(packed)).decode()
        )
        compressor = ' compressor="vtkZLibDataCompressor"'
    n = values.shape
    extent = f"0 {n[0] - 1} 0 {n[1] - 1} 0 {n[2] - 1}"
    return (
        f'<?xml version="1.0"?>\n<VTKFile type="ImageData" version="0.1" '
        f'byte_order="LittleEndian" header_type="{header}"{compressor}>\n'
        f'<ImageData WholeExtent="{extent}" Origin="{" ".join(map(str, origin))}" '
        f'Spacing="{" ".join(map(str, spacing))}">\n<Piece Extent="{extent}">\n'
        f'<PointData Scalars="v">\n<DataArray type="{kind}" Name="v" format="binary">\n'
        f"  {text}\n</DataArray>\n</PointData>\n<CellData>\n</CellData>\n</Piece>\n"
        "</ImageData>\n</VTKFile>\n"
    ).encode()


# ------------------------------------------------------------------ the reader


@pytest.mark.parametrize("block", [64, 1000, None])
@pytest.mark.parametrize("header", ["UInt32", "UInt64"])
def test_the_reader_returns_what_was_written_in_x_y_z_order(block, header):
    rng = np.random.default_rng(1)
    labels = rng.integers(0, 30, size=(7, 5, 4)).astype(np.uint8)
    labels[6, 0, 0] = 200  # one voxel to find by place: x = 6, y = 0, z = 0
    values, origin, spacing = read_vti(vti(labels, (1, 1, 1.5), (0.5, 0, -2), block=block,
                                           header=header))  # fmt: skip
    assert values.shape == (7, 5, 4) and values.dtype == np.uint8
    np.testing.assert_array_equal(values, labels)
    assert values[6, 0, 0] == 200
    np.testing.assert_allclose(origin, [0.5, 0, -2])
    np.testing.assert_allclose(spacing, [1, 1, 1.5])


def test_the_reader_reads_floats_and_refuses_what_it_cannot_read():
    field = np.linspace(-1, 1, 3 * 4 * 2, dtype=np.float32).reshape(3, 4, 2)
    np.testing.assert_array_equal(read_vti(vti(field, (1, 1, 1), (0, 0, 0), block=40))[0], field)
    text = vti(field, (1, 1, 1), (0, 0, 0))
    with pytest.raises(ValueError, match="VTKFile type 'PolyData'"):
        read_vti(text.replace(b'type="ImageData"', b'type="PolyData"', 1))
    with pytest.raises(ValueError, match="compressor 'vtkLZ4DataCompressor'"):
        read_vti(text.replace(b"vtkZLibDataCompressor", b"vtkLZ4DataCompressor"))
    with pytest.raises(ValueError, match="WholeExtent needs 30"):
        read_vti(text.replace(b'WholeExtent="0 2 0 3 0 1"', b'WholeExtent="0 2 0 4 0 1"'))


# ------------------------------------------------------------------ generated organs


GENERATED = {
    "lobe": (shapes.lobe, {"cells": (64, 32, 8)}),
    "hollow": (shapes.hollow, {"cells": 28, "layers": 4}),
    "limb": (shapes.limb, {"cells": (88, 12)}),
}


@pytest.mark.parametrize("name", list(GENERATED))
def test_a_generated_organ_is_valid_and_converges_to_its_analytic_volume(name):
    organ = ORGANS[name]
    build, finer = GENERATED[name]
    found = check(organ.mesh())
    assert found.valid, found
    assert found.sheets == (2 if name == "hollow" else 1)  # a closed wall: outside and inside
    assert max(found.extent) == pytest.approx(shapes.LONGEST, rel=1e-3)
    error = abs(found.volume / organ.volume - 1)
    fine = build(**finer)
    tets = fine.get_cells_type("tetra")
    assert len(tets) == 8 * found.tetrahedra
    c = fine.points[tets]
    volume = np.linalg.det(np.transpose(c[:, 1:] - c[:, :1], (0, 2, 1))) / 6
    assert volume.min() > 0
    assert error < 0.02
    # the polyhedral error of a smooth shape falls as h^2 (a plane-faced one's is exact already)
    assert abs(volume.sum() / organ.volume - 1) < max(error / 3, 1e-9)


def test_the_thin_parts_are_as_thin_as_they_are_said_to_be():
    lobe = np.asarray(ORGANS["lobe"].mesh().points)
    rim = lobe[np.isclose(lobe[:, 0], shapes.LONGEST)]
    assert np.ptp(rim[:, 2]) == pytest.approx(0.01 * shapes.LONGEST)  # 1% of its length
    root = lobe[np.isclose(lobe[:, 0], 0)]
    assert np.ptp(root[:, 2]) == pytest.approx(0.3 * shapes.LONGEST)
    limb = np.asarray(ORGANS["limb"].mesh().points)
    tip = limb[np.isclose(limb[:, 0], shapes.LONGEST)]
    assert np.ptp(tip[:, 1]) == pytest.approx(2 * shapes.LIMB["tip"])
    hollow = ORGANS["hollow"].mesh()
    radial = np.asarray(hollow.points) - np.ptp(hollow.points, axis=0) / 2
    axes = np.asarray(shapes.HOLLOW["semi_axes"])
    r = np.linalg.norm(radial / axes, axis=1)
    assert r.max() == pytest.approx(1) and r.min() == pytest.approx(1 - shapes.HOLLOW["wall"])


def test_the_check_finds_flat_inverted_loose_and_non_manifold_tetrahedra():
    unit = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], float)
    assert check(meshio.Mesh(unit, [("tetra", np.array([[0, 1, 2, 3]]))])).valid
    inverted = check(meshio.Mesh(unit, [("tetra", np.array([[0, 2, 1, 3]]))]))
    assert inverted.worst_shape < 0 and not inverted.valid
    flat = unit.copy()
    flat[3] = [0.3, 0.3, 1e-12]
    assert not check(meshio.Mesh(flat, [("tetra", np.array([[0, 1, 2, 3]]))])).valid
    two = np.vstack([unit, unit + 5])
    apart = check(meshio.Mesh(two, [("tetra", np.array([[0, 1, 2, 3], [4, 5, 6, 7]]))]))
    assert apart.pieces == 2 and apart.open_edges == 0 and not apart.valid
    # two tetrahedra sharing only the edge 0-1: four boundary triangles on it
    edge = np.vstack([unit, [[0.5, -1, -1]], [[0.5, -1, 0.2]]])
    hinge = check(meshio.Mesh(edge, [("tetra", np.array([[0, 1, 2, 3], [0, 1, 4, 5]]))]))
    assert hinge.open_edges == 1 and hinge.pieces == 2


@pytest.mark.parametrize("name", list(GENERATED))
def test_the_presses_are_the_command_lines_and_act_on_the_surface_of_the_organ(name):
    organ = ORGANS[name]
    mesh = organ.mesh()
    given = organ.presses(mesh)
    assert len(given["forces"]) == 2 and len(given["validation"]) == 3
    points = np.asarray(mesh.points)
    (fix,) = given["fix"]
    lo, hi = np.asarray(parse_selector(fix)["box"])
    held = ((points >= lo) & (points <= hi)).all(axis=1)
    assert 0.03 < held.mean() < 0.4  # a side held, most of the organ free
    triangles, _ = TetMesh(mesh.points, mesh.get_cells_type("tetra")).boundary
    a, b, c = (points[triangles[:, i]] for i in range(3))
    normal = np.cross(b - a, c - a)
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    for text in given["forces"] + given["validation"]:
        (force,) = parse_force(text)
        p, f = np.asarray(force["nearest"]), np.asarray(force["vector"])
        gap = np.linalg.norm(closest_on_triangles(np.tile(p, (len(a), 1)), a, b, c) - p, axis=1)
        assert gap.min() < 1e-3  # on the surface (the analytic one, 1 mm from the faces)
        assert f @ normal[np.argmin(gap)] < -0.7 * np.linalg.norm(f)  # pushing in
        assert 1e-4 < np.linalg.norm(f) <= 1.001 * anatomy.STRAIN * anatomy.YOUNGS * 0.02**2
        assert not held[np.argmin(np.linalg.norm(points - p, axis=1))]


# ------------------------------------------------------------------ the frog's organs

ANATOMY = all(importlib.util.find_spec(m) for m in ("skimage", "gmsh"))
needs_anatomy = pytest.mark.skipif(
    not ANATOMY, reason="the anatomy extra (scikit-image, gmsh) is not installed: "
    "pip install -e '.[anatomy]'"
)  # fmt: skip


def frog_labels():
    try:
        return frog.frog_labels()
    except subprocess.CalledProcessError as e:  # no package registry reachable
        pytest.skip(f"pip could not fetch {frog.PYVISTA}: {e}")


def test_the_frog_label_volume_is_the_segmentation_pyvista_ships():
    labels, spacing = frog_labels()
    assert labels.shape == (500, 470, 136) and labels.dtype == np.uint8
    np.testing.assert_allclose(spacing, [1e-3, 1e-3, 1.5e-3])
    counts = np.bincount(labels.ravel(), minlength=30)
    organs = {name: counts[k] for k, name in frog.FROG_TISSUES.items()}
    assert max(organs, key=organs.get) == "skeleton"  # type: ignore[arg-type]
    assert sorted(organs, key=organs.get)[-2:-1] == ["liver"]  # type: ignore[arg-type]
    assert counts[16:].sum() < 1e-3 * counts[1:16].sum()  # the other labels are specks
    boxes = ndimage.find_objects(labels, max_label=10)
    assert boxes[2 - 1][0].start > boxes[10 - 1][0].stop  # the brain lies beyond the liver in x


@needs_anatomy
def test_a_frog_organ_becomes_valid_tetrahedra_at_the_size_asked(tmp_path: Path, monkeypatch):
    frog_labels()  # the wheel from the user's cache; the mesh made afresh here
    monkeypatch.setattr(frog, "CACHE", tmp_path)
    mesh = frog.frog_organ("kidney", step=4)
    found = check(mesh)
    assert found.valid and found.sheets == 1, found
    assert max(found.extent) == pytest.approx(shapes.LONGEST)
    labels, spacing = frog.frog_labels()
    kidney = frog.largest_piece(labels == 8)
    scale = shapes.LONGEST / (np.ptp(np.argwhere(kidney) * spacing, axis=0) + spacing).max()
    voxels = kidney.sum() * np.prod(spacing) * scale**3
    # the smoothing (1.5 mm) fills the clefts narrower than it and rounds the mesh, which is
    # then scaled by its own extent: within 20% of the voxels' volume
    assert found.volume == pytest.approx(voxels, rel=0.2)
    assert (tmp_path / "frog-kidney-s4.vtu").exists()
    again = frog.frog_organ("kidney", step=4)
    np.testing.assert_array_equal(again.get_cells_type("tetra"), mesh.get_cells_type("tetra"))


@pytest.mark.slow
@needs_anatomy
@pytest.mark.parametrize("tissue", anatomy.FROG_ORGANS)
def test_every_frog_organ_of_the_registry_is_valid_and_pressed_on_its_surface(tissue):
    frog_labels()
    organ = ORGANS[f"frog {tissue}"]
    mesh = organ.mesh()
    found = check(mesh)
    assert found.valid, found
    given = organ.presses(mesh)
    assert len(given["forces"]) == 2 and len(given["validation"]) == 3
    for text in given["forces"] + given["validation"]:
        parse_force(text)
