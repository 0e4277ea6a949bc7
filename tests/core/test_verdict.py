"""The load compliance ratio and the verdict on a fit (fpm.fitting.cost, fpm.fitting.verdict)."""

from __future__ import annotations

import copy
import json
from pathlib import Path

import numpy as np
import pytest

import fpm
from bench.bench_volume import cube_spec
from fpm.fitting.calibration import calibrate
from fpm.fitting.cost import compliance_ratio, discrepancies
from fpm.fitting.verdict import CUBE_FLOORS, SETTINGS, judge

ROOT = Path(__file__).resolve().parents[2]
SMALL_BOX = json.loads((ROOT / "examples" / "small-box.json").read_text())
K_TRUE = 50.0


def small_box(**edits) -> dict:
    """The small box example (one k, 4 x 4 x 4 nodes, nu 0.45), ``edits`` applied by section."""
    spec = copy.deepcopy(SMALL_BOX)
    for section, values in edits.items():
        spec[section].update(values)
    return spec


def scaled(spec: dict, factor: float) -> dict:
    """``spec`` with every force times ``factor``."""
    spec = copy.deepcopy(spec)
    for case in spec["load_cases"]:
        for force in case["forces"]:
            force["vector"] = [factor * v for v in force["vector"]]
    return spec


def test_compliance_ratio_is_the_work_of_the_load_model_over_reference():
    """By hand: forces (0, 0, 1) N at node 1 and (1, 0, 0) N at node 3; the model moves them
    2 and 1 mm along their forces, the reference 1 and 1 mm (node 3 also 5 m across its
    force, which does no work): (2 + 1) / (1 + 1) = 1.5."""
    nodes = np.array([1, 3])
    forces = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0]])
    model = np.zeros((5, 3))
    truth = np.zeros((5, 3))
    model[1], model[3] = [0, 0, 2e-3], [1e-3, 0, 0]
    truth[1], truth[3] = [0, 0, 1e-3], [1e-3, 5.0, 0]
    model[0] = truth[0] = [7.0, 7.0, 7.0]  # an unloaded node counts for nothing
    assert compliance_ratio(nodes, forces, model, truth) == pytest.approx(1.5, rel=1e-12)
    # twice as stiff: half the work
    assert compliance_ratio(nodes, forces, model / 3, truth) == pytest.approx(0.5, rel=1e-12)
    # forces across the reference's displacement do no work: no ratio
    assert compliance_ratio(nodes, forces, model, np.zeros((5, 3))) is None


def test_compliance_ratio_is_one_at_the_reference_and_follows_a_uniform_softening():
    problem = fpm.load_problem(SMALL_BOX)
    rng = np.random.default_rng(1)
    ref = rng.normal(size=(2, problem.n_nodes, 3)) * 1e-3
    for j, case in enumerate(problem.load_cases):  # the loads do positive work on it
        ref[j, case.nodes] = 1e-3 * case.forces / np.linalg.norm(case.forces)
    assert discrepancies(problem, ref, ref).compliance == [1.0, 1.0]
    assert discrepancies(problem, 1.5 * ref, ref).compliance == pytest.approx([1.5, 1.5])


@pytest.fixture(scope="module")
def own_reference():
    """The small box against its own FPM at K_TRUE: the fit recovers it exactly."""
    problem = fpm.load_problem(SMALL_BOX)
    ref = np.stack(
        [
            fpm.simulate(problem, k=K_TRUE, d=0.2, load_case=j, max_steps=50000,
                         settle_tolerance=1e-10).displacements
            for j in range(len(problem.load_cases))
        ]
    )  # fmt: skip
    return problem, ref


def test_a_fit_that_reproduces_its_reference_feels_its_stiffness_and_is_good(own_reference):
    problem, ref = own_reference
    result = calibrate(problem, reference=ref)
    assert result.parameters.k == pytest.approx(K_TRUE, rel=1e-3)
    assert result.fit.compliance_ratio == pytest.approx([1.0, 1.0], abs=2e-3)
    assert result.fit.verdict is not None
    assert result.fit.verdict.grade == "good" and result.fit.verdict.causes == []
    assert result.fit.verdict.basis == "fitted"  # no validation cases, and it says so
    assert "no validation cases" in result.fit.verdict.summary


def test_the_compliance_ratio_does_not_change_when_the_forces_double_in_a_linear_regime():
    """At a hundredth of the example's forces (linear regime) the fitted one k feels the same
    under twice those forces; at the example's own forces already less so."""
    small = scaled(SMALL_BOX, 0.01)
    one, two = (calibrate(fpm.load_problem(s)) for s in (small, scaled(small, 2.0)))
    assert two.fit.compliance_ratio == pytest.approx(one.fit.compliance_ratio, rel=2e-3)
    assert two.parameters.k == pytest.approx(one.parameters.k, rel=2e-3)
    # the springs are not linear: at the example's forces, the same k feels stiffer
    big = calibrate(fpm.load_problem(SMALL_BOX))
    assert big.fit.compliance_ratio[1] < one.fit.compliance_ratio[1] - 0.01


