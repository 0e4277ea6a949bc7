"""Simulated annealing (paper Sec. 4.2-4.3) over a box in log space.

Metropolis acceptance ``exp(-dc / T)`` (Boltzmann constant folded into T), Lundy-Mees cooling
``T <- T / (1 + beta T)``, one move per temperature, stop once T is below ``t_final``. A
candidate that diverged, or whose cost exceeds ``c_max``, is rejected at once (paper Fig. 8).

Start: a given point when acceptable (the two-stage calibration passes its linear estimate),
else the best of a few random points of the box. Moves: a Gaussian step in log(parameter),
reflected into the bounds; its width shrinks geometrically from STEP_INITIAL to STEP_FINAL
(natural-log units) over the chain, so the early chain roams the whole box and the late chain
resolves the optimum to a fraction of a percent. The generator is passed in: the same state
gives the same chain, bit for bit.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np

from ..model.spec import lundy_mees_moves

STEP_INITIAL = 0.5
STEP_FINAL = 0.002
START_SAMPLES = 8


@dataclass
class Schedule:
    """Lundy-Mees cooling: T_{n+1} = T_n / (1 + beta T_n), from t_initial until T < t_final."""

    t_initial: float
    t_final: float
    beta: float

    def __post_init__(self) -> None:
        if not 0 < self.t_final < self.t_initial or self.beta <= 0:
            raise ValueError("need 0 < t_final < t_initial and beta > 0")

    @property
    def moves(self) -> int:
        """Number of moves (:func:`fpm.model.spec.lundy_mees_moves`)."""
        return lundy_mees_moves(self.t_initial, self.t_final, self.beta)

    def temperature(self, move: int) -> float:
        """Temperature at which move ``move`` (0-based) is judged."""
        return self.t_initial / (1 + move * self.beta * self.t_initial)


@dataclass
class State:
    """A point of the search: parameters, their (normalised) cost, and what else was measured."""

    x: list[float]
    cost: float
    info: dict[str, Any] = field(default_factory=dict)


@dataclass
class AnnealResult:
    """Outcome of one chain, shaped like scipy's ``OptimizeResult``: :attr:`x`, :attr:`fun`,
    :attr:`nfev`, :attr:`nit`, :attr:`message`, with the chain's own records beside them."""

    best: State
    history: list[float]
    """Current cost after each move."""
    evaluations: int
    """Objective calls, the start search's included."""
    accepted: int
    near_best: list[State]
    """The states evaluated within :data:`KEEP_NEAR_BEST` of the best cost (the best among
    them), for the caller's choice among nearly-as-good states."""

    @property
    def x(self) -> list[float]:
        """The best parameters found."""
        return self.best.x

    @property
    def fun(self) -> float:
        """Their cost."""
        return self.best.cost

    @property
    def nfev(self) -> int:
        """Objective calls (:attr:`evaluations`)."""
        return self.evaluations

    @property
    def nit(self) -> int:
        """Moves made (one per temperature)."""
        return len(self.history)

    @property
    def message(self) -> str:
        return f"cooled in {self.nit} moves, {self.accepted} accepted"


@dataclass
class Checkpoint:
    """Where a chain stands after ``move`` moves: passed back to :func:`anneal` as ``resume``, it
    continues the chain exactly (same result, bit for bit, as an uninterrupted chain).

    ``rng`` is the generator's ``bit_generator.state``; ``visited`` holds only the states the
    result can still keep (within :data:`KEEP_NEAR_BEST` of ``best``). :meth:`to_dict` is JSON.
    """

    move: int
    rng: dict[str, Any]
    current: State
    best: State
    history: list[float]
    evaluations: int
    accepted: int
    visited: list[State]

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> Checkpoint:
        states = {k: State(**data[k]) for k in ("current", "best")}
        visited = [State(**s) for s in data["visited"]]
        return cls(**{**data, **states, "visited": visited})


def metropolis(delta: float, temperature: float, u: float) -> bool:
    """Accept a move of cost change ``delta`` given a uniform draw ``u`` in [0, 1)."""
    return delta <= 0 or u < math.exp(-delta / temperature)


