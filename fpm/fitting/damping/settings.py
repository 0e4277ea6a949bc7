"""The damping stage's settings (:mod:`fpm.fitting.damping`): one frozen object."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class DampingSettings:
    """How the d search's runs advance and are judged, how the search brackets and refines d,
    when it gives up, and the stage's checks of its last run. Passed down from
    :func:`fpm.fitting.damping.stage.fit_stage` or defaulted (:data:`DEFAULT`); a worker that
    runs a search's runs for another process uses the default, so a search spread over
    workers must too (docs/explanation/physics/damping-search.md)."""

    chunk: int = 200
    """Time steps each load case advances between checks of a d's running total."""
    sample: int = 25
    """Steps between the residual samples a run's decay is read from."""
    predict_after: int = 600
    """A run's remaining steps are predicted only once it has taken this many (3 chunks)."""
    prune: float = 1.1
    """A d is dropped once its predicted total exceeds this times the best total (a margin
    probe: once a case's predicted steps exceed this times its cap)."""
    look: float = 0.2
    """Seconds between a lockstep's looks for what is named later."""
    margin_cap: int = 2
    """The margin's d settles every load case within this many times its fastest-d steps."""
    hold: int = 1000
    """Until what it needs is named, a lockstep's cases run at most this many steps and then
    wait (predict_after plus 2 chunks)."""
    margin_probes: int = 2
    """With a prediction, the margin search asks for at most this many probes: the reduced
    step's edge, and half a walk's step (12%) below it only where the edge settles."""
    bracket_step: float = 1.25
    """Smallest first step of the bracket, a factor on d."""
    walk_growth: float = 1.6
    """Each further bracket step is this much longer (on log d) than the last."""
    resolution: float = 1.02
    """The refinement stops once the best d's neighbours are within this factor squared."""
    refine_steps: int = 4
    """At most this many refining runs after the bracket."""
    flat: float = 0.02
    """The refinement stops once both neighbours settle within this fraction of the best
    total."""
    confirm: float = 1.04
    """The runs that confirm a predicted d sit this factor below and above it."""
    trust: float = 2.0
    """A confirming run is skipped where the reduced steps predict it slower than the
    predicted d by more than this many times their own relative error there."""
    confirm_prune: float = 1.0
    """A confirming run is dropped once its predicted total exceeds the predicted d's."""
    retries: int = 2
    """Under fpm.max_steps 'auto', repeats of a search that settles nothing, with a grown cap."""
    max_steps_growth: int = 4
    """The factor the cap grows by between those repeats."""
    hopeless: float = 10.0
    """A load case whose run at the predicted d reaches its cap unsettled, its decay
    predicting more than this many times the step budget, ends the search."""
    hopeless_after: int = 10_000
    """... once that run has taken this many steps (or the budget, if smaller); a tenth of
    the budget for a run that has not shrunk at all."""
    probe_steps: int = 20
    """When nothing settles, the probe run may take this many times max_steps (at most
    10^6)."""
    same_fit: float = 0.001
    """Material regions, anisotropy: chains within this fraction of the best cost fit
    equally well."""
    static_agreement: float = 1e-3
    """The last dynamic run reproduces the static cost to this fraction, else a warning ..."""
    settle_resolution: float = 1e-4
    """... or to this fraction of the reference cost (a fit whose cost is near 0)."""
    geometry_gap: float = 1.0
    """Points of relative discrepancy (%) by which a validation case's figure must exceed
    that of the model linearised at rest to be noted."""
    geometry_tolerance: float = 1e-4
    """The linearised solve's relative residual."""


DEFAULT = DampingSettings()
"""The settings every run and search takes unless given others."""
