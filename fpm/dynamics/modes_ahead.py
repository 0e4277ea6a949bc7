"""The slowest modes found ahead, on a thread of their own, while the polish goes on.

The prediction (:func:`fpm.dynamics.modes.reduced_steps`) reads each list's slowest modes off
the static solver's multigrid hierarchy of that list, which the polish builds and keeps.
:class:`ModesAhead` finds them after a round of the polish, one V-cycle at a time; the
prediction takes those whose hierarchy is still the one they were found on and finds the
others itself, so the modes are the same whatever the timing
(docs/explanation/physics/calibration-speed.md, *The modes beside the polish*).
"""

from __future__ import annotations

import threading

import numpy as np

from .eigen import DENSE_UP_TO, MODES, Modes, lowest_modes, single_threaded_blas
from .equilibrium import StaticSolver


class ModesAhead:
    """The slowest modes of ``solver``'s lists at ``depth``, found on a thread of their own.

    Args:
        solver: the static solver the prediction will read (the polish's cost solver).
        depth: the lists' depth, layers (None: every layer).
        count: modes per list.
    """

    def __init__(self, solver: StaticSolver, depth: int | None, count: int = MODES):
        self.solver, self.depth, self.count = solver, depth, count
        self._thread: threading.Thread | None = None
        self._found: dict[bytes, tuple[object, Modes]] = {}

    def start(self, _round: int = 0) -> None:
        """Find the modes of every list that has a hierarchy now, on a thread (the first call
        only; call it where no other thread uses the solver's lists: between the polish's
        rounds). Lists without one (small lists take dense modes) are left to the prediction."""
        if self._thread is not None:
            return
        problem = self.solver.problem
        work: dict[bytes, tuple[object, np.ndarray]] = {}
        for j in range(len(problem.load_cases)):
            system, _ = self.solver.system(j, self.depth)
            kept = self.solver.multigrid(system) if 3 * system.n_free > DENSE_UP_TO else None
            if kept is not None:
                work.setdefault(system.free.tobytes(), (kept, system.free))
        masses = problem.solid.masses
        self._thread = threading.Thread(
            target=self._find, args=(work, masses), name="modes-ahead", daemon=True
        )
        self._thread.start()

    def _find(self, work: dict[bytes, tuple[object, np.ndarray]], masses: np.ndarray) -> None:
        with single_threaded_blas():
            for key, (kept, free) in work.items():
                hierarchy = kept.hierarchy  # type: ignore[attr-defined]
                try:
                    modes = lowest_modes(
                        hierarchy.levels[0].A, masses[free], self.count, hierarchy=hierarchy,
                        free=free, threads=1,
                    )  # fmt: skip
                except (np.linalg.LinAlgError, ValueError, ArithmeticError):
                    continue  # the prediction finds them again, and says what went wrong
                self._found[key] = (kept, modes)

    def modes(self, depth: int | None) -> dict[bytes, Modes]:
        """Wait for the thread; the modes (keyed by the list's nodes, as
        :func:`fpm.dynamics.modes.reduced_steps` keys them) of the lists at ``depth`` whose
        hierarchy is still the one they were found on (a list at another depth with the same
        nodes is the same list)."""
        if self._thread is None:
            return {}
        self._thread.join()
        found = {}
        for j in range(len(self.solver.problem.load_cases)):
            system, _ = self.solver.system(j, depth)
            key = system.free.tobytes()
            if key in self._found and self._found[key][0] is self.solver.multigrid(system):
                found[key] = self._found[key][1]
        return found
