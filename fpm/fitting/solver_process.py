"""A static solver in a child process of its own: :func:`fpm.fitting.reduced.fit_reduced`'s
second solver, so that its static solves run at once with this process's on another core.

Two static solvers on two threads of one process share its interpreter lock: on the
93,705-node organ a round's solves took 33.7 s on two threads against 38.2 s on one, and a
depth probe's three solves split over two threads took longer than on one. Two processes each
solve at full speed (one case alone 17.9 s, beside another case in a second process 16.1 s).

The child is forked, so it starts with this process's problem as it is (nothing is pickled but
the stiffness parameters going out and the equilibria coming back) and builds its own
:class:`~fpm.dynamics.equilibrium.StaticSolver`, as a second solver here would: a solver's
answers depend only on the solves it was asked, in order, so they are the same to the bit.
Should the child die, the solves it was asked are replayed on a solver in this process, which
goes on from there: nothing lost, the same bits.
"""

from __future__ import annotations

import multiprocessing
from multiprocessing.connection import Connection

import numpy as np

from ..dynamics.equilibrium import Equilibrium, StaticSolver
from ..dynamics.modes import single_threaded_blas
from ..model.problem import Problem
from ..model.stiffness import model_stiffness

Solves = tuple[np.ndarray, list[int], int | None]
"""One call's solves: (the stiffness parameters theta, the load cases, the depth)."""


def can_fork() -> bool:
    """Whether this platform starts child processes by fork (Linux, macOS)."""
    return "fork" in multiprocessing.get_all_start_methods()


class SolverProcess:
    """Static solves of ``problem``'s load cases on a solver in a forked child process.

    :meth:`solve` blocks until the child answers (call it from a thread to solve here
    meanwhile); :meth:`close` ends the child. Not thread-safe: one caller at a time.
    """

    def __init__(self, problem: Problem):
        self.problem = problem
        self.asked: list[Solves] = []
        self.here: StaticSolver | None = None  # the replayed solver, once the child died
        context = multiprocessing.get_context("fork")
        self.connection, child = context.Pipe()
        self.process = context.Process(target=_serve, args=(child, problem), daemon=True)
        self.process.start()
        child.close()

    def solve(
        self, theta: np.ndarray, cases: list[int], depth: int | None
    ) -> dict[int, Equilibrium]:
        """The static equilibria of load ``cases`` at the stiffness of ``theta`` and
        ``depth``, {load case: equilibrium}, in that order on the child's solver."""
        solves: Solves = (np.asarray(theta, dtype=float), list(cases), depth)
        self.asked.append(solves)
        if self.here is None:
            try:
                self.connection.send(solves)
                answer: dict[int, Equilibrium] = self.connection.recv()
                return answer
            except (EOFError, OSError):  # the child died: replay its solves here
                self.here = StaticSolver(self.problem)
                for earlier in self.asked[:-1]:
                    _solve(self.problem, self.here, earlier)
        return _solve(self.problem, self.here, solves)

    def close(self) -> None:
        """End the child (it has answered every call)."""
        if self.here is None:
            try:
                self.connection.send(None)
            except OSError:
                pass
        self.connection.close()
        self.process.join(timeout=10)
        if self.process.is_alive():
            self.process.kill()
            self.process.join()


def _solve(problem: Problem, solver: StaticSolver, solves: Solves) -> dict[int, Equilibrium]:
    theta, cases, depth = solves
    stiffness = model_stiffness(problem, theta)
    return {j: solver.solve(j, stiffness, depth) for j in cases}


def _serve(connection: Connection, problem: Problem) -> None:
    """The child: a solver of its own answering each call's solves until told to stop (None)
    or its parent is gone."""
    solver = StaticSolver(problem)
    with single_threaded_blas():
        while True:
            try:
                solves = connection.recv()
            except EOFError:
                return
            if solves is None:
                return
            connection.send(_solve(problem, solver, solves))
