"""The damping stage's settings (:mod:`fpm.fitting.damping`): one frozen object,
:class:`DampingSettings`, whose defaults are the constants below (how the d search's runs
advance and are judged, how the search brackets and refines d, when it gives up, and the
stage's checks of its last run).
"""

from __future__ import annotations

from dataclasses import dataclass

BRACKET_STEP = 1.25
"""Smallest first step of the bracket, as a factor on d (used when the two guesses are closer
than this)."""
WALK_GROWTH = 1.6
"""Each further bracket step is this much longer (on log d) than the last."""
RESOLUTION = 1.02
"""The refinement stops once the best d's neighbours are within this factor squared of it."""
REFINE_STEPS = 4
"""At most this many refining runs after the bracket."""
FLAT = 0.02
"""The refinement stops once both neighbours of the best d settle within this fraction of its
total steps (the steps-versus-d curve is flat there)."""
CONFIRM = 1.04
"""The runs that confirm a predicted d sit this factor below and above it."""
TRUST = 2.0
"""A confirming run is skipped where the reduced steps predict it slower than the predicted d
by more than this many times their own relative error there
(:func:`fpm.fitting.damping.search._unsure`)."""
CONFIRM_PRUNE = 1.0
"""A confirming run is dropped once its predicted total exceeds the predicted d's total (it
would at best tie; the predicted d is kept)."""
RETRIES = 2
"""With fpm.max_steps 'auto', a search in which nothing settles within the predicted cap is
repeated this many times more with MAX_STEPS_GROWTH times the cap (up to the schema's 10^6)."""
MAX_STEPS_GROWTH = 4
"""... the factor the cap grows by between those repeats."""

CHUNK = 200
"""Time steps each load case advances between checks of a d's running total."""
SAMPLE = 25
"""Steps between the residual samples a run's decay is read from."""
PREDICT_AFTER = 3 * CHUNK
"""A run's remaining steps are predicted only once it has taken this many (past the transient)."""
PRUNE = 1.1
"""A d is dropped once its predicted total exceeds this times the best total (a margin probe:
once a case's predicted steps exceed this times its cap); the slack absorbs prediction error."""
LOOK = 0.2
"""Seconds between a lockstep's looks for what is named later."""
MARGIN_CAP = 2
"""A d 'still settles' for the margin if every load case settles within this many times its
steps at the fastest d (below the margin a run diverges or creeps; capping keeps the margin
search as cheap as the rest)."""
HOLD = PREDICT_AFTER + 2 * CHUNK
"""Until what it needs is named, a lockstep's cases run at most this many steps and then wait:
past PREDICT_AFTER, where the verdicts of the d run beside the predicted d's usually come
(their cores go to the predicted d's cases meanwhile)."""

MARGIN_PROBES = 2
"""With a prediction, the margin search asks for at most this many probes: the reduced step's
edge (run at once beside the predicted d's runs where a worker is free), and half a walk's step
(12%) below it only where the edge settles. d_min is then the smallest d found that settles,
bracketed to 1.12x or by the tried d above the edge (why the edge comes first:
docs/notes/2026-11-28-calibration-measured.md, *The margin's order*)."""

HOPELESS = 10.0
"""The search stops at once (:class:`fpm.fitting.damping.unsettled.DampingError` naming the load
case) when a case's run at the predicted d reaches its cap unsettled and the decay of its residual,
which is how fast its distance from equilibrium shrinks towards its settle distance
(:func:`fpm.fitting.damping.unsettled.long_decay`), predicts more than this many times the step
budget: fpm.max_steps, or under 'auto' the schema's 10^6 its cap may grow to. Its cap would
otherwise grow and the whole range of d be scanned at the budget's steps per case, only to reach
the same verdict. The slack covers the decay's error early in a long run (it can over-predict a
slender bar's steps several times)."""
HOPELESS_AFTER = 10_000
"""... and only once that run has taken at least this many steps (or the whole budget, if
smaller); a run whose distance has not shrunk at all, only after a tenth of the budget: a
lattice can ring for tens of thousands of steps before its decay shows (the transversely
isotropic block of docs/howto/regions-and-anisotropy.md settles, but only after that long)."""

PROBE_STEPS = 20
"""When nothing settles, the probe run may take this many times max_steps (capped at the
schema's 1,000,000) to measure the steps a run needs."""

