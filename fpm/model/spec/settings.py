"""``fpm`` and ``annealing``: the model's settings (time step in s, stiffness modes) and the
simulated annealing schedule."""

from __future__ import annotations

import math
from typing import Any, Literal

from pydantic import (
    Field,
    field_validator,
    model_validator,
)

from .base import StiffnessMode, Vector3, _Strict


class FpmSettings(_Strict):
    """FPM settings (paper Sec. 3; physics.md)."""

    depth: int | Literal["full", "auto"] = Field(
        "full",
        description="penetration depth in layers; 'full' = every layer a load reaches (the "
        "default: a load the fit never saw moves the whole organ as the FEM does); 'auto' = "
        "the smallest depth that keeps, within auto_depth_tolerance, both the Eq. 2 cost of "
        "every load case and the model's own response to each case's forces turned along x, "
        "y and z (a real-time list shorter than the organ, judged also for loads not fitted)",
    )
    auto_depth_tolerance: float = Field(
        0.01,
        ge=0,
        le=1,
        description="depth 'auto': allowed relative rise of the cost over full depth's (0.01 = "
        "the relative discrepancy may grow by 1% of itself), and allowed change of the model's "
        "own response as a share of the case's relative discrepancy; larger trades realism "
        "for speed",
    )
    step_budget_us: float | None = Field(
        None,
        gt=0,
        description="a frame budget for one step, microseconds (two-stage): the depth is then "
        "the deepest at most the fitted one whose region step (fpm.runtime's Runtime.region: "
        "only the load's perturbed list moves) takes at most this on the calibrating machine, "
        "in every load case; the result names the machine, the backend and the microseconds "
        "measured, and its figures are at that depth. None (default): no budget",
    )
    stiffness: StiffnessMode = Field(
        "families+volume",
        description="'families+volume' (the default where the lattice has cells with face "
        "diagonals, else 'single'): one k per spring family, springs assembled from cells, and "
        "a volume stiffness kappa per cell (Pa): can be any isotropic solid with nu >= 1/4; "
        "'single': one k for every spring (the paper's model); 'families': one k per spring "
        "family present (axis, face diagonal, body diagonal); 'field': families+volume, then a "
        "per-cell factor on the springs and on kappa fitted by adjoint gradients, smoothed "
        "between neighbouring cells by a weight chosen by cross-validation (one force pattern "
        "left out at a time), returned only where it predicts the left-out loads better than "
        "the four numbers (needs two or more load_cases; two-stage method)",
    )
    loads: Literal["auto", "node", "hat"] = Field(
        "auto",
        description="how the lattice takes a nodal force: 'node' (the paper's: all of it at its "
        "node), 'hat' (as the load it stands for and a refined FEM reference applies: a "
        "traction over the node's share of the surface, or a body load over its share of the "
        "volume, given to the lattice nodes as an FEM gives a distributed load, by the shape "
        "functions; cells only, not a spring network) or 'auto' (default): 'hat' where the "
        "reference spreads the forces (reference.refine at least 1 or 'auto', or a tetrahedral "
        "reference) and the lattice has cells, else 'node'. The result and the export say "
        "which was used",
    )
    dt: float | Literal["auto"] = Field(
        "auto",
        description="time step, s, or 'auto' (default): half the lattice's stability estimate "
        "at the fitted stiffness, at most 1 ms (a haptic 1 kHz loop)",
    )
    max_steps: int | Literal["auto"] = Field(
        "auto",
        description="steps per load case before a run gives up (a cap: the result reports the "
        "steps each load case took and the cap, max_steps), 1 to 1,000,000, or 'auto' "
        "(default): three times the steps the lattice's slowest modes predict at the fitted d, "
        "at least 1,000, at most 100,000 (20,000 where nothing predicts it, e.g. the paper "
        "method); a lattice predicted to need more is not searched: the calibration keeps its "
        "static fit and says d was not fitted",
    )
    settle_distance: float | Literal["auto"] = Field(
        "auto",
        description="settled when the run's distance from its static equilibrium is below "
        "this times the 2-norm of its displacement (scale-free, unlike settle_tolerance), "
        "0 < x < 1, or 'auto' (default): 1/20 of the load cases' static discrepancy against "
        "the reference, taken together (so settling moves the fit's cost by at most 5% of "
        "itself), the same for every case, between 1e-4 and 0.01 (always within 1% of the "
        "static equilibrium). The "
        "fit's runs measure the distance against the static equilibrium they have solved (with "
        "what the velocities still carry along the softest mode); a run with no equilibrium to "
        "read (fpm.simulate, an exported model) bounds it by its unbalanced forces over the "
        "stiffness of the softest mode, at 0.01 for 'auto'. Not used where settle_tolerance is "
        "named, nor by the paper method",
    )
    settle_tolerance: float | None = Field(
        None,
        ge=0,
        description="the force criterion instead of settle_distance: settled when the largest "
        "unbalanced nodal force in a sweep is below this times the largest applied nodal force "
        "(0 = never settle). None (default): settle_distance, or 1e-5 for the paper method "
        "and a lattice that is a mechanism at rest. Not scale-free: the same tolerance stops "
        "further from rest on a finer lattice",
    )
    stiffness_scale: Vector3 = Field(
        (1.0, 1.0, 1.0),
        description="per-axis stiffness factors (sx, sy, sz); a spring along unit vector e gets "
        "k * (sx ex^2 + sy ey^2 + sz ez^2) (paper Fig. 5)",
    )
    gravity: Vector3 = Field((0.0, 0.0, 0.0), description="m/s^2; the paper ignores gravity")

    @field_validator("dt")
    @classmethod
    def _positive_dt(cls, v: float | str) -> float | str:
        if not isinstance(v, str) and not v > 0:
            raise ValueError("dt must be > 0 (s) or 'auto'")
        return v

    @field_validator("settle_distance")
    @classmethod
    def _settle_distance_range(cls, v: float | str) -> float | str:
        if not isinstance(v, str) and not 0 < v < 1:
            raise ValueError("settle_distance must be between 0 and 1 (exclusive) or 'auto'")
        return v

    @field_validator("max_steps")
    @classmethod
    def _max_steps_range(cls, v: int | str) -> int | str:
        if not isinstance(v, str) and not 1 <= v <= 1_000_000:
            raise ValueError("max_steps must be 1 to 1,000,000 or 'auto'")
        return v

    @field_validator("depth")
    @classmethod
    def _depth_nonneg(cls, v: int | str) -> int | str:
        if isinstance(v, int) and v < 0:
            raise ValueError("depth must be >= 0, 'full' or 'auto'")
        return v

    @property
    def layers(self) -> int | None:
        """The spec's integer depth, layers; None for 'full' and 'auto' (every layer: 'auto'
        is resolved after the stiffness is fitted at full depth)."""
        return None if isinstance(self.depth, str) else int(self.depth)

    @field_validator("stiffness_scale")
    @classmethod
    def _positive_scale(cls, v: Vector3) -> Vector3:
        if min(v) <= 0:
            raise ValueError("stiffness factors must be > 0")
        return v


