"""A calibration's jobs as a timeline, and its critical path (no numerical code here).

Each job that works for a calibration adds a span when it finishes
(:func:`store.scratch.add_span`; :class:`fpm.fitting.result.JobSpan`): its name, the worker
that ran it, Unix start and end times (s), the CPU seconds it used, and the names of the spans
it waited for (``after``). The damping stage is two spans around the
load-case tasks it hands out (:mod:`worker.spread`): ``damping`` up to the hand-out, the tasks
after it, and ``damping (gather)`` after the tasks.

The critical path is the longest chain of spans each waiting for the one before, by the sum of
their durations: what the calibration would take with a worker free for every job at once
(queueing and hand-over times left out). Spans of distinct tasks named alike are told apart
by :func:`numbered`.
"""

from __future__ import annotations

from typing import Any


def critical_path(spans: list[dict[str, Any]]) -> tuple[float, list[str]]:
    """The longest chain of ``spans`` (dicts of :class:`fpm.fitting.result.JobSpan`) along
    ``after``: (its seconds,
    the names on it, first first). A name in ``after`` that no span has is skipped; a span
    named twice (a job run again) counts once, its last run."""
    by_name = {s["name"]: s for s in spans}
    longest: dict[str, tuple[float, list[str]]] = {}

    def path(name: str, seen: frozenset[str]) -> tuple[float, list[str]]:
        if name in longest:
            return longest[name]
        span = by_name[name]
        before = [
            path(a, seen | {name}) for a in span.get("after", []) if a in by_name and a not in seen
        ]
        head = max(before, key=lambda p: p[0], default=(0.0, []))
        own = max(float(span["end"]) - float(span["start"]), 0.0)
        longest[name] = (head[0] + own, [*head[1], name])
        return longest[name]

    return max((path(n, frozenset()) for n in by_name), key=lambda p: p[0], default=(0.0, []))


def numbered(spans: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """``spans`` with the names of distinct tasks that share one told apart: the second task
    named ``n`` becomes ``n [2]``, and so on (two requests at one d whose caps differ, say, are
    named alike by :func:`worker.tasks.task_name`; the critical path goes by names). A task
    run twice keeps its name."""
    tasks: dict[str, list[str]] = {}  # name -> the digests of the tasks so named, in order
    for span in spans:
        task = span.get("task")
        if task is None:
            continue
        seen = tasks.setdefault(span["name"], [])
        if task not in seen:
            seen.append(task)
        if (n := seen.index(task)) > 0:
            span["name"] = f"{span['name']} [{n + 1}]"
    return spans
