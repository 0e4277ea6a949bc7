"""``make demo``: calibrate the paper's materials A and B through the SDK.

Starts the local stack (Redis, API, 2 workers; see :mod:`stack.local`) unless $FPM_URL
names a running service, submits examples/paper-material-a.json and -b.json (with the spec's
default method, two-stage: a stiffness search on static equilibria, then the fastest-settling
d), shows their progress, and prints the fitted parameters beside the paper's Table 1, then the
fit per load case: the relative discrepancy first (the headline figure), with the loaded-node
error and the paper's unit, % of h, beside it, and the verdict on each fit. Stops the stack.
Stored results survive in ./data: a second run answers at once.
"""

from __future__ import annotations

import os
from contextlib import nullcontext
from pathlib import Path
from typing import Any

from stack.local import local_stack
from stack.redis_server import free_port

from .cli import DISCREPANCY_HEADERS, discrepancy_rows, mean, stiffness_text
from .sdk import Client, read_spec
from .table import table, verdict_lines

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"
PAPER = {
    "paper-material-a": {"k": 38.60, "d": 20.36, "depth": 10},
    "paper-material-b": {"k": 358.6, "d": 313.6, "depth": 10},
}
"""Choi et al. 2004, Table 1."""
PAPER_H = {"mean": "about 9", "smallest": "1.4"}
"""The paper's mean nodal discrepancy, % of h: over its forces, and at the smallest force."""
STACK_URL = "http://127.0.0.1:8000"
"""Where ``make run`` (``fpmcal up``) serves the API and the web view."""
LOG_DIR = Path("data") / "logs"
"""Where the demo's API and workers log."""
PAPER_NOTE = """\
The paper (Table 1) reports only % of h: a mean discrepancy of about 9% of h over the forces,
1.4% of h at the smallest force. It gives no relative figure, so the relative column has
nothing to compare with; % of h shrinks with small loads and soft solids, hence the relative
discrepancy first. The paper gives neither its dt nor its node masses, so its d cannot be
compared: d here is the fastest-settling damping at the spec's dt."""


def report(results: dict[str, dict[str, Any]], specs: dict[str, dict[str, Any]]) -> str:
    """The fitted parameters beside the paper's, then the discrepancies per load case."""
    rows = []
    for name, done in results.items():
        r, paper = done["result"], PAPER[name]
        rows.append(
            [
                name,
                r["method"],
                stiffness_text(r["stiffness"]),
                paper["k"],
                r["d"],
                paper["d"],
                r["depth"],
                paper["depth"],
            ]
        )
    headers = [
        "material",
        "method",
        "stiffness N/m",
        "paper k",
        "d N s/m",
        "paper d",
        "depth",
        "paper",
    ]
    parts = [table(headers, rows)]
    rows = []
    for name, done in results.items():
        r = done["result"]
        smallest = min(range(len(r["discrepancy_h"])), key=lambda j: _force(specs[name], j))
        rows.append(
            [
                name,
                mean(r["relative_discrepancy"]),
                "not given",
                mean(r["discrepancy_h"]),
                PAPER_H["mean"],
                r["discrepancy_h"][smallest],
                PAPER_H["smallest"],
            ]
        )
    headers = [
        "material",
        "relative %",
        "paper",
        "% of h",
        "paper",
        "% of h, smallest f",
        "paper",
    ]
    parts.append(f"fit (means over the load cases)\n{table(headers, rows)}")
    for name, done in results.items():
        r = done["result"]
        cases = [c.get("name") or f"case {i + 1}" for i, c in enumerate(specs[name]["load_cases"])]
        parts.append(f"{name}\n{table(DISCREPANCY_HEADERS, discrepancy_rows(r, cases))}")
        parts += verdict_lines(r.get("verdict"))[:1]  # the grade and its summary
        parts += [f"warning: {w}" for w in r.get("warnings", [])]
    return "\n\n".join(parts) + f"\n\n{PAPER_NOTE}"


def _force(spec: dict[str, Any], j: int) -> float:
    """The largest force vector's length in load case ``j``, N."""
    return max(sum(c * c for c in f["vector"]) ** 0.5 for f in spec["load_cases"][j]["forces"])


def main() -> None:
    url = os.environ.get("FPM_URL")
    stack = nullcontext(url) if url else local_stack(workers=2, port=free_port(), log_dir=LOG_DIR)
    with stack as base_url:
        print(f"service: {base_url}" + ("" if url else f" (logs in {LOG_DIR}/)"), flush=True)
        print(f"web view, live while the demo runs: {base_url}/", flush=True)
        with Client(base_url, api_key=os.environ.get("FPM_API_KEY")) as client:
            specs = {name: read_spec(EXAMPLES / f"{name}.json") for name in PAPER}
            submitted = {name: client.calibrate(spec) for name, spec in specs.items()}
            results = {}
            for name, calibration in submitted.items():
                results[name] = client.wait(calibration["id"])
                if results[name]["status"] != "succeeded":
                    raise SystemExit(f"{name}: {results[name]['status']} {results[name]['error']}")
    print()
    print(report(results, specs))
    print()
    print(web_view_hint(url))


def web_view_hint(url: str | None) -> str:
    """The demo's last line: where to look at the results in a browser."""
    if url:
        return f"web view: {url.rstrip('/')}/"
    return (
        f"web view: {STACK_URL}/ once the stack runs again (`make run`; the results are kept "
        "in ./data)"
    )


if __name__ == "__main__":
    main()