STATIC_AGREEMENT = 1e-3
"""The last dynamic run must reproduce the static cost to this fraction, else a warning ..."""
GEOMETRY_GAP = 1.0
"""Points of relative discrepancy by which a validation case's figure must exceed the figure of
the model linearised at rest (its small-load limit) for
:func:`fpm.fitting.damping.validation.geometry_notes` to say so."""
GEOMETRY_TOLERANCE = 1e-4
"""The linearised solve's relative residual: the figures need a few digits, not the
equilibrium's."""
SETTLE_RESOLUTION = 1e-4
"""... or to this fraction of the reference cost, for a fit so close (cost near 0) that the
settle tolerance's own error dominates."""

SAME_FIT = 0.001
"""Material regions, anisotropy: chains within this fraction of the best cost fit equally well
(:func:`fpm.fitting.damping.polish.chain_to_polish`)."""


@dataclass(frozen=True)
class DampingSettings:
    """The stage's settings, one object: each field's default is the constant of the same name
    above, where it is explained. Passed to :func:`fpm.fitting.damping.search.fastest_damping`
    (and from there to its runs, :class:`fpm.fitting.damping.lockstep._Runs`) or defaulted
    (:data:`DEFAULT`); a worker that runs a search's runs for another process uses the
    default, so a search spread over workers must too.

    Attributes:
        chunk: time steps each load case advances between checks of a d's total.
        sample: steps between the residual samples a run's decay is read from.
        predict_after: steps a run takes before its remaining steps are predicted.
        prune: a d is dropped once its predicted total exceeds this times the best total.
        look: seconds between a lockstep's looks for what is named later, s.
        margin_cap: the margin's d settles within this many times the fastest d's steps.
        hold: steps a lockstep's case runs at most until what it needs is named.
        margin_probes: probes the margin search asks for at most, with a prediction.
        bracket_step: smallest first step of the bracket, a factor on d.
        walk_growth: each further bracket step is this much longer on log d.
        resolution: the refinement stops once the neighbours are within this factor squared.
        refine_steps: refining runs after the bracket, at most.
        flat: the refinement stops once both neighbours settle within this fraction of the
            best total.
        confirm: the confirming runs sit this factor below and above the predicted d.
        trust: a confirming run is skipped beyond this many times the reduced steps' error.
        confirm_prune: a confirming run is dropped past this times the predicted d's total.
        retries: repeats of a search with a grown cap under fpm.max_steps 'auto'.
        max_steps_growth: the factor the cap grows by between those repeats.
        hopeless: a case predicted past this many times the step budget ends the search.
        hopeless_after: steps its run must have taken first.
        probe_steps: the probe run of a failed search may take this many times max_steps.
        same_fit: chains within this fraction of the best cost fit equally well.
        static_agreement: the last run reproduces the static cost to this fraction.
        settle_resolution: ... or to this fraction of the reference cost.
        geometry_gap: points of relative discrepancy (%) a validation case must exceed its
            linearised figure by to be noted.
        geometry_tolerance: the linearised solve's relative residual.
    """

    chunk: int = CHUNK
    sample: int = SAMPLE
    predict_after: int = PREDICT_AFTER
    prune: float = PRUNE
    look: float = LOOK
    margin_cap: int = MARGIN_CAP
    hold: int = HOLD
    margin_probes: int = MARGIN_PROBES
    bracket_step: float = BRACKET_STEP
    walk_growth: float = WALK_GROWTH
    resolution: float = RESOLUTION
    refine_steps: int = REFINE_STEPS
    flat: float = FLAT
    confirm: float = CONFIRM
    trust: float = TRUST
    confirm_prune: float = CONFIRM_PRUNE
    retries: int = RETRIES
    max_steps_growth: int = MAX_STEPS_GROWTH
    hopeless: float = HOPELESS
    hopeless_after: int = HOPELESS_AFTER
    probe_steps: int = PROBE_STEPS
    same_fit: float = SAME_FIT
    static_agreement: float = STATIC_AGREEMENT
    settle_resolution: float = SETTLE_RESOLUTION
    geometry_gap: float = GEOMETRY_GAP
    geometry_tolerance: float = GEOMETRY_TOLERANCE


DEFAULT = DampingSettings()
"""The settings every run and search takes unless given others."""
