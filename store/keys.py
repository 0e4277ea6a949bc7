"""Every Redis key and RQ job id the project uses, built in one place.

Our own data lives under ``fpm:`` (RQ keeps its own ``rq:`` keys). Records that must outlive
the jobs (FEM references, parameter sets, calibration records) are stored with no expiry;
scratch data (chain checkpoints and results, progress) carries a TTL set by the writer.

Ids are made here too, each with the pattern it always matches: the service checks an id from a
URL against it before the id goes into a key, so ``<id>:progress`` cannot name another key.
"""

import re
import secrets

PREFIX = "fpm"
QUEUE = "fpm"
"""The RQ queue of the long jobs: FEM references and annealing chains."""

PRIORITY_QUEUE = "fpm-priority"
"""The RQ queue of the jobs that finish a calibration (the damping stage, finalize): workers
take from it first, so a calibration whose chains are done never waits behind the chains of
calibrations submitted after it."""

QUEUES = (PRIORITY_QUEUE, QUEUE)
"""Every queue of the project, in the order a worker takes jobs from them."""

# The jobs, by the dotted path RQ imports (the graph enqueues them, tests and the failure
# callback recognise them): one name each.
FEM_JOB = "worker.jobs.fem_reference"
CHAIN_JOB = "worker.jobs.anneal_chain"
BASIS_JOB = "worker.jobs.reduced_basis"
DAMPING_JOB = "worker.jobs.fit_damping_stage"
FINALIZE_JOB = "worker.jobs.finalize_calibration"
CASE_JOB = "worker.spread.damping_case"
FAILURE_CALLBACK = "worker.jobs.on_failure"
PROFILE_JOB = "worker.profile.calibration_profile"
EXPORT_JOB = "worker.jobs.export_parameter_set"
VIEW_JOB = "worker.view.parameter_set_view"


CALIBRATION_ID = re.compile(r"[0-9a-f]{16}")
"""Every calibration id: 16 lowercase hex digits (:func:`new_calibration_id`)."""

FEM_ID = re.compile(r"[0-9a-f]{64}")
"""Every FEM reference id: the sha256 hex digest of :func:`store.hashing.fem_hash`."""

MESH_ID = re.compile(r"[0-9a-f]{64}")
"""Every uploaded mesh id: the sha256 hex digest of :func:`store.hashing.mesh_hash`."""

PARAMETER_SET_ID = re.compile(r"ps-[0-9a-f]{16}")
"""Every parameter set id (:func:`parameter_set_id`)."""


def new_calibration_id() -> str:
    """A fresh random calibration id (64 bits: no collision in practice)."""
    return secrets.token_hex(8)


def parameter_set_id(spec_hash: str) -> str:
    """The id of the parameter set a spec's calibration stores (one per spec hash)."""
    return f"ps-{spec_hash[:16]}"


def calibration(calibration_id: str) -> str:
    """Hash: the calibration record (status, spec, result, ...)."""
    return f"{PREFIX}:calibration:{calibration_id}"


def calibration_progress(calibration_id: str) -> str:
    """Hash: chain index -> JSON progress of that chain; DAMPING_PROGRESS -> the damping
    stage's (two-stage method)."""
    return f"{PREFIX}:calibration:{calibration_id}:progress"


DAMPING_PROGRESS = "damping"
"""The field of :func:`calibration_progress` the damping stage reports in."""


def calibrations() -> str:
    """Sorted set: calibration ids scored by creation time."""
    return f"{PREFIX}:calibrations"


def calibration_by_spec(spec_hash: str) -> str:
    """String: the calibration id last submitted for this spec hash."""
    return f"{PREFIX}:calibration-by-spec:{spec_hash}"


def chain_result(calibration_id: str, chain: int) -> str:
    """String: JSON ChainResult of one chain (written once per chain)."""
    return f"{PREFIX}:calibration:{calibration_id}:chain:{chain}"


def fitted_chain(stiffness_hash: str, chain: int) -> str:
    """String: JSON ChainResult of one chain by the identity of what it fits
    (:func:`store.hashing.stiffness_hash`), whichever calibration ran it: a calibration of the
    same stiffness fit (one run again after its damping stage failed, or with other damping
    settings) takes it instead of annealing again."""
    return f"{PREFIX}:stiffness:{stiffness_hash}:chain:{chain}"


def reduced_basis(calibration_id: str) -> str:
    """Hash: stage 1's first reduced basis of a families+volume calibration (written once by
    its reduced-basis job, read by the chains and the damping job): field ``layout`` (JSON:
    per load case its nodes and columns), field ``arrays`` (the raw int64 / float64 arrays)."""
    return f"{PREFIX}:calibration:{calibration_id}:reduced-basis"


def damping_targets(calibration_id: str) -> str:
    """The static equilibria the damping stage's runs settle towards (raw float64)."""
    return f"{PREFIX}:calibration:{calibration_id}:damping-targets"


def chain_checkpoint(calibration_id: str, chain: int) -> str:
    """String: JSON annealing state of one chain, so a retried chain resumes."""
    return f"{PREFIX}:calibration:{calibration_id}:checkpoint:{chain}"