def test_the_paper_cube_with_the_default_model_is_good_or_fair_on_unseen_loads():
    """The paper's cube, families+volume, its two validation cases: within the documented
    floor, judged on the unseen cases, no parameter at a bound."""
    problem = fpm.load_problem(cube_spec(0.45, "families+volume"))
    result = calibrate(problem)
    v = result.fit.verdict
    assert v is not None and v.grade in ("good", "fair")
    assert v.basis == "unseen" and v.worst == max(result.fit.validation_relative_discrepancy)
    assert v.worst_case in ("sideways", "corner")
    assert v.floor.figure == CUBE_FLOORS[("families+volume", "unseen")]
    assert v.bounds == []
    assert len(result.fit.validation_compliance_ratio) == 2
    assert all(
        0.5 < c < 2 for c in result.fit.compliance_ratio + result.fit.validation_compliance_ratio
    )


def test_a_narrowed_bound_holding_k_makes_a_poor_fit_naming_the_bound():
    spec = small_box(annealing={"bounds": {"k": [3.0, 6.0]}, "c_max": 10})
    result = calibrate(fpm.load_problem(spec))
    v = result.fit.verdict
    assert v is not None and v.grade == "poor"
    [hit] = v.bounds
    assert (hit.parameter, hit.side, hit.bound, hit.setting) == (
        "k",
        "upper",
        6.0,
        "annealing.bounds.k",
    )
    bound = [c for c in v.causes if c.cause == "bound"]
    assert len(bound) == 1 and "annealing.bounds.k" in bound[0].action
    # held too soft: a probe feels it so
    assert min(result.fit.compliance_ratio) > SETTINGS.compliance[1]
    assert any(c.cause == "compliance" for c in v.causes)
    assert "k (upper)" in v.summary


def test_one_k_on_a_nearly_incompressible_cube_is_poor_with_its_causes():
    spec = small_box(material={"poisson_ratio": 0.4999})
    result = calibrate(fpm.load_problem(spec))
    v = result.fit.verdict
    assert v is not None and v.grade == "poor"
    causes = {c.cause: c for c in v.causes}
    assert "nu near 0.5" in causes and "families+volume" in causes["nu near 0.5"].action
    assert "model family" in causes
    assert "bound" not in causes and v.bounds == []
    # the same box at nu 0.45 is not near incompressible
    other = calibrate(fpm.load_problem(SMALL_BOX)).fit.verdict
    assert other is not None and "nu near 0.5" not in {c.cause for c in other.causes}


def test_large_deformation_and_a_coarse_lattice_are_named():
    """The small box under 10 times its forces moves past small strain; two cells across
    (3 x 3 x 3 nodes) is too coarse to bend."""
    spec = scaled(SMALL_BOX, 10.0)
    spec["geometry"]["nodes"] = [3, 3, 3]
    spec["load_cases"] = [
        {"name": c["name"], "forces": [{**f, "at": [0.015, 0.015, 0.03]} for f in c["forces"]]}
        for c in spec["load_cases"]
    ]
    problem = fpm.load_problem(spec)
    result = calibrate(problem)
    v = result.fit.verdict
    assert v is not None and v.grade != "good"
    causes = {c.cause: c for c in v.causes}
    assert "large deformation" in causes and "'0.1 N'" in causes["large deformation"].detail
    assert "lattice too coarse" in causes and "2.0 cells" in causes["lattice too coarse"].detail
    # judged again at the example's own size: neither
    small = calibrate(fpm.load_problem(SMALL_BOX))
    again = judge(fpm.load_problem(SMALL_BOX), small, [small.parameters.k], small_reference())
    assert {"large deformation", "lattice too coarse"}.isdisjoint(c.cause for c in again.causes)


def small_reference() -> np.ndarray:
    """The small box example's FEM reference displacements, (L, N, 3) m."""
    from fpm.fem.reference import reference_for

    return reference_for(fpm.load_problem(SMALL_BOX)).displacements


def test_the_documented_cube_floors_are_the_benchmark_json_s():
    """CUBE_FLOORS are the worst figures bench/results/volume.json records for the paper's
    cube at nu 0.45 against the selective linear reference, at the paper's forces."""
    records = json.loads((ROOT / "bench" / "results" / "volume.json").read_text())["records"]
    for mode in ("single", "families+volume"):
        [r] = [
            r
            for r in records
            if r["part"] == "cube" and r["poisson_ratio"] == 0.45 and r["stiffness_mode"] == mode
            and r["reference_integration"] == "selective" and r["reference_material"] == "linear"
            and r["force_scale"] == 1.0
        ]  # fmt: skip
        assert CUBE_FLOORS[(mode, "fitted")] == round(max(r["relative_discrepancy"]), 1)
        assert CUBE_FLOORS[(mode, "unseen")] == round(max(r["validation_relative_discrepancy"]), 1)


