"""Benchmark results as JSON, so that no figure in the README or the manual is typed by hand.

A bench module records what it measured with :func:`record` (one dict of plain values per row:
numbers, strings, lists of them) while it runs; whoever runs it (``python -m bench``, i.e.
``make bench``, or the module's own ``python -m bench.NAME``) then calls :func:`save`, which
writes ``bench/results/NAME.json``: the records with the command that made them, the date
(UTC), the git commit of the tree they were measured on (and whether it had uncommitted
changes), and the machine (CPU, cores, load average before and after, Python and NumPy).
A part of a bench that was not run leaves the records of its earlier run in place: rows are
keyed by ``part``, and :func:`save` replaces only the parts recorded in this run.

``python -m bench.render`` renders the manual's benchmark pages and the README's headline
figures from the committed files; ``tests/house/test_bench_render.py`` fails when a committed page
differs from what the committed JSON renders.
"""

from __future__ import annotations

import datetime as _dt
import json
import os
import platform
import subprocess
import sys
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
RESULTS = Path(__file__).resolve().parent / "results"

_records: dict[str, list[dict[str, Any]]] = {}
_load_before: dict[str, list[float]] = {}


def _plain(value: Any) -> Any:
    """``value`` as JSON-able plain data (NumPy scalars and arrays become numbers and lists)."""
    if isinstance(value, dict):
        return {str(k): _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    if hasattr(value, "tolist"):
        return _plain(value.tolist())
    if isinstance(value, float) and value != value:
        return None
    return value


def record(bench: str, part: str, **fields: Any) -> None:
    """One measured row of ``bench`` (the JSON file's name), in its ``part``."""
    if bench not in _records:
        _records[bench] = []
        _load_before[bench] = list(os.getloadavg())
    _records[bench].append({"part": part, **_plain(fields)})


def recorded(bench: str) -> list[dict[str, Any]]:
    return list(_records.get(bench, []))


CODE_ONLY = [".", ":!docs", ":!tests", ":!*.md", ":!bench/results"]
"""What "uncommitted changes" counts: tracked files other than the manual, the tests, Markdown
and the benchmark results (editing a page while a benchmark runs, or a benchmark run in parts
writing its rows, does not change what it measures)."""


def commit() -> tuple[str, bool]:
    """(HEAD's commit, whether tracked code differs from it); ("unknown", True) without git."""
    try:
        head = subprocess.run(
            ["git", "rev-parse", "HEAD"], cwd=ROOT, capture_output=True, text=True, check=True
        ).stdout.strip()
        status = subprocess.run(
            ["git", "status", "--porcelain", "--untracked-files=no", "--", *CODE_ONLY],
            cwd=ROOT,
            capture_output=True,
            text=True,
            check=True,
        ).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown", True
    return head, bool(status)


def machine() -> dict[str, Any]:
    import numpy

    from fpm.fitting.step_budget import cpu_name

    return {
        "cpu": cpu_name(),
        "cores": os.cpu_count(),
        "system": f"{platform.system()} {platform.release()}",
        "python": platform.python_version(),
        "numpy": numpy.__version__,
    }


def save(bench: str, command: str | None = None) -> Path | None:
    """Write what ``bench`` recorded in this process to ``bench/results/{bench}.json`` (parts
    not run this time keep their earlier rows); None when it recorded nothing."""
    rows = _records.pop(bench, None)
    if not rows:
        return None
    path = RESULTS / f"{bench}.json"
    parts = {r["part"] for r in rows}
    earlier: list[dict[str, Any]] = []
    runs: dict[str, Any] = {}
    if path.is_file():
        old = json.loads(path.read_text())
        earlier = [r for r in old["records"] if r["part"] not in parts]
        runs = {p: run for p, run in old.get("runs", {}).items() if p not in parts}
    head, dirty = commit()
    run = {
        "command": command or " ".join([Path(sys.executable).name, *sys.argv]),
        "date": _dt.datetime.now(_dt.timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ"),
        "commit": head,
        "dirty": dirty,
        "machine": machine(),
        "load_average": {
            "before": [round(x, 2) for x in _load_before.pop(bench, os.getloadavg())],
            "after": [round(x, 2) for x in os.getloadavg()],
        },
    }
    for part in sorted(parts):
        runs[part] = run
    document = {
        "benchmark": bench,
        "runs": dict(sorted(runs.items())),
        "records": earlier + rows,
    }
    RESULTS.mkdir(exist_ok=True)
    path.write_text(json.dumps(document, indent=1) + "\n")
    return path


def save_all(command: str | None = None) -> list[Path]:
    """:func:`save` every bench that recorded something in this process."""
    return [p for name in list(_records) if (p := save(name, command)) is not None]


def load(bench: str) -> dict[str, Any]:
    return json.loads((RESULTS / f"{bench}.json").read_text())
