"""`fpmcal` errors: one clear line each on stderr (one per field error for a bad spec), never a
traceback; exit status 2 for a bad spec or spec file, 1 for a calibration that cannot proceed."""

from __future__ import annotations

import copy
import json
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest

from fpmcal.cli import error_report, main

ROOT = Path(__file__).resolve().parents[2]
SMALL: dict[str, Any] = json.loads((ROOT / "examples" / "small-box.json").read_text())


def fpmcal(*args: str, cwd: Path) -> subprocess.CompletedProcess[str]:
    """The installed script if there is one, else ``python -m fpmcal.cli``."""
    script = Path(sys.executable).with_name("fpmcal")
    command = [str(script)] if script.exists() else [sys.executable, "-m", "fpmcal.cli"]
    return subprocess.run([*command, *args], capture_output=True, text=True, cwd=cwd, timeout=120)


def write(tmp_path: Path, name: str, spec: dict[str, Any]) -> Path:
    path = tmp_path / name
    path.write_text(json.dumps(spec))
    return path


def small(**changes: Any) -> dict[str, Any]:
    """small-box.json with ``section={field: value}`` changes."""
    spec = copy.deepcopy(SMALL)
    for section, fields in changes.items():
        spec[section].update(fields)
    return spec


def test_a_bad_spec_is_one_line_naming_the_field(tmp_path: Path):
    write(tmp_path, "bad.json", small(material={"poisson_ratio": 0.5}))
    run = fpmcal("calibrate", "bad.json", cwd=tmp_path)
    assert run.returncode == 2
    assert run.stderr.splitlines() == [
        "bad.json: material.poisson_ratio: Input should be less than 0.5"
    ]
    assert run.stdout == ""


def test_not_json_says_so(tmp_path: Path):
    (tmp_path / "lobe.vtu").write_bytes(b"# vtk DataFile Version 3.0\nlobe\nASCII\n")
    run = fpmcal("calibrate", "lobe.vtu", cwd=tmp_path)
    assert run.returncode == 2
    assert run.stderr.splitlines() == [
        "SPEC must be a JSON problem spec (got lobe.vtu, not JSON: Expecting value: line 1 "
        "column 1 (char 0)); lobe.vtu looks like a mesh: make a spec of it first with fpmcal "
        "spec from-mesh lobe.vtu --spacing H --fix face:z- --force 'nearest:X,Y,Z:FX,FY,FZ' "
        "--E PA --nu NU"
    ]


def test_a_missing_file_says_so(tmp_path: Path):
    run = fpmcal("fem", "missing.json", cwd=tmp_path)
    assert run.returncode == 2
    assert len(run.stderr.splitlines()) == 1
    assert run.stderr.startswith("SPEC missing.json: no such file")
    assert "Traceback" not in run.stderr


# In-process from here on (main catches everything a subprocess would show).


def test_every_field_error_is_a_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]):
    spec = small(material={"density": -1.0})
    spec["load_cases"][0]["forces"][0] = {"node": 3, "face": "z+", "vector": [0, 0, 1]}
    del spec["fixed"]
    path = write(tmp_path, "bad.json", spec)
    assert main(["fem", str(path)]) == 2
    lines = capsys.readouterr().err.splitlines()
    assert lines == [
        f"{path}: material.density: Input should be greater than 0",
        f"{path}: fixed: Field required",
        f"{path}: load_cases.0.forces.0: give exactly one of face, node, at, nearest, box, point "
        "(got face, node)",
    ]


@pytest.mark.parametrize(
    ("content", "reason"),
    [(b"\x89PNG\r\n\x1a\n\x00\xff", "not UTF-8 text"), (b'{"name": ', "Expecting value")],
    ids=["binary", "truncated"],
)
def test_other_files_that_are_not_json(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], content: bytes, reason: str
):
    path = tmp_path / "spec.json"
    path.write_bytes(content)
    assert main(["calibrate", str(path)]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"SPEC must be a JSON problem spec (got {path}, not JSON: {reason}")
    assert len(err.splitlines()) == 1


