"""Bad specs and bad meshes on every entry point: in process (``fpm.load_problem``,
``fpm.calibrate``), the command line (``fpmcal`` through its ``main``), and the SDK against a test
service (REST itself: tests/service/test_fuzz.py and tests/core/test_fuzz_meshes.py, same
generators).

The rule, everywhere: a bad input is a named error (a field error, or one of the package's
own errors, raised by its own code with its reason), never an internal error: in process no
exception from NumPy, SciPy or Python itself escapes; ``fpmcal`` prints one line (one per
field error) and exits 1 or 2, never "internal error"; the SDK gets a 422 naming the field or a
calibration that failed with its reason. ``FUZZ_ENTRY_EXAMPLES`` (environment) scales the
example counts (default 1: 60 specs in process, 60 on the CLI, 80 meshes on the CLI, 30 specs
through the SDK).
"""

from __future__ import annotations

import json
import os
import tempfile
import traceback
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from hypothesis import HealthCheck, event, given
from hypothesis import settings as hyp_settings
from pydantic import ValidationError
from test_fuzz import FAILURE_REASONS, specs
from test_fuzz_meshes import Case, cases

import fpm
from client import ApiError
from fpmcal.cli import main

SCALE = float(os.environ.get("FUZZ_ENTRY_EXAMPLES", "1"))
PACKAGE = Path(fpm.__file__).resolve().parent


def examples(n: int) -> int:
    return max(1, round(n * SCALE))


def settings(n: int, derandomize: bool = False) -> Any:
    """``n`` examples (times the scale); drawn afresh each run unless ``derandomize`` (the
    derandomised draw of :func:`test_fuzz.specs` stays near its simplest specs, which the
    schema refuses)."""
    return hyp_settings(
        max_examples=examples(n),
        deadline=None,
        database=None,
        derandomize=derandomize,
        suppress_health_check=list(HealthCheck),
    )


def raised_by_the_package(error: BaseException) -> bool:
    """True when ``error`` was raised by a frame of the ``fpm`` package (its own message), not
    by NumPy, SciPy or Python under it."""
    frames = traceback.extract_tb(error.__traceback__)
    return bool(frames) and Path(frames[-1].filename).resolve().is_relative_to(PACKAGE)


def assert_named(error: BaseException) -> str:
    """A named error: a field error, or an error of the package's own (its class, or a
    ValueError / RuntimeError it raised itself with the reason). Returns its kind."""
    if isinstance(error, ValidationError):
        errors = error.errors()
        assert errors and all(e["loc"] and e["msg"] for e in errors), errors
        return "ValidationError"
    ours = type(error).__module__.startswith("fpm.")
    assert ours or (
        isinstance(error, ValueError | RuntimeError) and raised_by_the_package(error)
    ), "".join(traceback.format_exception(error))
    assert str(error) and "\n" not in str(error).strip(), repr(error)
    return type(error).__name__


def small(spec: dict[str, Any]) -> dict[str, Any]:
    """The drawn spec with one chain (the property is about errors, not about the fit)."""
    out = json.loads(json.dumps(spec))
    if isinstance(out.get("annealing"), dict):
        out["annealing"]["chains"] = 1
    return out


# --- in process -------------------------------------------------------------------------------


@settings(60)
@given(spec=specs())
def test_in_process_a_bad_spec_is_a_named_error(spec: dict[str, Any]):
    try:
        problem = fpm.load_problem(small(spec))
    except Exception as error:  # noqa: BLE001 - the property is what escapes
        event(f"load_problem: {assert_named(error)}")
        return
    try:
        fpm.calibrate(problem, threads=1)
    except Exception as error:  # noqa: BLE001
        event(f"calibrate: {assert_named(error)}")
        return
    event("calibrate: calibrated")


# --- the command line ---------------------------------------------------------------------------