def anneal(
    objective: Callable[[list[float]], State],
    lower: np.ndarray,
    upper: np.ndarray,
    schedule: Schedule,
    rng: np.random.Generator,
    *,
    c_max: float,
    progress: Callable[[dict[str, Any]], None] | None = None,
    checkpoint: Callable[[Checkpoint], None] | None = None,
    checkpoint_every: int = 10,
    resume: Checkpoint | None = None,
    initial: list[float] | None = None,
) -> AnnealResult:
    """Minimise ``objective`` over the box [lower, upper] (positive bounds, log-space moves).

    ``objective(x)`` returns a :class:`State` whose cost is inf for a diverged candidate.
    ``initial``: where the chain starts when that point is acceptable (else, and when None, the
    best of a few random points of the box).
    ``checkpoint(state)`` receives a :class:`Checkpoint` every ``checkpoint_every`` moves;
    passing it back as ``resume`` continues the chain exactly where it stood (same result as
    uninterrupted).
    """
    lo, hi = np.log(np.asarray(lower, float)), np.log(np.asarray(upper, float))
    if not np.all(lo < hi):
        raise ValueError("need 0 < lower < upper")
    moves = schedule.moves
    if resume is None:
        start = 0

        def started(samples: int) -> None:  # the start search reports too (and may be canceled)
            if progress is not None:
                progress({"move": 0, "moves": moves, "temperature": schedule.t_initial,
                          "start_samples": samples})  # fmt: skip

        given = objective(list(initial)) if initial is not None else None
        if given is not None and given.cost <= c_max:
            current, evaluations = given, 1
            started(1)
        else:
            current, evaluations = _start(objective, lo, hi, rng, c_max, started)
            evaluations += given is not None
        best = current
        history: list[float] = []
        visited = [current]
        accepted = 0
    else:
        start = resume.move
        rng.bit_generator.state = resume.rng
        current, best, visited = resume.current, resume.best, list(resume.visited)
        history, evaluations, accepted = list(resume.history), resume.evaluations, resume.accepted
    for move in range(start, moves):
        if checkpoint is not None and move > start and move % checkpoint_every == 0:
            checkpoint(_snapshot(move, rng, current, best, history, evaluations, accepted, visited))
        t = schedule.temperature(move)
        width = STEP_INITIAL * (STEP_FINAL / STEP_INITIAL) ** (move / max(moves - 1, 1))
        y = _reflect(np.log(current.x) + width * rng.standard_normal(len(lo)), lo, hi)
        candidate = objective(np.exp(y).tolist())
        evaluations += 1
        u = rng.random()
        if math.isfinite(candidate.cost):
            visited.append(candidate)
            if candidate.cost <= c_max and metropolis(candidate.cost - current.cost, t, u):
                current = candidate
                accepted += 1
                if current.cost < best.cost:
                    best = current
        history.append(current.cost)
        if progress is not None:
            progress(
                {
                    "move": move + 1,
                    "moves": moves,
                    "temperature": t,
                    "best_cost": best.cost,
                    "current_cost": current.cost,
                }
            )
    return AnnealResult(best, history, evaluations, accepted, _near(visited, best))


KEEP_NEAR_BEST = 0.01
"""Visited states kept for the caller: those within this fraction of the chain's best cost."""


def _near(visited: list[State], best: State) -> list[State]:
    return [s for s in visited if s.cost <= best.cost * (1 + KEEP_NEAR_BEST)]


def _start(
    objective, lo, hi, rng, c_max, report, samples: int = START_SAMPLES, tries: int = 50
) -> tuple[State, int]:
    """The best of ``samples`` random acceptable points of the box (log-uniform draws), and the
    number of evaluations made.

    Starting from the best of a few draws rather than from one spares a chain the long walk
    from a poor corner of the box, which at one move per temperature it may never finish.
    A rejected draw is counted by its ``info["rejected"]`` reason (else "diverged" for an
    infinite cost, "c_max" for a finite one).
    """
    found: list[State] = []
    rejected: dict[str, int] = {}
    n = 0
    while len(found) < samples and n < tries:
        n += 1
        state = objective(np.exp(rng.uniform(lo, hi)).tolist())
        if state.cost <= c_max:
            found.append(state)
        else:
            reason = state.info.get("rejected") or (
                "c_max" if math.isfinite(state.cost) else "diverged"
            )
            rejected[reason] = rejected.get(reason, 0) + 1
        report(n)
    if not found:
        counts = ", ".join(f"{v} {k}" for k, v in sorted(rejected.items()))
        raise AnnealingError(
            f"no acceptable starting point in {tries} random tries ({counts}; c_max={c_max:g})",
            rejected=rejected,
            tries=tries,
        )
    return min(found, key=lambda st: st.cost), n


class AnnealingError(RuntimeError):
    """The search cannot proceed (e.g. every candidate diverges).

    Attributes:
        rejected: why the start search's candidates were rejected: {reason: count}, reasons
            "diverged", "unsettled", "no equilibrium", "c_max".
        tries: candidates drawn.
    """

    def __init__(self, message: str, rejected: dict[str, int] | None = None, tries: int = 0):
        super().__init__(message)
        self.rejected = rejected or {}
        self.tries = tries


def _reflect(y: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    span = hi - lo
    z = np.mod(y - lo, 2 * span)
    return lo + np.where(z > span, 2 * span - z, z)


def _snapshot(move, rng, current, best, history, evaluations, accepted, visited) -> Checkpoint:
    def state(s: State) -> State:
        return State(list(s.x), s.cost, s.info)

    return Checkpoint(
        move=move,
        rng=rng.bit_generator.state,
        current=state(current),
        best=state(best),
        history=list(history),
        evaluations=evaluations,
        accepted=accepted,
        visited=[state(s) for s in _near(visited, best)],
    )
