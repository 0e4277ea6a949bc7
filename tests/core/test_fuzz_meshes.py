"""Bad organ meshes, generated: small tetrahedral meshes (a box or an L-shape split into
tetrahedra, interior nodes jittered), sometimes corrupted (a flipped, a flat or a repeated-corner
tetrahedron, a duplicated, unused, non-finite or out-of-range node, a second piece, a slab
thinner than the spacing, coordinates in mm, m or km), at spacings from one cell thick to fine, held
and loaded at surface points, inside or far away.

The product's rule: bad input gives a clear error naming the field and the place (a
:class:`~fpm.io.errors.MeshError` from ``spec_from_mesh``, a pydantic ``ValidationError`` from the
spec's checks: a 422 in the API, never a 500); good input gives a problem that loads.
``FUZZ_MESH_EXAMPLES`` (environment) sets the in-process example count (default 300) to hunt.
"""

from __future__ import annotations

import json
import math
import os
import re
from dataclasses import dataclass
from typing import Any

import meshio
import numpy as np
import pytest
from hypothesis import HealthCheck, event, given
from hypothesis import settings as hyp_settings
from hypothesis import strategies as st
from pydantic import ValidationError
from test_service import PROBLEM_JSON

import fpm
from fpm.io.meshes import MeshError, spec_from_mesh

MATERIAL = {"youngs_modulus": 5e3, "poisson_ratio": 0.45, "density": 1040.0}
EXAMPLES = int(os.environ.get("FUZZ_MESH_EXAMPLES", "300"))
"""In-process examples (each well under a second); more to hunt defects."""
API_EXAMPLES = int(os.environ.get("FUZZ_MESH_API_EXAMPLES", "2"))
"""Examples over REST per corruption."""
MAX_LATTICE_NODES = 700
"""The spacing drawn is coarsened so that the lattice has about at most this many nodes."""
KUHN = [[0, 1, 2, 6], [0, 2, 3, 6], [0, 3, 7, 6], [0, 7, 4, 6], [0, 4, 5, 6], [0, 5, 1, 6]]
"""Six tetrahedra around the diagonal 0-6 of a hexahedron (VTK order)."""
HEX = [(0, 0, 0), (1, 0, 0), (1, 1, 0), (0, 1, 0), (0, 0, 1), (1, 0, 1), (1, 1, 1), (0, 1, 1)]