def damping_result(calibration_id: str) -> str:
    """String: JSON DampingStage of a two-stage calibration (written once)."""
    return f"{PREFIX}:calibration:{calibration_id}:damping"


def case_run(calibration_id: str, task: str) -> str:
    """Hash: one load case's run of the damping stage's d search (:mod:`worker.spread`),
    ``task`` its digest: field ``task`` (JSON: what to run), then ``run`` (JSON: how it
    ended) and ``displacements`` (raw float64 bytes) once run (written once)."""
    return f"{PREFIX}:calibration:{calibration_id}:case-run:{task}"


def case_claim(calibration_id: str, task: str) -> str:
    """String: who runs the load-case task now (SET NX with a short expiry its holder renews;
    an expired claim of a task with no result means its holder died)."""
    return f"{PREFIX}:calibration:{calibration_id}:case-claim:{task}"


def case_runs(calibration_id: str) -> str:
    """Set: the digests of a calibration's load-case tasks (to drop them once finished)."""
    return f"{PREFIX}:calibration:{calibration_id}:case-runs"


def calibration_jobs(calibration_id: str) -> str:
    """List: JSON spans of the calibration's jobs as they finish (worker, start, end, CPU s,
    the jobs each waited for: :mod:`store.timeline`)."""
    return f"{PREFIX}:calibration:{calibration_id}:jobs"


def fem_reference(fem_hash: str) -> str:
    """String: JSON FemResult (nodes, displacements per load case); no expiry."""
    return f"{PREFIX}:fem:{fem_hash}"


def mesh(mesh_id: str) -> str:
    """String: JSON tetrahedral mesh ``{"nodes", "tetrahedra"}`` uploaded for FEM references
    (``POST /v1/meshes``), content-addressed; no expiry."""
    return f"{PREFIX}:mesh:{mesh_id}"


def fem_meta(fem_hash: str) -> str:
    """Hash: FEM reference status, spec subset, summary."""
    return f"{PREFIX}:fem:{fem_hash}:meta"


def parameter_set(parameter_set_id: str) -> str:
    """String: JSON parameter set (k, d, depth, material, provenance); no expiry."""
    return f"{PREFIX}:parameter-set:{parameter_set_id}"


def parameter_sets() -> str:
    """Sorted set: parameter set ids scored by creation time."""
    return f"{PREFIX}:parameter-sets"


def evaluations_total() -> str:
    """Integer: annealing cost evaluations of every chain finished so far (the metrics'
    counter; its rate is the evaluations per second)."""
    return f"{PREFIX}:evaluations-total"


def fem_job_id(fem_hash: str) -> str:
    """RQ job id of the FEM job for a reference (shared by every calibration that needs it)."""
    return f"fem-{fem_hash[:40]}"


def chain_job_id(calibration_id: str, chain: int) -> str:
    """RQ job id of one annealing chain."""
    return f"{calibration_id}-chain-{chain}"


def basis_job_id(calibration_id: str) -> str:
    """RQ job id of the reduced-basis job (families+volume, two-stage calibrations)."""
    return f"{calibration_id}-reduced-basis"


def damping_job_id(calibration_id: str) -> str:
    """RQ job id of the damping stage (two-stage calibrations)."""
    return f"{calibration_id}-damping"


def case_job_id(calibration_id: str, task: str) -> str:
    """RQ job id of one load-case task of the damping stage."""
    return f"{calibration_id}-case-{task[:16]}"


def finalize_job_id(calibration_id: str) -> str:
    """RQ job id of the finalize job."""
    return f"{calibration_id}-finalize"


def profile_job_id(calibration_id: str) -> str:
    """RQ job id of the profile job of a calibration (the web view's plot data)."""
    return f"{calibration_id}-profile"


def export(export_hash: str) -> str:
    """String: the bytes of a parameter set's export in one format (made by the export job)."""
    return f"{PREFIX}:export:{export_hash}"


def export_failure(export_hash: str) -> str:
    """String: JSON ``{"error", "invalid"}`` of an export job that failed (a short TTL: the
    cool-down before it is tried again)."""
    return f"{PREFIX}:export:{export_hash}:failed"


def export_claim(export_hash: str) -> str:
    """String: held (SET NX, a few seconds) by the request that enqueues an export job, so
    concurrent first requests enqueue one job."""
    return f"{PREFIX}:export:{export_hash}:claim"


def export_job_id(export_hash: str) -> str:
    """RQ job id of the export job of one (parameter set, format, export version)."""
    return f"export-{export_hash[:40]}"


def view_job_id(view_hash: str) -> str:
    """RQ job id of the job that makes a parameter set's 3D view data (cached like an export,
    under :func:`export` of its :func:`store.hashing.view_hash`)."""
    return f"view-{view_hash[:40]}"


def owner_calibrations(owner: str) -> str:
    """Sorted set: an owner's (an API key's hash) calibrations, scored by their node count."""
    return f"{PREFIX}:owner:{owner}:calibrations"


def owners() -> str:
    """Set: every owner that has submitted a calibration (for the usage metrics)."""
    return f"{PREFIX}:owners"
