"""Spring families and per-spring stiffness (fpm.model.stiffness)."""

from __future__ import annotations

import numpy as np
import pytest

from fpm import load_problem, simulate
from fpm.model.stiffness import family_names, spring_stiffness, stiffness_dict


def _box(connectivity: str, **fpm: object) -> dict:
    return {
        "material": {"youngs_modulus": 1e4, "poisson_ratio": 0.3, "density": 1000},
        "geometry": {"type": "box", "size": [0.03, 0.02, 0.02], "nodes": [4, 3, 3],
                     "connectivity": connectivity},
        "fixed": [{"face": "z-"}],
        "load_cases": [{"forces": [{"node": 35, "vector": [0.01, 0, 0.02]}]}],
        "fpm": fpm,
    }  # fmt: skip


@pytest.mark.parametrize("connectivity", ["axis", "axis+face", "full"])
def test_families_are_edge_face_body_by_length(connectivity: str) -> None:
    """On a cubic lattice a family is told by its rest length: h, h sqrt 2, h sqrt 3."""
    spec = _box(connectivity)
    spec["geometry"]["size"] = [0.03, 0.02, 0.02]
    p = load_problem(spec)
    ratio = p.rest_lengths / p.h
    expected = np.sqrt(p.solid.families.astype(float) + 1)
    assert np.allclose(ratio, expected)
    assert set(np.unique(p.solid.families)) == set(
        range(len(family_names(load_problem(_box(connectivity, stiffness="families")))))
    )


def test_voxels_and_box_give_the_same_families() -> None:
    """The hexahedron path (voxels) and the index path (box) label every spring alike."""
    box = load_problem(_box("full"))
    vox = load_problem({**_box("full"), "geometry": {
        "type": "voxels", "occupancy": np.ones((3, 2, 2), bool).tolist(),
        "spacing": [0.01, 0.01, 0.01], "connectivity": "full"}})  # fmt: skip

    def labelled(p):  # {(node a, node b) as coordinates: family}
        x = np.round(p.nodes / 0.01).astype(int)
        return {
            tuple(sorted((tuple(x[a]), tuple(x[b])))): int(f)
            for (a, b), f in zip(p.solid.springs, p.solid.families, strict=True)
        }

    assert labelled(box) == labelled(vox)


def test_spring_stiffness_single_families_and_scale() -> None:
    single = load_problem(_box("full", stiffness="single", stiffness_scale=(1, 1, 2)))
    fam = load_problem(_box("full", stiffness="families"))
    assert family_names(single) == ("k",)
    assert family_names(fam) == ("axis", "face", "body")
    k = spring_stiffness(fam, [30.0, 20.0, 10.0])
    assert np.array_equal(k, np.array([30.0, 20.0, 10.0])[fam.solid.families])
    # the per-axis scale: a spring along z gets 2k, one in the x-y plane k
    ks = spring_stiffness(single, 5.0)
    e = single.nodes[single.solid.springs[:, 1]] - single.nodes[single.solid.springs[:, 0]]
    e /= single.rest_lengths[:, None]
    assert np.allclose(ks, 5.0 * (1 + e[:, 2] ** 2))
    assert stiffness_dict(single, [5.0]) == {"axis": 5.0, "face": 5.0, "body": 5.0}
    with pytest.raises(ValueError, match="give 3 values"):
        spring_stiffness(fam, [1.0, 2.0])


def test_equal_family_stiffness_is_the_single_k_run() -> None:
    """Families all at k reproduce the single-k run (to round-off: k is applied in another
    order of operations)."""
    p = load_problem(_box("full", stiffness="families"))
    one = simulate(p, k=40.0, d=0.05, dt=1e-4, max_steps=300)
    three = simulate(p, k=[40.0, 40.0, 40.0], d=0.05, dt=1e-4, max_steps=300)
    assert not one.diverged
    assert np.allclose(one.displacements, three.displacements, rtol=1e-12, atol=1e-15)
    # and a softer body-diagonal family moves the loaded node further
    soft = simulate(p, k=[40.0, 40.0, 4.0], d=0.05, dt=1e-4, max_steps=300)
    assert np.linalg.norm(soft.displacements[35]) > np.linalg.norm(one.displacements[35])
