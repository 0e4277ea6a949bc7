"""Diagnoses: a FEM reference in the wrong units is refused, one outside small strain is flagged,
the lattice's stability estimate separates runs that settle from runs that diverge, and a
failed annealing start is explained."""

from __future__ import annotations

import importlib.util
import math
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from helpers_fpm import box_spec

import fpm
from fpm.dynamics.stability import stable_time_step
from fpm.fem.reference import solve_fem
from fpm.fitting.diagnosis import UnitsError, check_reference, explain_rejections
from fpm.io.plot import calibration_figure, profile_line
from fpm.model.stiffness import spring_stiffness

ROOT = Path(__file__).resolve().parents[2]


def block(youngs_modulus: float, forces: tuple[float, ...] = (0.05,)) -> fpm.Problem:
    """A 6 cm cube, 4x4x4 nodes, bottom fixed, one load case per force (N, along +z) at a top
    node. The figures quoted in the tests below are those of the 2x2x2 ("full") element, which
    the spec names; the default selective element moves the loaded node 65% further on this
    coarse block (0.69 -> 1.14 m at E = 5 Pa)."""
    spec = box_spec((4, 4, 4), 0.02)
    spec["material"]["youngs_modulus"] = youngs_modulus
    spec["reference"] = {"integration": "full"}
    spec["load_cases"] = [
        {"name": f"{f:g} N", "forces": [{"at": [0.02, 0.02, 0.06], "vector": [0, 0, f]}]}
        for f in forces
    ]
    return fpm.load_problem(spec)


def test_a_reference_that_moves_further_than_the_solid_is_thick_is_refused():
    """E = 5 (meant: 5 kPa) on a 6 cm block: the linear FEM moves the loaded node 0.69 m."""
    problem = block(5.0)
    u = solve_fem(problem).displacements
    largest = float(np.linalg.norm(u, axis=2).max())
    assert largest == pytest.approx(0.688, abs=1e-3)
    with pytest.raises(UnitsError) as info:
        check_reference(problem, u)
    message = str(info.value)
    assert isinstance(info.value, ValueError)
    assert "load case '0.05 N'" in message
    assert f"{largest:.3g} m" in message and "smallest extent (0.06 m)" in message
    assert "E is in Pa (5 kPa = 5000), lengths in m, forces in N" in message
    assert "E = 5 Pa" in message and "\n" not in message


def test_a_validation_case_that_moves_too_far_is_named_as_one():
    """E = 5 kPa, a 0.05 N press fitted (0.69 mm) and a 10 N press unseen (0.14 m, more than
    the 6 cm block): the reference of every case is checked, the case named by the spec's name
    as a validation case (an index past the load cases raised IndexError), and with the units
    right the message says the load is too large, not to check them."""
    spec = block(5000.0).spec.model_dump(mode="json")
    spec["validation_cases"] = [
        {"name": "hard press", "forces": [{"at": [0.02, 0.02, 0.06], "vector": [0, 0, 10.0]}]}
    ]
    problem = fpm.load_problem(spec)
    every = solve_fem(problem)
    assert every.displacements.shape[0] == 2
    with pytest.raises(UnitsError) as info:
        check_reference(problem, every)
    message = str(info.value)
    assert message.startswith("validation case 'hard press': the linear FEM reference moves")
    assert "the load is far too large for a linear reference: lower the forces" in message
    assert "units" not in message and "\n" not in message
    assert check_reference(problem, every.displacements[:1]) == []  # the load cases alone
    with pytest.raises(ValueError, match="holds 3 cases where the spec has 1 load cases and 1"):
        check_reference(problem, np.zeros((3, problem.n_nodes, 3)))