def fpmcal(argv: list[str], capsys: pytest.CaptureFixture[str], what: str) -> tuple[int, str]:
    """``fpmcal argv`` through main: exit 0, or 1 / 2 with one line per error and never an
    internal error or a traceback. Returns (status, stdout)."""
    status = main(argv)
    captured = capsys.readouterr()
    assert "internal error" not in captured.err and "Traceback" not in captured.err, captured.err
    assert status in (0, 1, 2), (status, captured.err)
    if status:
        errors = [
            line
            for line in captured.err.splitlines()
            if not line.startswith(("note:", "warning:", "  ", "FEM reference:")) and ": " in line
        ]
        assert errors, captured.err
        event(f"{what}: exit {status}")
    else:
        event(f"{what}: done")
    return status, captured.out


@settings(60)
@given(spec=specs())
def test_fpmcal_calibrate_of_a_bad_spec_is_one_named_line(
    spec: dict[str, Any], capsys: pytest.CaptureFixture[str]
):
    with tempfile.TemporaryDirectory() as scratch:
        path = Path(scratch) / "spec.json"
        path.write_text(json.dumps(small(spec)))
        status, out = fpmcal(["calibrate", str(path), "-q", "--json"], capsys, "fpmcal calibrate")
        if status == 0:
            assert json.loads(out)["k"] > 0


def argv_of(case: Case, mesh: Path) -> list[str]:
    """``fpmcal spec from-mesh`` arguments for the drawn case (its ``spec_from_mesh`` options)."""
    o = case.options
    argv = ["spec", "from-mesh", str(mesh), "--E", str(o["youngs_modulus"])]
    argv += ["--nu", str(o["poisson_ratio"]), "--density", str(o["density"])]
    argv += ["--lattice", o["lattice"]]
    if "nodes" in o:
        argv += ["--nodes", str(o["nodes"])]
    else:
        argv += ["--spacing", repr(o["spacing"])]
    if "scale" in o:
        argv += ["--scale", repr(o["scale"])]
    for selector in o["fix"]:
        argv += ["--fix", selector]
    for force in o["forces"]:
        argv += ["--force", force]
    return argv


@settings(80, derandomize=True)
@given(case=cases())
def test_fpmcal_spec_from_mesh_of_a_bad_mesh_is_one_named_line(
    case: Case, capsys: pytest.CaptureFixture[str]
):
    """The drawn mesh written as VTU (non-finite points and out-of-range cells as they are),
    made a spec of; about every fourth spec made then has its FEM reference solved on one
    level (``fpmcal fem``, ``reference.refine`` 0)."""
    with tempfile.TemporaryDirectory() as scratch:
        mesh, spec = Path(scratch) / "organ.vtu", Path(scratch) / "organ.json"
        try:
            case.mesh().write(mesh)
        except Exception:  # noqa: BLE001 - meshio cannot even write it: nothing to read
            event("the mesh cannot be written")
            return
        status, _ = fpmcal([*argv_of(case, mesh), "-o", str(spec)], capsys, "from-mesh")
        if status == 0 and int(np.sum(case.tets)) % 4 == 0:
            made = json.loads(spec.read_text())
            made.setdefault("reference", {})["refine"] = 0  # one level: seconds, not minutes
            spec.write_text(json.dumps(made))
            fpmcal(["fem", str(spec), "-o", str(Path(scratch) / "fem.json")], capsys, "fem")


# --- the SDK against a test service ---------------------------------------------------------------


@pytest.mark.redis
def test_the_sdk_gets_a_field_error_or_a_reason(sdk, redis, run_workers):
    @settings(30)
    @given(spec=specs())
    def check(spec: dict[str, Any]) -> None:
        redis.flushdb()
        try:
            submitted = sdk.calibrate(small(spec))
        except ApiError as e:
            assert e.status == 422 and e.errors, e
            assert all(err["field"] and err["message"] for err in e.errors), e.errors
            event("SDK: 422 naming the field")
            return
        run_workers()
        done = sdk.get(submitted["id"])
        assert done["status"] in ("succeeded", "failed"), done
        if done["status"] == "failed":
            assert done["error"].startswith(FAILURE_REASONS), done["error"]
            assert "Traceback" not in done["error"] and "internal" not in done["error"]
        event(f"SDK: {done['status']}")

    check()
