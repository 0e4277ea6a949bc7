"""fpm.max_steps: the cap on a run's steps, from the number the spec gives or, for 'auto', from
the steps the reduced step (:mod:`fpm.dynamics.reduced_step`) predicts at a d, with a margin.
"""

from __future__ import annotations

import math

from ..fem.linear_solver import SingularStiffnessError
from ..model.forces import Stiffness
from ..model.problem import Problem
from .eigen import single_threaded_blas
from .modes import reduced_steps
from .reduced_step import StepModel

AUTO_MARGIN = 3.0
"""fpm.max_steps 'auto': this many times the predicted steps of the slowest load case (the
reduced step predicts 0.8-1.0 times the steps the runs take)."""
AUTO_MIN_STEPS = 1000
"""fpm.max_steps 'auto' is at least this."""
FALLBACK_STEPS = 20_000
"""fpm.max_steps 'auto' where there is no prediction (the paper method's joint search, a
lattice at rest that is a mechanism, a d that does not settle in the reduced step): the
default before 'auto'."""
SCHEMA_MAX_STEPS = 1_000_000
"""The schema's largest fpm.max_steps."""
AUTO_CEILING = 100_000
"""fpm.max_steps 'auto' is at most this: a lattice whose kernel needs more steps to settle a load
case (100 s of simulated time at 1 ms) is not interactive, and a search for its fastest d would
run for hours (the damping stage then keeps the static fit: fpm.fitting.damping.stage)."""


def auto_max_steps(predicted: list[float] | float) -> int:
    """fpm.max_steps 'auto' from predicted steps (one per load case, or one): AUTO_MARGIN
    times the largest, at least AUTO_MIN_STEPS, at most AUTO_CEILING; FALLBACK_STEPS when
    one does not settle."""
    values = [float(p) for p in predicted] if isinstance(predicted, list) else [float(predicted)]
    if not values or not all(math.isfinite(v) for v in values):
        return FALLBACK_STEPS
    return int(min(AUTO_CEILING, max(AUTO_MIN_STEPS, math.ceil(AUTO_MARGIN * max(values)))))


def fixed_max_steps(value: int | str) -> int:
    """fpm.max_steps where nothing predicts it: the number, or FALLBACK_STEPS for 'auto'."""
    return FALLBACK_STEPS if value == "auto" else int(value)


def case_models(
    problem: Problem,
    stiffness: Stiffness,
    depth: int | None,
    dt: float,
    cases: list[int] | None = None,
) -> list[StepModel] | None:
    """The reduced steps of ``cases`` (None: every load case) at (``stiffness``, ``depth``,
    ``dt`` s), each starting from the modes' linear response; None where there are none (the
    lattice at rest a mechanism). The modes of the last stiffness asked for are kept on the
    problem (``problem.cache.modes``)."""
    from .equilibrium import static_solver

    key = (stiffness.parameters().tobytes(), depth)
    kept = problem.cache.modes
    if kept is None or kept[0] != key:
        kept = problem.cache.modes = (key, {})
    try:
        with single_threaded_blas():
            return reduced_steps(
                problem, static_solver(problem), stiffness, depth, dt, cases=cases, modes=kept[1]
            )
    except (SingularStiffnessError, ValueError, ArithmeticError):
        return None


def predicted_max_steps(
    problem: Problem,
    stiffness: Stiffness,
    d: float,
    depth: int | None,
    dt: float,
    cases: list[int] | None = None,
) -> int:
    """fpm.max_steps 'auto' for runs at (``stiffness``, ``d`` N s/m, ``depth``, ``dt`` s) of
    ``cases`` (None: every load case): :func:`auto_max_steps` of the reduced steps'
    (:func:`case_models`) prediction at d; FALLBACK_STEPS where there is none (the lattice at
    rest a mechanism, d not settling)."""
    models = case_models(problem, stiffness, depth, dt, cases)
    if models is None:
        return FALLBACK_STEPS
    with single_threaded_blas():
        return auto_max_steps([m.steps(d, SCHEMA_MAX_STEPS) for m in models])
