"""Prometheus metrics at ``/metrics``.

Per route (prometheus-fastapi-instrumentator, labelled by the route's path template, so ids
do not multiply the series; unknown paths are one ``handler="none"``):

- ``http_requests_total{handler, method, status}``
- ``http_request_duration_seconds{handler, method}`` (histogram), and
  ``http_request_duration_highr_seconds`` (finer buckets, all routes together)
- ``http_request_size_bytes{handler}``, ``http_response_size_bytes{handler}``

Read from Redis and RQ on each scrape (:class:`QueueCollector`):

- ``fpm_redis_up``: 1 when Redis answered the scrape (the rest is left out when not)
- ``fpm_queue_depth{queue}``: jobs waiting for a worker
- ``fpm_jobs{queue, state}``: deferred (waiting on other jobs), running, failed, stopped (by a
  cancel)
- ``fpm_workers{state}``: busy, idle, suspended, silent (no recent heartbeat: dead or hung)
- ``fpm_calibrations{status}``: queued, running, succeeded, failed, canceled
- ``fpm_parameter_sets``: stored parameter sets
- ``fpm_calibration_duration_seconds`` (summary: ``_count``, ``_sum``): start to finish of
  every succeeded calibration (``_sum / _count`` the mean; the rate of both, recent ones)
- ``fpm_cost_evaluations_total`` (counter): annealing cost evaluations of every finished chain;
  ``rate(fpm_cost_evaluations_total[1m])`` is the evaluations per second
- ``fpm_key_active_calibrations{owner}``, ``fpm_key_nodes_in_flight{owner}``: each API key's
  usage of its quotas (``owner``: the first 16 hex digits of the key's SHA-256, never the key)

Each app has a registry of its own, so apps built in one process (tests) do not collide.
The endpoint needs no API key (like ``/docs``): it shows counts, no data.
"""

from __future__ import annotations

import logging
from collections import Counter
from collections.abc import Callable, Iterator

from fastapi import FastAPI
from prometheus_client import CollectorRegistry
from prometheus_client.core import (
    CounterMetricFamily,
    GaugeMetricFamily,
    Metric,
    SummaryMetricFamily,
)
from prometheus_client.registry import Collector
from prometheus_fastapi_instrumentator import Instrumentator
from redis import Redis
from redis.exceptions import RedisError

from store import queue_stats, quotas, records
from store.status import CalibrationStatus

ENDPOINT = "/metrics"
log = logging.getLogger("service")


class QueueCollector(Collector):
    """Gauges of the queues, workers and records, read from Redis when scraped."""

    def __init__(self, redis: Callable[[], Redis]):
        self.redis = redis

    def collect(self) -> Iterator[Metric]:
        up = GaugeMetricFamily("fpm_redis_up", "1 if Redis answered this scrape, else 0")
        try:
            gauges = self._read(self.redis())
        except RedisError as e:
            log.warning("metrics: Redis unavailable: %s", type(e).__name__)
            up.add_metric([], 0)
            yield up
            return
        up.add_metric([], 1)
        yield up
        yield from gauges

    def _read(self, redis: Redis) -> list[Metric]:
        """Every gauge but fpm_redis_up (read in full before any is yielded)."""
        depth = GaugeMetricFamily(
            "fpm_queue_depth", "Jobs waiting for a worker, per queue", labels=["queue"]
        )
        jobs = GaugeMetricFamily(
            "fpm_jobs",
            "Jobs per queue and state: deferred (waiting on other jobs), running, failed, "
            "stopped (by a cancel)",
            labels=["queue", "state"],
        )
        for name, counts in queue_stats.all_job_counts(redis).items():
            depth.add_metric([name], counts.queued)
            for state in ("deferred", "running", "failed", "stopped"):
                jobs.add_metric([name, state], getattr(counts, state))
        workers = GaugeMetricFamily(
            "fpm_workers",
            "Workers by state (silent: no heartbeat within the window: dead or hung)",
            labels=["state"],
        )
        for state, n in queue_stats.worker_states(redis).items():
            workers.add_metric([state], n)
        calibrations = GaugeMetricFamily(
            "fpm_calibrations", "Calibrations by status", labels=["status"]
        )
        statuses, durations = calibration_statuses(redis)
        for status, n in statuses.items():
            calibrations.add_metric([status], n)
        duration = SummaryMetricFamily(
            "fpm_calibration_duration_seconds",
            "Start to finish of every succeeded calibration, s",
            count_value=len(durations),
            sum_value=sum(durations),
        )
        evaluations = CounterMetricFamily(
            "fpm_cost_evaluations",
            "Annealing cost evaluations of every finished chain",
            value=records.evaluations_total(redis),
        )
        sets = GaugeMetricFamily("fpm_parameter_sets", "Stored parameter sets")
        sets.add_metric([], records.parameter_set_count(redis))
        active = GaugeMetricFamily(
            "fpm_key_active_calibrations",
            "Calibrations queued or running per API key (owner: a hash of the key, never the key)",
            labels=["owner"],
        )
        nodes = GaugeMetricFamily(
            "fpm_key_nodes_in_flight",
            "Lattice nodes of the calibrations queued or running per API key (owner: a hash)",
            labels=["owner"],
        )
        for owner, used in quotas.all_usage(redis).items():
            active.add_metric([owner], used.active)
            nodes.add_metric([owner], used.nodes)
        return [depth, jobs, workers, calibrations, duration, evaluations, sets, active, nodes]


def calibration_statuses(redis: Redis) -> tuple[dict[str, int], list[float]]:
    """Calibrations by status (every status, zeros included), and the durations (s) of the
    succeeded ones."""
    counts: Counter[str] = Counter({s.value: 0 for s in CalibrationStatus})
    durations = []
    for status, started, finished in records.calibration_timings(redis):
        counts[status.value] += 1
        if status == CalibrationStatus.SUCCEEDED and started > 0 and finished > 0:
            durations.append(max(finished - started, 0.0))
    return dict(counts), durations


def install(app: FastAPI, redis: Callable[[], Redis]) -> None:
    """Instrument ``app`` and serve ``/metrics`` (``redis`` gives the client to read from)."""
    registry = CollectorRegistry()
    registry.register(QueueCollector(redis))
    Instrumentator(
        should_group_status_codes=False,
        excluded_handlers=[ENDPOINT],
        registry=registry,
    ).instrument(app).expose(app, endpoint=ENDPOINT, include_in_schema=False)