def test_units_are_blamed_only_where_a_value_looks_like_another_unit():
    """A 6 cm block at E = 5 kPa moved 0.14 m by 10 N: too large a load, units not named; the
    same block read as 60 m (a mesh in mm) and 10 kN: the size is named as the suspect."""
    problem = block(5000.0, forces=(10.0,))
    u = solve_fem(problem).displacements
    with pytest.raises(UnitsError) as info:
        check_reference(problem, u)
    assert "check the units" not in str(info.value)
    assert "E = 5000 Pa, largest nodal force 10 N" in str(info.value)
    metres = box_spec((4, 4, 4), 20.0)
    metres["material"]["youngs_modulus"] = 5000.0
    big = fpm.load_problem(metres)
    with pytest.raises(UnitsError) as info:
        check_reference(big, np.full((1, big.n_nodes, 3), 100.0))
    message = str(info.value)
    assert "check the units (E is in Pa" in message
    assert "the solid is 60 m across (a mesh in mm is read with --scale 0.001)" in message
    assert "E = 5000 Pa is" not in message  # E is plausible: not named


def test_a_reference_outside_small_strain_is_flagged_per_load_case():
    """E = 500 Pa: 0.05 N moves the node 6.9 mm (11% of 6 cm), 0.005 N 0.69 mm (1.1%)."""
    problem = block(500.0, forces=(0.05, 0.005))
    warnings = check_reference(problem, solve_fem(problem))
    assert len(warnings) == 1
    assert warnings[0].startswith("load case '0.05 N': the largest FEM displacement, 0.00688 m")
    assert "11% of the solid's smallest extent (0.06 m)" in warnings[0]
    assert "outside small strain: the linear reference" in warnings[0]
    assert "consider" in warnings[0]
    # At the right E (5 kPa) nothing to say.
    problem = block(5000.0)
    assert check_reference(problem, solve_fem(problem).displacements) == []


def test_the_stability_estimate_is_the_worst_node_of_the_small_box():
    """small-box (4x4x4, 1 cm, full connectivity): the worst node is a free top corner, 1/8 of a
    cell's mass on 7 springs (3 edges, 3 face diagonals, 1 body diagonal)."""
    problem = fpm.load_problem(ROOT / "examples" / "small-box.json")
    corner_mass = 1040.0 * 0.01**3 / 8
    expected = math.sqrt(2 * corner_mass / (7 * 38.8))
    assert stable_time_step(problem, 38.8) == pytest.approx(expected, rel=1e-12)
    per_spring = spring_stiffness(problem, 38.8)
    assert stable_time_step(problem, per_spring) == pytest.approx(expected, rel=1e-12)
    assert stable_time_step(problem, 4 * per_spring) == pytest.approx(expected / 2, rel=1e-12)
    with pytest.raises(ValueError, match="one per spring"):
        stable_time_step(problem, per_spring[:-1])


@pytest.mark.parametrize("example", ["small-box.json", "paper-material-a.json"])
def test_half_the_estimate_settles_and_three_times_it_diverges(example: str):
    """k = 38.8 N/m, d = 0.5 sqrt(E h m) (small: the default d range starts at 0.1 of it and
    reaches 5 times it); every layer moves."""
    problem = fpm.load_problem(ROOT / "examples" / example)
    k = 38.8
    dt = stable_time_step(problem, k)
    eh = problem.spec.material.youngs_modulus * problem.h
    d = 0.5 * math.sqrt(eh * problem.solid.masses.mean())
    calm = fpm.simulate(problem, k=k, d=d, dt=0.5 * dt, depth=None, max_steps=5000)
    assert calm.settled and not calm.diverged
    wild = fpm.simulate(problem, k=k, d=d, dt=3 * dt, depth=None, max_steps=5000)
    assert wild.diverged


def test_explain_rejections_counts_and_suggests_a_time_step():
    message = explain_rejections(
        {"diverged": 38, "unsettled": 12, "c_max": 0}, 50, suggested_dt=9.78e-4, dt=2e-3
    )
    assert message.startswith(
        "no acceptable starting point in 50 random tries: 38 diverged, 12 did not settle "
        "within max_steps"
    )
    assert "c_max" not in message  # nothing was rejected for it
    assert "the lattice's stability estimate suggests dt <= 0.000978 s (the spec has 0.002 s)" in (
        message
    )
    assert "lower fpm.dt" in message and "fpm.max_steps" in message
    assert "\n" not in message