def grid_tetrahedra(
    counts: tuple[int, int, int], size: np.ndarray, keep: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """(N, 3) nodes and (T, 4) positive tetrahedra of a box of ``size`` (m) cut into ``counts``
    cells, each split into 6 tetrahedra (Kuhn: conforming across cells); ``keep`` (cx, cy, cz)
    bool: the cells kept (an L-shape); only the nodes the tetrahedra use."""
    nx, ny, nz = counts
    axes = [np.linspace(0.0, s, n + 1) for s, n in zip(size, counts, strict=True)]
    grid = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    index = np.arange(len(grid)).reshape(nx + 1, ny + 1, nz + 1)
    cells = np.argwhere(np.ones(counts, bool) if keep is None else keep)
    i, j, k = cells.T
    corners = np.stack([index[i + a, j + b, k + c] for a, b, c in HEX], axis=1)
    tets = corners[:, KUHN].reshape(-1, 4)
    used, inverse = np.unique(tets, return_inverse=True)
    nodes, tets = grid[used], inverse.reshape(-1, 4)
    return nodes, positive(nodes, tets)


def positive(nodes: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """``tets`` with the inside-out ones renumbered."""
    c = nodes[tets]
    volume = np.linalg.det(np.transpose(c[:, 1:] - c[:, :1], (0, 2, 1)))
    tets = tets.copy()
    tets[volume < 0] = tets[volume < 0][:, [0, 2, 1, 3]]
    return tets


def surface_nodes(tets: np.ndarray, n: int) -> np.ndarray:
    """(N,) bool: the nodes of the faces that belong to one tetrahedron only."""
    faces = np.sort(tets[:, [[1, 2, 3], [0, 2, 3], [0, 1, 3], [0, 1, 2]]].reshape(-1, 3), axis=1)
    unique, count = np.unique(faces, axis=0, return_counts=True)
    out = np.zeros(n, dtype=bool)
    out[unique[count == 1].ravel()] = True
    return out


@dataclass
class Case:
    """One drawn input: the mesh, the ``spec_from_mesh`` arguments, what was done to it."""

    points: np.ndarray
    tets: np.ndarray
    options: dict[str, Any]
    corruption: str = "none"
    clean: tuple[np.ndarray, np.ndarray] | None = None
    """The mesh before the corruption (same units)."""
    tags: bool = False
    """Integer cell data (gmsh:physical: 1 below the middle in z, 2 above)."""
    blocks: int = 1
    """Tetrahedra in this many cell blocks."""

    def mesh(self, clean: bool = False) -> meshio.Mesh:
        points, tets = self.clean if clean and self.clean is not None else (self.points, self.tets)
        cuts = np.linspace(0, len(tets), self.blocks + 1).astype(int)
        spans = list(zip(cuts[:-1], cuts[1:], strict=True))
        parts = [tets[a:b] for a, b in spans]
        cell_data = None
        if self.tags:
            finite = np.where(np.isfinite(points), points, 0.0)
            z = finite[np.clip(tets, 0, len(points) - 1)][:, :, 2].mean(axis=1)
            tag = np.where(z > np.median(z), 2, 1)
            cell_data = {"gmsh:physical": [tag[a:b] for a, b in spans]}
        return meshio.Mesh(points, [("tetra", p) for p in parts], cell_data=cell_data)


CORRUPTIONS = (
    "flip",
    "flat",
    "repeated corner",
    "duplicate node",
    "split node",
    "unused node",
    "far unused node",
    "index out of range",
    "negative index",
    "nan",
    "inf",
    "unused nan",
    "second piece",
    "touching piece",
    "unmerged halves",
    "thin slab",
)


@st.composite
def cases(draw: st.DrawFn, corruption: str | None = None) -> Case:
    """A small tetrahedral mesh (50-600 tetrahedra), jittered, in one case of two corrupted
    (or with the ``corruption`` given); a spacing (or a node count), fixed nodes and forces."""
    unit = draw(st.sampled_from([1e-3, 1.0, 1e3]))  # the solid is 20 um .. 80 m
    shape = draw(st.sampled_from(["box", "L"]))
    if corruption is None:
        corruption = draw(st.sampled_from(("none",) * len(CORRUPTIONS) + CORRUPTIONS))
    counts = tuple(draw(st.integers(2, 5)) for _ in range(3))
    while 6 * math.prod(counts) > 600:
        counts = tuple(max(2, c - 1) for c in counts)
    size = np.array([draw(st.sampled_from([0.02, 0.03, 0.05, 0.08])) for _ in range(3)]) * unit
    if corruption == "thin slab":
        axis = draw(st.integers(0, 2))
        size[axis] *= draw(st.sampled_from([1e-3, 0.02, 0.1]))
    keep = None
    if shape == "L":
        keep = np.ones(counts, bool)
        keep[counts[0] // 2 :, :, counts[2] // 2 :] = False  # the upper half of x's far half
    points, tets = grid_tetrahedra(counts, size, keep)  # type: ignore[arg-type]
    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
    cell = size / np.asarray(counts)
    jitter = draw(st.sampled_from([0.0, 0.1, 0.25, 0.45]))
    inner = ~surface_nodes(tets, len(points))
    points[inner] += rng.uniform(-jitter, jitter, (int(inner.sum()), 3)) * cell
    if draw(st.booleans()):  # the surface too, a little (its faces no longer flat)
        outer = ~inner
        points[outer] += rng.uniform(-0.05, 0.05, (int(outer.sum()), 3)) * cell
    tets = positive(points, tets)
    extent = np.ptp(points, axis=0)
    clean = points.copy(), tets.copy()
    points, tets = corrupt(draw, rng, corruption, points, tets)

    # the spacing: from one cell across the thinnest side to fine, capped in nodes
    volume = float(np.prod(extent))
    floor = (volume / MAX_LATTICE_NODES) ** (1 / 3)
    options: dict[str, Any] = {}
    if draw(st.integers(0, 3)) == 0:
        options["nodes"] = draw(st.integers(8, MAX_LATTICE_NODES))
    else:
        fraction = draw(st.sampled_from([0.1, 0.2, 0.34, 0.5, 0.7, 1.0, 1.5]))
        options["spacing"] = float(f"{max(fraction * extent.min(), floor):.3g}")
    scaled = draw(st.booleans()) and unit != 1.0  # given in its units, with scale to m
    finite = points[np.isfinite(points).all(axis=1)]
    lo, hi = finite.min(axis=0), finite.max(axis=0)
    fix = draw(
        st.sampled_from(
            [
                ["face:z-"],
                ["face:x-"],
                [box(lo - 0.1 * extent, [hi[0], hi[1], lo[2] + 0.3 * extent[2]])],
                ["face:z-", "nearest:" + vec(hi)],
            ]
        )
    )
    kinds = st.sampled_from(["surface point", "inside point", "far point", "nearest top", "face"])
    texts = [  # 1-2 load cases of 1-2 forces each
        ";".join(
            force_text(draw(kinds), points, tets, lo, hi, extent, rng)
            for _ in range(draw(st.integers(1, 2)))
        )
        for _ in range(draw(st.integers(1, 2)))
    ]
    if scaled:  # the mesh in mm or km: scale brings it to m
        points = points / unit
        clean = clean[0] / unit, clean[1]
        options["scale"] = unit  # (the spacing, selectors and forces are in m, after it)
    options.update(
        fix=fix,
        forces=texts,
        lattice=draw(st.sampled_from(["conforming", "conforming", "voxels"])),
        **MATERIAL,
    )
    event(f"corruption: {corruption}")
    tags, blocks = draw(st.booleans()), draw(st.sampled_from([1, 1, 2]))
    return Case(points, tets, options, corruption, clean, tags, blocks)


def vec(v: Any) -> str:
    return ",".join(repr(float(x)) for x in v)


def box(lo: Any, hi: Any) -> str:
    return f"box:{vec(lo)}:{vec(hi)}"


def force_text(
    kind: str,
    points: np.ndarray,
    tets: np.ndarray,
    lo: np.ndarray,
    hi: np.ndarray,
    extent: np.ndarray,
    rng: np.random.Generator,
) -> str:
    """A force (``parse_force``'s short form) of a load case: at a point of the surface (its
    top's, as ``bench/tet_organ.py`` puts them), inside, far away, at the nearest node or
    spread over the top face."""
    vector = ",".join(repr(float(x)) for x in rng.choice([-1.0, 1.0], 3) * [0.01, 0.01, 0.02])
    top = np.array([(lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, hi[2]])
    if kind == "surface point":
        aim = top + rng.uniform(-0.3, 0.3, 3) * extent
        try:
            from fpm.model.tetrahedra import TetMesh

            good = np.isfinite(points).all(axis=1)
            valid = tets[((tets >= 0) & (tets < len(points))).all(axis=1)]
            valid = valid[good[valid].all(axis=1)]
            aim = TetMesh(points, valid).nearest_on_boundary(aim[None])[1][0]
        except Exception:  # a corrupted mesh: the aim as it is
            pass
        return f"point:{vec(aim)}:{vector}"
    if kind == "inside point":
        return f"point:{vec((lo + hi) / 2)}:{vector}"
    if kind == "far point":
        return f"point:{vec(hi + 3 * extent)}:{vector}"
    if kind == "nearest top":
        return f"nearest:{vec(top)}:{vector}"
    return f"face:z+:{vector}:distribute"  # "face"


def corrupt(
    draw: st.DrawFn,
    rng: np.random.Generator,
    corruption: str,
    points: np.ndarray,
    tets: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """The mesh with one ``corruption`` (:data:`CORRUPTIONS`; "none" and "thin slab": as it
    is)."""
    points, tets = points.copy(), tets.copy()
    t = draw(st.integers(0, len(tets) - 1))
    n = len(points)
    if corruption == "flip":
        tets[t] = tets[t][[1, 0, 2, 3]]
    elif corruption == "flat":  # a node on a tetrahedron's face, and a tetrahedron on it
        c = points[tets[t, :3]].mean(axis=0)
        points = np.vstack([points, c])
        tets = np.vstack([tets, [[tets[t, 0], tets[t, 1], tets[t, 2], n]]])
    elif corruption == "repeated corner":
        tets[t, 3] = tets[t, draw(st.integers(0, 2))]
    elif corruption == "duplicate node":  # a copy, unused
        points = np.vstack([points, points[draw(st.integers(0, n - 1))]])
    elif corruption == "split node":  # a copy, used by some of the tetrahedra at the node
        node = int(tets[t, 0])
        points = np.vstack([points, points[node]])
        users = np.flatnonzero((tets == node).any(axis=1))
        moved = users[: max(1, len(users) // 2)]
        tets[moved] = np.where(tets[moved] == node, n, tets[moved])
    elif corruption == "unused node":
        points = np.vstack([points, points.mean(axis=0)])
    elif corruption == "far unused node":
        points = np.vstack([points, points.max(axis=0) + 50 * np.ptp(points, axis=0)])
    elif corruption == "index out of range":
        tets[t, draw(st.integers(0, 3))] = n + draw(st.integers(0, 5))
    elif corruption == "negative index":
        tets[t, draw(st.integers(0, 3))] = -draw(st.integers(1, 3))
    elif corruption in ("nan", "inf"):
        value = np.nan if corruption == "nan" else draw(st.sampled_from([np.inf, -np.inf]))
        points[tets[t, 0], draw(st.integers(0, 2))] = value
    elif corruption == "unused nan":
        points = np.vstack([points, [np.nan, 0.0, 0.0]])
    elif corruption == "unmerged halves":  # two blocks meeting at a face, each its own nodes
        x = points[tets].mean(axis=1)[:, 0]
        upper = x > np.median(x)
        mine = np.unique(tets[upper])
        copy = np.full(n, -1)
        copy[mine] = n + np.arange(len(mine))
        points = np.vstack([points, points[mine]])
        tets[upper] = copy[tets[upper]]
    elif corruption in ("second piece", "touching piece"):
        extent = np.ptp(points, axis=0)
        scale = draw(st.sampled_from([0.2, 0.5, 1.0]))
        other, other_tets = grid_tetrahedra((2, 2, 2), extent * scale)
        gap = 0.0 if corruption == "touching piece" else draw(st.sampled_from([0.05, 0.5, 2.0]))
        other = other + points.min(axis=0) + [extent[0] * (1 + gap), 0.0, 0.0]
        points = np.vstack([points, other])
        tets = np.vstack([tets, other_tets + n])
    return points, tets


# --- Property: a spec that loads, or a clear error ---------------------------------------------


def index_pieces(tets: np.ndarray) -> int:
    """How many pieces ``tets`` (T, 4) make, tetrahedra joined through faces of shared node
    indices (as the FEM joins them: two nodes at one point are two nodes to it)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    faces = np.sort(tets[:, [[1, 2, 3], [0, 2, 3], [0, 1, 3], [0, 1, 2]]].reshape(-1, 3), axis=1)
    _, face = np.unique(faces, axis=0, return_inverse=True)
    count = len(tets) + int(face.max()) + 1
    owner = np.repeat(np.arange(len(tets)), 4)
    graph = coo_matrix((np.ones(len(owner)), (owner, len(tets) + face.ravel())), (count, count))
    labels = connected_components(graph, directed=False)[1][: len(tets)]
    return len(np.unique(labels))


def loads_or_says_where(case: Case) -> str:
    """``spec_from_mesh`` then ``fpm.load_problem``: a problem with finite nodes, a fixed and a
    free node, whose reference tetrahedra are one piece (the lattice is); or a MeshError /
    ValidationError whose message names the cell, the node, the field or the place (a number:
    an index, a point, a spacing). Returns what happened (for ``event``)."""
    try:
        spec, _ = spec_from_mesh(case.mesh(), **case.options)
        problem = fpm.load_problem(spec)
    except MeshError as e:
        message = str(e)
        assert re.search(r"\d", message), f"MeshError naming no place: {message}"
        assert "Traceback" not in message
        return f"MeshError: {message[:40]}"
    except ValidationError as e:
        errors = e.errors()
        assert errors and all(err["loc"] and err["msg"] for err in errors), errors
        return f"ValidationError at {'.'.join(map(str, errors[0]['loc'][:2]))}"
    assert np.all(np.isfinite(problem.nodes)), "non-finite lattice nodes"
    assert problem.fixed.any() and not problem.fixed.all()
    assert problem.n_nodes > 0 and len(problem.load_cases) == len(case.options["forces"])
    if "mesh" in spec.get("reference", {}):
        tets = np.asarray(spec["reference"]["mesh"]["tetrahedra"])
        assert index_pieces(tets) == 1, "the reference's tetrahedra are in pieces"
    return "loaded"


@hyp_settings(
    max_examples=EXAMPLES,
    deadline=None,
    database=None,
    derandomize=True,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.filter_too_much],
)
@given(case=cases())
def test_a_mesh_loads_or_is_refused_naming_the_place(case: Case):
    event(loads_or_says_where(case))


# --- The same over REST: 422 naming the field, never a 500 -------------------------------------


NUMBERED_TWICE = ("duplicate node", "split node", "unmerged halves")
"""Corruptions that only number nodes twice: the FEM joins them
(:func:`fpm.model.tetrahedra.merge_coincident`), so a spec answers as the clean mesh's does."""
PIECES = ("second piece", "touching piece")
"""Corruptions that add a piece: refused at ``reference.mesh`` when the lattice joins it."""


def raw_mesh(case: Case, clean: bool = False) -> dict[str, Any]:
    """The drawn mesh (or the ``clean`` one) as ``reference.mesh`` / ``POST /v1/meshes`` take
    it (m; NaN and inf go out as JSON's NaN / Infinity tokens, which the service's parser
    reads)."""
    points, tets = case.clean if clean and case.clean is not None else (case.points, case.tets)
    return {
        "nodes": (points * case.options.get("scale", 1.0)).tolist(),
        "tetrahedra": tets.tolist(),
    }


def assert_422_naming_fields(answer: Any, prefix: str = "") -> list[str]:
    assert answer.status_code == 422, answer.text
    assert answer.headers["content-type"] == PROBLEM_JSON and "Traceback" not in answer.text
    errors = answer.json()["errors"]
    assert errors and all(e["field"] and e["message"] for e in errors), errors
    fields = [e["field"] for e in errors]
    assert all(f.startswith(prefix) for f in fields), fields
    return fields


def post(api: Any, route: str, body: Any) -> Any:
    """POST ``body`` as JSON, NaN and infinities as JavaScript writes them (httpx refuses)."""
    content = json.dumps(body, allow_nan=True)
    return api.post(route, content=content, headers={"content-type": "application/json"})


@pytest.mark.redis
@pytest.mark.parametrize("corruption", ("none",) + CORRUPTIONS)
def test_a_mesh_over_rest_is_accepted_or_422_naming_the_field(api, redis, corruption: str):
    """The drawn mesh uploaded (``POST /v1/meshes``) and as the ``reference.mesh`` of a spec on
    the clean mesh's voxels (``POST /v1/calibrations``): accepted, or 422 naming the element or
    node; the service and ``fpm.load_problem`` agree. :data:`API_EXAMPLES` per corruption."""

    @hyp_settings(
        max_examples=API_EXAMPLES,
        deadline=None,
        database=None,
        derandomize=True,
        suppress_health_check=list(HealthCheck),
    )
    @given(case=cases(corruption))
    def check(case: Case) -> None:
        redis.flushdb()
        over_rest(api, case)

    check()


def over_rest(api: Any, case: Case) -> None:
    uploaded = post(api, "/v1/meshes", raw_mesh(case))
    if uploaded.status_code == 422:
        event(f"upload 422 at {assert_422_naming_fields(uploaded)[0].split('.')[0]}")
    else:
        assert uploaded.status_code in (200, 201), uploaded.text
        event("upload accepted")
    try:  # the spec of the clean mesh, its lattice the voxels (no conforming to a bad mesh)
        options = dict(
            case.options, lattice="voxels", fix=["face:z-"], forces=["face:z+:0,0,-0.01"]
        )
        spec, _ = spec_from_mesh(case.mesh(clean=True), **options)
    except (MeshError, ValidationError):
        event("the clean mesh makes no spec here")
        return
    spec["reference"]["mesh"] = raw_mesh(case)
    spec["annealing"] = {"chains": 1}
    try:
        fpm.load_problem(spec)
        loads = True
    except ValidationError:
        loads = False
    answer = post(api, "/v1/calibrations", spec)
    assert answer.status_code < 500, answer.text
    if uploaded.status_code == 422:  # what the upload refuses, the spec refuses at its place
        assert_422_naming_fields(answer, "reference.mesh.")
    if case.corruption in NUMBERED_TWICE:  # joined, not refused: as the clean mesh answers
        spec["reference"]["mesh"] = raw_mesh(case, clean=True)
        clean = post(api, "/v1/calibrations", spec)
        assert answer.status_code == clean.status_code, (answer.text, clean.text)
    if answer.status_code == 422:
        fields = assert_422_naming_fields(answer)
        event(f"spec 422 at {'.'.join(fields[0].split('.')[:3])}")
        if fields == ["reference.mesh"]:  # pieces the lattice joins, one named
            assert case.corruption in PIECES, answer.text
            assert re.search(
                r"the piece of tetrahedron \d+ \(\d+ tetrahedra, around \[", answer.text
            )
    else:
        assert answer.status_code == 202, answer.text
        assert loads, "the service accepted a spec fpm.load_problem refuses"
        event("spec accepted")


# --- Found by the fuzz tests above (each failed before its fix) --------------------------------


def block(lo: Any, cells: int, size: float) -> tuple[np.ndarray, np.ndarray]:
    """A cube of ``cells``^3 cells, edge ``size`` (m), corner at ``lo``, 6 tetrahedra a cell."""
    nodes, tets = grid_tetrahedra((cells, cells, cells), np.full(3, size))
    return nodes + np.asarray(lo, dtype=float), tets


def joined(*blocks: tuple[np.ndarray, np.ndarray]) -> meshio.Mesh:
    """One tetra block of ``blocks``, each keeping its own nodes (none merged)."""
    nodes, tets, offset = [], [], 0
    for n, t in blocks:
        nodes.append(n)
        tets.append(t + offset)
        offset += len(n)
    return meshio.Mesh(np.vstack(nodes), [("tetra", np.vstack(tets))])


GIVEN = dict(fix=["face:x-"], forces=["face:x+:0,0,-0.01:distribute"], spacing=0.006, **MATERIAL)


@pytest.mark.parametrize("sizing", [{"spacing": 0.006}, {"nodes": 200}])
@pytest.mark.parametrize("where", ["used", "unused"])
def test_a_non_finite_node_is_refused_naming_it(sizing, where):
    """Was "the mesh has non-finite coordinates" (no node named) and, given a node count,
    "the mesh has no extent along some axis" (NaN's extent is NaN)."""
    nodes, tets = block([0, 0, 0], 3, 0.03)
    if where == "used":
        nodes[7, 1] = np.nan
    else:
        nodes = np.vstack([nodes, [np.inf, 0.0, 0.0]])
    bad = 7 if where == "used" else len(nodes) - 1
    with pytest.raises(MeshError, match=rf"^node {bad} of the mesh has a non-finite coordinate"):
        spec_from_mesh(
            meshio.Mesh(nodes, [("tetra", tets)]), **{**GIVEN, "spacing": None, **sizing}
        )


@pytest.mark.parametrize("index", [-1, 10_000])
def test_a_cell_naming_a_node_not_in_the_mesh_is_refused_naming_the_cell(index):
    """Was "a cell names a node that is not in the mesh" (no cell named)."""
    nodes, tets = block([0, 0, 0], 3, 0.03)
    tets[5, 2] = index
    with pytest.raises(MeshError) as raised:
        spec_from_mesh(meshio.Mesh(nodes, [("tetra", tets)]), **GIVEN)
    assert str(raised.value).startswith(
        f"tetra cell 5 (of {len(tets)} in its block; 1 such) names node {index}, which is not "
        f"in the mesh (nodes 0..{len(nodes) - 1})"
    )


def test_nodes_numbered_twice_are_merged_so_the_reference_is_one_solid():
    """Two blocks meeting at a face, each with its own nodes there (as two regions exported
    without merging): the lattice is one solid, but the reference kept both nodes of each
    point, so its tetrahedra were two pieces and the FEM found the unheld one free ("the
    stiffness matrix is singular")."""
    from fpm.fem.reference import solve_fem

    mesh = joined(block([0, 0, 0], 3, 0.03), block([0.03, 0, 0], 3, 0.03))
    spec, notes = spec_from_mesh(mesh, **GIVEN)
    reference = spec["reference"]["mesh"]
    assert index_pieces(np.asarray(reference["tetrahedra"])) == 1
    assert len(reference["nodes"]) == 2 * 64 - 16
    assert any("merged 16 node(s) at the same point" in n for n in notes), notes
    spec["reference"]["refine"] = 0
    u = solve_fem(fpm.load_problem(spec)).displacements
    assert np.all(np.isfinite(u)) and np.abs(u).max() > 0


def test_pieces_the_lattice_joins_without_shared_faces_are_refused_naming_one():
    """A block against another whose nodes do not meet its own (no shared face): their lattice
    cells are one solid, but the reference kept them as two pieces, the FEM holding only the
    one the support touches."""
    mesh = joined(block([0, 0, 0], 3, 0.03), block([0.03, 0, 0], 2, 0.025))
    message = (
        r"the mesh's tetrahedra are 2 pieces not joined through shared faces, and the "
        r"lattice's cells join 2 of them into one solid: the piece of tetrahedron 162 \(48 "
        r"tetrahedra, around \[0\.0425, 0\.0125, 0\.0125\] m\) touches or overlaps the rest"
    )
    with pytest.raises(MeshError, match=message):
        spec_from_mesh(mesh, **GIVEN)
