"""Statuses of the project's own records (RQ job statuses are RQ's business)."""

from enum import Enum


class CalibrationStatus(str, Enum):
    """Lifecycle of a calibration: queued -> running -> succeeded | failed | canceled."""

    QUEUED = "queued"
    RUNNING = "running"
    SUCCEEDED = "succeeded"
    FAILED = "failed"
    CANCELED = "canceled"

    @property
    def terminal(self) -> bool:
        """True once nothing will change the calibration any more."""
        return self in TERMINAL


TERMINAL = frozenset(
    {CalibrationStatus.SUCCEEDED, CalibrationStatus.FAILED, CalibrationStatus.CANCELED}
)


class FemStatus(str, Enum):
    """Lifecycle of a FEM reference: queued -> running -> succeeded | failed."""

    QUEUED = "queued"
    RUNNING = "running"
    SUCCEEDED = "succeeded"
    FAILED = "failed"


class Phase(str, Enum):
    """What a calibration is doing (shown with its progress)."""

    QUEUED = "queued"
    FEM = "fem"
    ANNEALING = "annealing"
    """Stage 1: the annealing chains (over the stiffness for two-stage, (k, d) for paper)."""
    DAMPING = "damping"
    """Two-stage, stage 2: polish of the stiffness, depth, fastest-settling d."""
    FINALIZE = "finalize"
    DONE = "done"


def calibration_stages(method: str) -> list[Phase]:
    """The stages of a calibration of ``method`` ("two-stage" or "paper"), in order: the one
    numbering that the status answer, ``fpm-client`` and the web page show ("stage 2 of 4").
    The FEM reference is always stage 1, done at once when a stored one is reused, so a stage
    has the same number whether or not it is."""
    middle = [Phase.ANNEALING, Phase.DAMPING] if method == "two-stage" else [Phase.ANNEALING]
    return [Phase.FEM, *middle, Phase.FINALIZE]