def test_explain_rejections_when_dt_is_not_the_cause():
    message = explain_rejections({"diverged": 50}, 50, suggested_dt=2e-3, dt=1e-3)
    assert "(the spec has 0.001 s), so the time step is not the cause" in message
    assert "raise the low end of annealing.bounds.d" in message
    message = explain_rejections({"diverged": 50}, 50, suggested_dt=None, dt=1e-3)
    assert "lower fpm.dt" in message


def test_explain_rejections_over_c_max_points_at_the_reference():
    message = explain_rejections({"c_max": 50, "odd": 2}, 52, suggested_dt=1e-3, dt=1e-3)
    assert "50 cost more than c_max, 2 odd" in message
    assert "the FEM reference may be wrong" in message and "annealing.c_max" in message
    assert "stability" not in message  # nothing diverged


# --- the calibration plot: a profile line with points, and the relative discrepancy -----------


def organ_problem() -> fpm.Problem:
    """bench/organ.py's soft ellipsoid at h = 10 mm (724 nodes)."""
    module_spec = importlib.util.spec_from_file_location("organ", ROOT / "bench" / "organ.py")
    assert module_spec is not None and module_spec.loader is not None
    organ = importlib.util.module_from_spec(module_spec)
    module_spec.loader.exec_module(organ)
    return fpm.load_problem(organ.ellipsoid_spec(0.01, fpm={"stiffness": "single"}))


@pytest.fixture(scope="module")
def organ() -> fpm.Problem:
    return organ_problem()


def test_the_profile_runs_along_the_fullest_line_through_the_loaded_node(organ):
    x = organ.nodes
    for j, case in enumerate(organ.load_cases):
        line, along, direction = profile_line(organ, j)
        first = case.nodes[0]
        counts = [
            int(np.sum(np.all(np.abs(np.delete(x - x[first], a, axis=1)) < 1e-6, axis=1)))
            for a in range(3)
        ]
        assert len(line) == max(counts) >= 8, (case.name, counts)
        assert first in line
        assert np.all(np.diff(x[line, along]) > 0)  # sorted along the line
        others = [a for a in range(3) if a != along]
        assert np.allclose(x[line][:, others], x[first, others])
    # The press at the top node: the top is a small flat patch (the old line along x had 2
    # points); the column through the top node is the fullest.
    assert profile_line(organ, 0)[1] == 2


def test_the_legend_gives_the_relative_discrepancy_beside_the_percent_of_h(organ):
    reference = solve_fem(organ).displacements
    result = SimpleNamespace(
        parameters=SimpleNamespace(k=17.0, d=0.09, depth=None),
        fit=SimpleNamespace(),
        settle=SimpleNamespace(),
        run=SimpleNamespace(history=[1.0, 0.4, 0.5]),
    )
    fig = calibration_figure(organ, reference, result)
    legend = [t.get_text() for t in fig.axes[0].get_legend().get_texts()]
    for j in range(len(organ.load_cases)):
        run = fpm.simulate(organ, k=17.0, d=0.09, load_case=j)
        p, q = run.displacements, reference[j]
        relative = 100 * np.linalg.norm(p - q, axis=1).sum() / np.linalg.norm(q, axis=1).sum()
        h_percent = 100 * np.linalg.norm(p - q, axis=1).mean() / organ.h
        assert f"FPM: {relative:.2f}% relative, {h_percent:.2f}% of h" in legend
    # A result that carries the figures is quoted as it is.
    result.fit.relative_discrepancy = [1.25, 2.5, 3.75]
    result.fit.discrepancy_h = [0.5, 0.25, 0.125]
    fig = calibration_figure(organ, reference, result)
    legend = [t.get_text() for t in fig.axes[0].get_legend().get_texts()]
    assert "FPM: 2.50% relative, 0.25% of h" in legend
    assert all("% relative" in t for t in legend if t.startswith("FPM"))
    import matplotlib.pyplot as plt

    plt.close("all")