class Bounds(_Strict):
    """Search box for the annealer; None = derived (see :mod:`fpm.fitting.bounds`)."""

    k: tuple[float, float] | None = Field(None, description="spring stiffness range, N/m")
    d: tuple[float, float] | None = Field(None, description="nodal damping range, N s/m")

    @field_validator("k", "d")
    @classmethod
    def _ordered(cls, v: tuple[float, float] | None) -> tuple[float, float] | None:
        if v is not None and not 0 < v[0] < v[1]:
            raise ValueError("need 0 < low < high")
        return v


DEFAULT_T_FINAL = {"paper": 2e-4, "two-stage": 2e-3}


class AnnealingSettings(_Strict):
    """Simulated annealing settings (paper Sec. 4.2-4.3).

    Temperatures and ``c_max`` are in units of the reference cost (the cost of an FPM that does
    not move at all, i.e. the summed FEM displacement): a scale-free schedule that works for any
    material. Lundy-Mees cooling T <- T / (1 + beta T), one move per temperature, so a chain
    makes about (1/t_final - 1/t_initial) / beta moves.

    ``t_final`` defaults by method: 2e-4 for ``paper`` (151 moves, the joint (k, d) search on
    dynamic runs) and 2e-3 for ``two-stage`` (15 moves: its stage 1 searches 1-3 stiffness
    parameters of a smooth cost, where the anneal only has to find the basin and the bounded
    polish that follows resolves the optimum).
    """

    method: Literal["two-stage", "paper"] = Field(
        "two-stage",
        description="'two-stage': anneal the stiffness on static equilibria, then find the "
        "fastest-settling d; 'paper': anneal (k, d) jointly on dynamic runs (paper Sec. 4.3)",
    )
    seed: int = Field(0, ge=0)
    chains: int = Field(2, ge=1, le=64, description="independent chains; the best one wins")
    t_initial: float = Field(0.05, gt=0)
    t_final: float = Field(
        DEFAULT_T_FINAL["two-stage"], gt=0, description="default 2e-4 for paper, 2e-3 two-stage"
    )
    beta: float = Field(33.0, gt=0)
    c_max: float = Field(2.0, gt=0, description="reject at once a candidate costing more")
    bounds: Bounds = Field(default_factory=Bounds)

    @model_validator(mode="before")
    @classmethod
    def _default_t_final(cls, data: Any) -> Any:
        if isinstance(data, dict) and data.get("t_final") is None:
            paper = data.get("method") == "paper"  # a bad method is the field's own error
            data = {**data, "t_final": DEFAULT_T_FINAL["paper" if paper else "two-stage"]}
        return data

    @model_validator(mode="after")
    def _cooling(self) -> AnnealingSettings:
        if self.t_final >= self.t_initial:
            raise ValueError("t_final must be below t_initial")
        moves = lundy_mees_moves(self.t_initial, self.t_final, self.beta)
        if moves > 1e6:
            raise ValueError(f"this schedule makes {moves:.3g} moves per chain (limit 1e6)")
        return self

    @property
    def moves(self) -> int:
        """Moves per chain implied by the cooling schedule (:func:`lundy_mees_moves`)."""
        return lundy_mees_moves(self.t_initial, self.t_final, self.beta)


MOVES_CAP = 1 << 62
""":func:`lundy_mees_moves` saturates here (a schedule this long is refused anyway)."""


def lundy_mees_moves(t_initial: float, t_final: float, beta: float) -> int:
    """Moves of a Lundy-Mees chain, one per temperature: T_{n+1} = T_n / (1 + beta T_n) makes
    1/T grow by beta per move, from 1/t_initial until T falls below t_final. (The one home of
    this formula: the spec's limits and moves, and the annealer's schedule, use it.)"""
    moves = (1 / t_final - 1 / t_initial) / beta
    return math.floor(moves) + 1 if moves < MOVES_CAP else MOVES_CAP  # beta 5e-324: inf
