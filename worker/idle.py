"""Which workers are idle or busy: those the damping job hands its tasks to
(:mod:`worker.spread`), and how many tasks it runs on its own threads."""

from __future__ import annotations

import socket
from collections.abc import Sequence

from redis import Redis
from rq import Worker
from rq.worker import BaseWorker

from store import keys


def free_workers(redis: Redis, me: str, calibration_id: str) -> int:
    """Workers other than ``me`` that are idle now, or about to be: their job is one of this
    calibration's tasks, whose runs the damping job is done waiting for (RQ marks a worker
    idle a moment after its job has stored its runs)."""
    prefix = keys.case_job_id(calibration_id, "")
    return sum(
        1 for w in Worker.all(connection=redis)
        if w.name != me
        and (w.get_state() == "idle" or (w.get_current_job_id() or "").startswith(prefix))
    )  # fmt: skip


def here(workers: Sequence[BaseWorker], me: str, host: str | None, state: str) -> int:
    """Of ``workers``, those other than ``me`` on the host ``host`` in ``state`` ("busy":
    running a job, "idle")."""
    return sum(1 for w in workers if w.name != me and w.hostname == host and w.get_state() == state)


def local_threads(redis: Redis, me: str, cores: int, queued: int = 0) -> int:
    """How many tasks the damping job runs at once on its own threads: this host's ``cores``
    less the other workers here that are busy, and the idle ones that will take one of the
    ``queued`` tasks (enqueued as jobs, not claimed yet), at least one. Two tasks sharing the
    core another worker leaves would each take twice as long (the kernel shares the cores
    between worker processes evenly, not between threads), so the d whose runs they are would
    be known later and every span on the critical path would stretch; in turn they end as
    soon as the work allows. Workers on other hosts (or in containers of their own) are not
    counted."""
    workers, host = Worker.all(connection=redis), socket.gethostname()
    taking = min(here(workers, me, host, "idle"), queued)
    return max(1, cores - here(workers, me, host, "busy") - taking)
