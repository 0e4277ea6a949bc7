"""RQ job functions: FEM reference, stage 1's reduced basis (families+volume), one annealing
chain, the damping stage (two-stage method), finalize, and the export of a parameter set
(enqueued by dotted path).

Every job takes ids only and reads what it needs from our keys; every job may run twice
(a retry after its worker died) and writes its results once, under deterministic keys:
a stored reduced basis is not built again, a finished chain is not re-run (nor one that an
earlier calibration of the same stiffness fit ran: its result is kept by the fit's identity,
:func:`store.hashing.stiffness_hash`, so a calibration run again after its damping stage
failed, or with other damping settings, resumes from the stored FEM reference and chains), a
stopped chain resumes from its checkpoint, a finished damping stage is not re-run (an
interrupted one starts again: it is deterministic), and the parameter set is written with SET
NX.

Progress goes to the calibration's progress hash (:func:`store.keys.calibration_progress`):
one field per chain, and the field :data:`store.keys.DAMPING_PROGRESS` for the damping stage.
Each progress write also reads the calibration's status, and a job whose calibration has been
canceled (or failed elsewhere) stops there.
"""

from .basis import reduced_basis
from .chains import anneal_chain
from .context import Canceled
from .damping import fit_damping_stage
from .export import export_parameter_set
from .failure import on_failure
from .fem import fem_reference
from .finalize import finalize_calibration

__all__ = [
    "Canceled",
    "anneal_chain",
    "export_parameter_set",
    "fem_reference",
    "finalize_calibration",
    "fit_damping_stage",
    "on_failure",
    "reduced_basis",
]