def test_a_directory_is_not_a_spec(tmp_path: Path, capsys: pytest.CaptureFixture[str]):
    assert main(["fem", str(tmp_path)]) == 2
    assert (
        capsys.readouterr().err
        == f"SPEC {tmp_path} is a directory: give a JSON problem spec file\n"
    )


def test_wrong_units_stop_a_calibration(tmp_path: Path, capsys: pytest.CaptureFixture[str]):
    """E = 5 Pa (meant 5 kPa): refused before any annealing, exit 1, one line."""
    path = write(tmp_path, "units.json", small(material={"youngs_modulus": 5.0}))
    assert main(["calibrate", str(path), "-q"]) == 1
    captured = capsys.readouterr()
    error = captured.err.splitlines()[-1]
    assert error.startswith("error: load case '0.1 N' (and 1 more case): the linear FEM")
    assert "E is in Pa (5 kPa = 5000), lengths in m, forces in N" in error
    assert "E = 5 Pa is softer than any tissue" in error
    assert "annealing" not in captured.err and captured.out == ""


def test_a_validation_case_that_moves_far_stops_a_calibration_naming_it(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
):
    """The units right, a validation case of 20 N on the 3 cm box at 10 kPa (it moves a node
    further than the box is thick): one line naming it, exit 1; it was an internal error
    (IndexError) where the check indexed the load cases with the validation cases' places."""
    spec = small()
    spec["validation_cases"] = [
        {"name": "hard press", "forces": [{"at": [0.01, 0.01, 0.03], "vector": [0, 0, 20.0]}]}
    ]
    path = write(tmp_path, "far.json", spec)
    assert main(["calibrate", str(path), "-q"]) == 1
    captured = capsys.readouterr()
    error = captured.err.splitlines()[-1]
    assert error.startswith("error: validation case 'hard press': the linear FEM reference")
    assert error.endswith("lower the forces (this spec: E = 10000 Pa, largest nodal force 20 N, "
                          "solid 0.03 x 0.03 x 0.03 m)")  # fmt: skip
    assert "internal error" not in captured.err and "units" not in captured.err


def test_an_annealing_start_that_fails_is_explained(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
):
    """The paper's joint (k, d) annealing with a 50 ms step: every candidate diverges."""
    spec = small(fpm={"dt": 0.05}, annealing={"method": "paper"})
    path = write(tmp_path, "fast.json", spec)
    assert main(["calibrate", str(path), "-q"]) == 1
    error = capsys.readouterr().err.splitlines()[-1]
    assert error.startswith("error: no acceptable starting point in 50 random tries: ")
    assert "the lattice's stability estimate suggests dt <= " in error
    assert "(the spec has 0.05 s)" in error


def test_notes_and_warnings_go_to_stderr(tmp_path: Path, capsys: pytest.CaptureFixture[str]):
    spec = small()
    spec["load_cases"][0]["forces"][0] = {"nearest": [0.011, 0.009, 0.031], "vector": [0, 0, 0.05]}
    path = write(tmp_path, "nearest.json", spec)
    assert main(["simulate", str(path), "--k", "38.8", "--d", "0.1", "--dt", "0.003"]) == 0
    captured = capsys.readouterr()
    json.loads(captured.out)  # stdout: the result only
    err = captured.err.splitlines()
    assert err[0] == (
        "note: load_cases.0.forces.0.nearest: node 53 at [0.01, 0.01, 0.03] is 1.73 mm from "
        "the point"
    )
    assert err[1].startswith("warning: dt = 0.003 s: the lattice's stability estimate for k = ")
    assert any(line.startswith("warning: load case 0: diverged at step") for line in err)


def test_anything_else_is_one_line_too():
    lines, status = error_report(KeyError("boom"), "spec.json")
    assert status == 1 and len(lines) == 1
    assert lines[0].startswith("internal error (KeyError): 'boom'; please report it")
    lines, status = error_report(RuntimeError("a\nb"), "spec.json")  # not the package's own
    assert status == 1 and lines == ["internal error (RuntimeError): a b; please report it with "
                                     "the spec and the command"]  # fmt: skip