def test_a_reference_that_does_not_resolve_its_load_is_named_as_a_cause():
    """The small box's point loads on a coarse mesh: the reference's own estimate says 44%."""
    result = calibrate(fpm.load_problem(SMALL_BOX))
    assert result.reference.error is not None and max(result.reference.error) > 5
    v = result.fit.verdict
    assert v is not None and v.grade == "poor"
    [reference] = [c for c in v.causes if c.cause == "reference"]
    assert "reference.refine 'auto'" in reference.action and "'0.05 N'" in reference.detail


def test_both_command_lines_show_the_verdict_first_and_the_compliance_per_case(tmp_path, capsys):
    """fpmcal calibrate's table, and fpm-client's report of the same result as the service
    answers it: the verdict in capitals before the figures, its causes, a compliance column
    for the fitted and the validation cases."""
    from client.cli import show_calibration
    from fpmcal.cli import main

    spec = copy.deepcopy(SMALL_BOX)
    spec["validation_cases"] = [
        {"name": "sideways", "forces": [{"at": [0.01, 0.01, 0.03], "vector": [0.05, 0, 0]}]}
    ]
    path = tmp_path / "box.json"
    path.write_text(json.dumps(spec))
    assert main(["calibrate", str(path), "-q", "--json"]) == 0
    captured = capsys.readouterr()
    result = json.loads(captured.out)
    v = result["verdict"]
    assert v["basis"] == "unseen" and v["worst_case"] == "sideways"
    table = captured.err.splitlines()
    first = next(i for i, line in enumerate(table) if line.startswith("verdict: "))
    assert table[first].startswith(f"verdict: {v['grade'].upper()}: worst {v['worst']:.1f}%")
    header = next(i for i, line in enumerate(table) if line.startswith("load case"))
    assert first < header and table[header].endswith("compliance")
    row = table[header + 1].split()
    assert row[0:2] == ["0.05", "N"] and float(row[-1]) == pytest.approx(
        result["compliance_ratio"][0], abs=5e-4
    )
    unseen = next(line for line in table if line.startswith("sideways"))
    assert float(unseen.split()[-1]) == pytest.approx(
        result["validation_compliance_ratio"][0], abs=5e-4
    )
    assert any(line.startswith("  cause: ") for line in table) == bool(v["causes"])
    answer = {
        "id": "c1",
        "name": "box",
        "status": "succeeded",
        "parameter_set_id": "ps-1",
        "progress": {"phase": "done", "method": "two-stage", "stage": "done", "stages": [],
                     "iterations": 1, "total_iterations": 1},
        "result": result,
    }  # fmt: skip
    lines = show_calibration(answer).splitlines()
    first = next(i for i, line in enumerate(lines) if line.startswith("verdict: "))
    header = next(i for i, line in enumerate(lines) if line.startswith("load case"))
    assert first < header and lines[header].split()[-1] == "compliance"
    assert lines[header + 2].split()[-1] == f"{result['compliance_ratio'][0]:.3f}".rstrip("0")
    unseen = next(line for line in lines if line.startswith("sideways"))
    assert unseen.split()[-1] == f"{result['validation_compliance_ratio'][0]:.3f}".rstrip("0")


def test_the_demo_adds_one_verdict_line_per_material_and_nothing_else():
    from client.demo import report

    result = calibrate(fpm.load_problem(SMALL_BOX)).to_dict()
    spec = {"load_cases": SMALL_BOX["load_cases"]}
    bare = {k: v for k, v in result.items() if k != "verdict"}
    before = report({"paper-material-a": {"result": bare}}, {"paper-material-a": spec})
    after = report({"paper-material-a": {"result": result}}, {"paper-material-a": spec})
    added = [line for line in after.splitlines() if line not in before.splitlines()]
    assert added == [f"verdict: POOR{result['verdict']['summary'][len('poor') :]}"]
    assert after.replace(added[0] + "\n\n", "") == before


def test_the_manual_page_lists_every_threshold_as_the_code_has_it():
    from dataclasses import fields

    page = (ROOT / "docs" / "explanation" / "verdict.md").read_text()
    for f in fields(SETTINGS):
        value = getattr(SETTINGS, f.name)
        shown = "-".join(f"{v:g}" for v in value) if isinstance(value, tuple) else f"{value:g}"
        if f.name in ("good", "fair"):
            shown = f"{value:.1f} %"
        assert f"| `{f.name}` | {shown} |" in page, f.name
