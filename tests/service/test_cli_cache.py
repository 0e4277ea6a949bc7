"""`fpmcal calibrate`'s work kept beside the spec (fpmcal/cache.py): the FEM reference and stage
1's chains stored before the damping stage starts, reused on a rerun (as stored, or scaled
where only the forces scale), kept when the damping stage fails; and its damping stage's
progress, a line per d tried."""

from __future__ import annotations

import copy
import json
import re
from pathlib import Path
from typing import Any

import meshio
import numpy as np
import pytest

import fpm
from fpmcal.cache import Cache, cache_dir, scaled_factors
from fpmcal.cli import main
from store.hashing import fem_spec

ROOT = Path(__file__).resolve().parents[2]
SMALL: dict[str, Any] = json.loads((ROOT / "examples" / "small-box.json").read_text())


def write(tmp_path: Path, spec: dict[str, Any], name: str = "box.json") -> Path:
    path = tmp_path / name
    path.write_text(json.dumps(spec))
    return path


def calibrate(path: Path, capsys: pytest.CaptureFixture[str], *extra: str) -> tuple[int, Any, str]:
    """(exit status, the result's JSON or None, stderr) of ``fpmcal calibrate --json -q``."""
    status = main(["calibrate", str(path), "--json", "-q", *extra])
    out = capsys.readouterr()
    return status, json.loads(out.out) if status == 0 else None, out.err


def scaled(spec: dict[str, Any], factors: list[float]) -> dict[str, Any]:
    out = copy.deepcopy(spec)
    for case, factor in zip(out["load_cases"], factors, strict=True):
        for force in case["forces"]:
            force["vector"] = [factor * v for v in force["vector"]]
    return out


def dumped(spec: dict[str, Any]) -> dict[str, Any]:
    return fem_spec(fpm.load_problem(spec).spec.model_dump(mode="json"))


def test_scaled_factors_only_where_every_case_only_scales():
    base = dumped(SMALL)
    assert scaled_factors(dumped(scaled(SMALL, [0.5, -2.0])), base) == [0.5, -2.0]
    assert scaled_factors(base, base) == [1.0, 1.0]
    moved = copy.deepcopy(SMALL)
    moved["load_cases"][1]["forces"][0]["at"] = [0.02, 0.01, 0.03]  # another node
    assert scaled_factors(dumped(moved), base) is None
    turned = copy.deepcopy(SMALL)
    turned["load_cases"][0]["forces"][0]["vector"] = [0.01, 0, 0.05]  # another direction
    assert scaled_factors(dumped(turned), base) is None
    softer = copy.deepcopy(SMALL)
    softer["material"]["youngs_modulus"] = 5000.0
    assert scaled_factors(dumped(softer), base) is None
    heavy = copy.deepcopy(SMALL)
    heavy["fpm"]["gravity"] = [0, 0, -9.81]  # the weight does not scale with the forces
    assert scaled_factors(dumped(scaled(heavy, [0.5, 0.5])), dumped(heavy)) is None


def test_a_rerun_reuses_the_reference_and_the_chains_and_says_so(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
):
    path = write(tmp_path, SMALL)
    status, first, err = calibrate(path, capsys)
    assert status == 0 and "reused" not in err
    assert (cache_dir(path) / "reference").is_dir() and (cache_dir(path) / "chains").is_dir()
    status, again, err = calibrate(path, capsys)
    assert status == 0
    assert "FEM reference: reused from" in err and "as stored, saving" in err
    assert "stage 1's 2 chain(s) reused" in err
    for name in ("k", "d", "depth", "relative_discrepancy", "settle_steps"):
        assert again[name] == first[name], name
    # a damping setting changed: the reference and the chains still hold, d is found anew
    other = copy.deepcopy(SMALL)
    other["fpm"]["max_steps"] = "auto"
    status, auto, err = calibrate(write(tmp_path, other), capsys)
    assert status == 0 and "chain(s) reused" in err and auto["k"] == first["k"]
    # --no-cache neither reads nor writes
    fresh = write(tmp_path, SMALL, "fresh.json")
    status, _, err = calibrate(fresh, capsys, "--no-cache")
    assert status == 0 and "reused" not in err and not cache_dir(fresh).exists()


def test_a_smaller_press_reuses_the_reference_scaled_as_a_new_solve_gives_it(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
):
    path = write(tmp_path, SMALL)
    assert calibrate(path, capsys)[0] == 0
    smaller = scaled(SMALL, [0.5, 0.25])
    status, result, err = calibrate(write(tmp_path, smaller), capsys)
    assert status == 0
    assert "scaled per case by 0.5, 0.25" in err
    assert "chain(s) reused" not in err  # another reference: the stiffness is fitted anew
    problem = fpm.load_problem(smaller)
    reused = Cache(cache_dir(path)).reference(problem.spec.model_dump(mode="json"))
    assert reused is not None and reused.factors == [0.5, 0.25]
    solved = fpm.solve_fem(problem).displacements
    scale = np.abs(solved).max()
    np.testing.assert_allclose(reused.reference.displacements, solved, atol=1e-9 * scale, rtol=0)
    assert reused.reference.load_cases == [c.name for c in problem.load_cases]
    assert result["relative_discrepancy"]  # and the calibration ran on it


def test_a_failed_damping_stage_keeps_the_reference_and_the_chains(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
):
    hopeless = copy.deepcopy(SMALL)
    hopeless["fpm"]["max_steps"] = 5  # no d settles in 5 steps
    status, _, err = calibrate(write(tmp_path, hopeless), capsys)
    assert status == 1 and "max_steps=5" in err
    status, result, err = calibrate(write(tmp_path, SMALL), capsys)
    assert status == 0
    assert "FEM reference: reused" in err and "chain(s) reused" in err
    status, fresh, _ = calibrate(write(tmp_path, SMALL, "fresh.json"), capsys, "--no-cache")
    assert (result["k"], result["d"]) == (fresh["k"], fresh["d"])


def test_the_vtu_export_takes_the_stored_reference_with_its_validation_cases(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
):
    spec = copy.deepcopy(SMALL)
    spec["validation_cases"] = [
        {"name": "side", "forces": [{"at": [0.03, 0.01, 0.02], "vector": [-0.02, 0, 0]}]}
    ]
    path = write(tmp_path, spec)
    status, result, _ = calibrate(path, capsys)
    assert status == 0
    params = tmp_path / "result.json"
    params.write_text(json.dumps(result))
    out = tmp_path / "box.vtu"
    assert main(["export", str(path), str(params), "--format", "vtu", "-o", str(out)]) == 0
    assert "FEM reference: reused from" in capsys.readouterr().err
    data = meshio.read(out).point_data
    fem = Cache(cache_dir(path)).reference(fpm.load_problem(spec).spec.model_dump(mode="json"))
    assert fem is not None
    np.testing.assert_array_equal(
        data["validation_fem_displacement_1"], fem.reference.displacements[2]
    )
    assert np.abs(data["validation_fpm_displacement_1"]).max() > 0


def test_the_damping_stage_shows_each_d_it_tries(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
):
    assert main(["calibrate", str(write(tmp_path, SMALL)), "--json", "--no-cache"]) == 0
    err = capsys.readouterr().err.splitlines()
    tried = [line for line in err if re.fullmatch(r"    d = \S+ N s/m: .*", line)]
    assert tried and err.index("  damping ...") < err.index(tried[0])
    assert any(re.search(r": [\d,]+ steps$", line) for line in tried)
