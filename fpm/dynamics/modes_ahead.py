"""The slowest modes found ahead, on a thread of their own, while the static fit goes on.

The prediction of the fastest d (:func:`fpm.dynamics.modes.predict_damping`) reads each
list's slowest modes off the static solver's multigrid hierarchy of that list: its finest
level's matrix is the stiffness the modes solve, its V-cycle their preconditioner
(:func:`fpm.dynamics.modes.reduced_steps`). That hierarchy is built by the polish's first
round (:func:`fpm.fitting.defect_correction.fit_reduced`, on the tangent at rest at the round's
parameters) and kept while CG stays fast on it. Found after the polish, the modes would run
alone on the damping job's critical path, while the polish leaves part of a core idle
(docs/explanation/physics/calibration-speed.md, *The modes beside the polish*).

:class:`ModesAhead` takes the hierarchies as they stand after a round of the polish and finds
their modes on one thread (one V-cycle at a time, so the polish keeps its two threads); the
prediction then takes the modes of every list whose hierarchy is still the one they were found
on, and finds the others as before. So the modes are the ones the prediction would have found
whenever the polish did not rebuild the hierarchy after that round, bit for bit, and otherwise
those of the newer hierarchy; which happens depends on the runs only, never on timing.
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
