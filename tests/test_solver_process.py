"""A static solver in a child process (fpm.fitting.solver_process): the same equilibria to the
bit as a solver in this process asked the same solves in the same order, warm starts included;
a child that dies loses nothing (its solves are replayed here and the answers stay the same)."""

from __future__ import annotations

import os
import signal

import numpy as np
import pytest
from helpers_fpm import box_spec

import fpm
from fpm.dynamics.equilibrium import StaticSolver
from fpm.fitting.solver_process import SolverProcess, can_fork
from fpm.model.stiffness import continuum_start, model_stiffness

pytestmark = pytest.mark.skipif(not can_fork(), reason="the platform does not fork")


@pytest.fixture(scope="module")
def box() -> fpm.Problem:
    spec = box_spec(
        (5, 4, 6), 0.01,
        forces=[{"at": [0.02, 0.01, 0.05], "vector": [0.0, 0.0, -0.01]}],
        fpm_settings={"stiffness": "families+volume"},
    )  # fmt: skip
    spec["load_cases"].append({"forces": [{"at": [0.04, 0.03, 0.05], "vector": [0.01, 0, 0]}]})
    spec["material"]["poisson_ratio"] = 0.45
    return fpm.load_problem(spec)


def thetas(problem: fpm.Problem) -> list[np.ndarray]:
    """Three stiffness parameter sets, as a fit's rounds would ask (each a warm start for the
    next)."""
    start = np.array(continuum_start(problem))
    return [start * f for f in (1.0, 1.1, 1.12)]


def here(problem: fpm.Problem, depth: int | None) -> list[dict[int, np.ndarray]]:
    solver = StaticSolver(problem)
    return [
        {j: solver.solve(j, model_stiffness(problem, t), depth).displacements for j in (0, 1)}
        for t in thetas(problem)
    ]


def displacements(answer) -> dict[int, np.ndarray]:
    return {j: e.displacements for j, e in answer.items()}


@pytest.mark.parametrize("depth", [None, 2])
def test_the_child_solves_as_a_solver_here_does(box, depth):
    expected = here(box, depth)
    process = SolverProcess(box)
    try:
        found = [displacements(process.solve(t, [0, 1], depth)) for t in thetas(box)]
    finally:
        process.close()
    assert not process.process.is_alive()
    for f, e in zip(found, expected, strict=True):
        assert f.keys() == e.keys()
        assert all(np.array_equal(f[j], e[j]) for j in e)  # to the bit


def test_a_child_that_dies_loses_nothing(box):
    """Killed after the first call, the second and third are answered here after the first is
    replayed (the warm starts as the child had them): the same bits as a solver here."""
    expected = here(box, None)
    process = SolverProcess(box)
    try:
        found = [displacements(process.solve(thetas(box)[0], [0, 1], None))]
        os.kill(process.process.pid, signal.SIGKILL)
        process.process.join()
        found += [displacements(process.solve(t, [0, 1], None)) for t in thetas(box)[1:]]
    finally:
        process.close()
    assert process.here is not None  # solved here from the second call on
    for f, e in zip(found, expected, strict=True):
        assert all(np.array_equal(f[j], e[j]) for j in e)
