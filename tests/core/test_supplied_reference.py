"""A reference the user brings (``reference.displacements``): it takes the FEM's place in the
fit and in every figure, no FEM is solved or queued, and a bad field is refused naming it."""

from __future__ import annotations

import copy
import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from pydantic import ValidationError

import fpm
from fpm.fem.reference import reference_label
from fpm.fitting.calibration import calibrate
from store import keys
from store.hashing import fem_hash

ROOT = Path(__file__).resolve().parents[2]
SMALL: dict[str, Any] = json.loads((ROOT / "examples" / "small-box.json").read_text())


def small(**reference: Any) -> dict[str, Any]:
    spec = copy.deepcopy(SMALL)
    if reference:
        spec["reference"] = reference
    return spec


def fem_field() -> np.ndarray:
    """(L, N, 3) the small box's FEM displacements, m."""
    return fpm.solve_fem(fpm.load_problem(small())).displacements


def error_locs(spec: dict[str, Any]) -> list[tuple]:
    with pytest.raises(ValidationError) as caught:
        fpm.load_problem(spec)
    return [tuple(e["loc"]) for e in caught.value.errors()]


def test_a_supplied_field_of_the_wrong_shape_or_not_finite_is_refused_naming_it():
    u = fem_field().tolist()
    assert error_locs(small(displacements=u[:1])) == [("reference", "displacements")]
    assert error_locs(small(displacements=[u[0], u[1][:-1]])) == [("reference", "displacements", 1)]
    bad = copy.deepcopy(u)
    bad[0][5][2] = float("nan")
    assert error_locs(small(displacements=bad)) == [("reference", "displacements", 0, 5, 2)]
    bad[0][5][2] = float("inf")
    assert error_locs(small(displacements=bad)) == [("reference", "displacements", 0, 5, 2)]
    bad = copy.deepcopy(u)
    bad[1][3] = [0.0, 0.0]
    locs = error_locs(small(displacements=bad))
    assert locs and all(loc[:4] == ("reference", "displacements", 1, 3) for loc in locs)


def test_the_supplied_field_is_the_reference_and_names_it():
    u = fem_field()
    problem = fpm.load_problem(small(displacements=(2 * u).tolist()))
    reference = fpm.fem.reference.reference_for(problem)
    assert reference.model == "supplied" and reference.method == "supplied"
    assert np.array_equal(reference.displacements, 2 * u)
    assert reference_label(problem.spec) == "supplied"
    assert reference_label(fpm.load_problem(small()).spec) == "fem-linear-selective"
    assert reference_label(fpm.load_problem(small(integration="full")).spec) == "fem-linear-full"
    nh = small()
    nh["material"]["model"] = "neo-hookean"
    assert reference_label(fpm.load_problem(nh).spec) == "fem-neo-hookean-selective"
    # a supplied reference is its own stored reference
    dumps = [
        fpm.load_problem(s).spec.model_dump(mode="json")
        for s in (small(), small(displacements=u.tolist()), small(displacements=(2 * u).tolist()))
    ]
    assert len({fem_hash(d) for d in dumps}) == 3


def test_a_field_125_times_the_fems_gives_stiffness_080_times():
    """Linear lattice and linear reference: displacements 1.25x larger want a k 1/1.25 = 0.8x
    (up to the lattice's geometric nonlinearity at these loads)."""
    u = fem_field()
    fitted = calibrate(fpm.load_problem(small()), threads=1)
    supplied = calibrate(fpm.load_problem(small(displacements=(1.25 * u).tolist())), threads=1)
    assert (
        fitted.reference.label == "fem-linear-selective" and supplied.reference.label == "supplied"
    )
    assert supplied.parameters.k / fitted.parameters.k == pytest.approx(0.80, abs=0.02)


@pytest.mark.redis
def test_rest_refuses_a_bad_field_with_422_and_queues_nothing(api, redis):
    u = fem_field().tolist()
    spec = small(displacements=u[:1])
    response = api.post("/v1/calibrations", json=spec)
    assert response.status_code == 422, response.text
    body = response.json()
    assert "reference.displacements" in [e["field"] for e in body["errors"]]
    bad = copy.deepcopy(u)
    bad[0][0][0] = float("nan")
    text = json.dumps(small(displacements=bad))  # NaN as JSON5-ish literal, as Python writes it
    response = api.post(
        "/v1/calibrations", content=text, headers={"content-type": "application/json"}
    )
    assert response.status_code == 422, response.text
    fields = [e["field"] for e in response.json()["errors"]]
    assert any(f.startswith("reference.displacements") for f in fields), fields
    assert redis.dbsize() == 0


@pytest.mark.redis
def test_the_service_runs_no_fem_job_for_a_supplied_reference(api, redis, run_workers):
    u = fem_field()
    spec = small(displacements=(1.25 * u).tolist())
    submitted = api.post("/v1/calibrations", json=spec)
    assert submitted.status_code == 202, submitted.text
    dumped = fpm.load_problem(spec).spec.model_dump(mode="json")
    digest = fem_hash(dumped)
    assert not redis.exists(f"rq:job:{keys.fem_job_id(digest)}")  # no FEM job queued
    assert redis.exists(keys.fem_reference(digest))  # the supplied field, stored at once
    run_workers()
    done = api.get(submitted.headers["location"]).json()
    assert done["status"] == "succeeded", done
    assert done["result"]["reference"] == "supplied"


def test_the_cli_reads_a_supplied_field_from_json_or_vtu(tmp_path, capsys):
    import meshio

    from fpmcal.cli import main

    problem = fpm.load_problem(small())
    u = 1.25 * fem_field()
    spec = tmp_path / "spec.json"
    spec.write_text(json.dumps(small()))
    as_json = tmp_path / "field.json"
    as_json.write_text(json.dumps({"displacements": u.tolist()}))
    as_vtu = tmp_path / "field.vtu"
    point_data = {f"displacement_{j + 1}": u[j] for j in range(len(u))}
    meshio.write(as_vtu, meshio.Mesh(problem.nodes, [("vertex", [[0]])], point_data=point_data))
    ks = []
    for path in (as_json, as_vtu):
        capsys.readouterr()
        assert main(["calibrate", str(spec), "--reference", str(path), "--json", "-q"]) == 0
        printed = capsys.readouterr()
        result = json.loads(printed.out.strip().splitlines()[-1])  # stdout: the JSON only
        assert len(printed.out.strip().splitlines()) == 1
        assert result["reference"] == "supplied"
        assert f"{result['k']:.3f} N/m" in printed.err  # the table, for the person, on stderr
        ks.append(result["k"])
    assert ks[0] == pytest.approx(ks[1], rel=1e-9)
    short = tmp_path / "short.json"
    short.write_text(json.dumps(u[:, :-1].tolist()))
    assert main(["calibrate", str(spec), "--reference", str(short), "-q"]) == 2
    assert "reference.displacements" in capsys.readouterr().err
    missing = tmp_path / "missing.vtu"
    meshio.write(missing, meshio.Mesh(problem.nodes, [("vertex", [[0]])]))
    assert main(["calibrate", str(spec), "--reference", str(missing), "-q"]) == 2
    assert "displacement_1" in capsys.readouterr().err
