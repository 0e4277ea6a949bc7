"""``make demo``: calibrate the paper's materials A and B through the SDK.

Starts the local stack (Redis, API, 2 workers; see :mod:`service.stack`) unless $FPM_URL
names a running service, submits examples/paper-material-a.json and -b.json, shows their
progress, prints the fitted (k, d, depth) and the discrepancies beside the paper's Table 1,
and stops the stack. Stored results survive in ./data: a second run answers at once.
"""

from __future__ import annotations

import os
from contextlib import nullcontext
from pathlib import Path

from service.redis_server import free_port
from service.stack import local_stack

from .sdk import Client, read_spec
from .table import table

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"
PAPER = {
    "paper-material-a": {"k": 38.60, "d": 20.36, "depth": 10},
    "paper-material-b": {"k": 358.6, "d": 313.6, "depth": 10},
}
"""Choi et al. 2004, Table 1."""
LOG_DIR = Path("data") / "logs"
"""Where the demo's API and workers log."""
PAPER_DISCREPANCY = "paper: mean discrepancy about 9% of h, 1.4% at the smallest force"


def report(results: dict[str, dict], specs: dict[str, dict]) -> str:
    """The fitted parameters beside the paper's, then the discrepancy per load case."""
    rows = []
    for name, done in results.items():
        r, paper = done["result"], PAPER[name]
        rows.append([name, r["k"], paper["k"], r["d"], paper["d"], r["depth"], paper["depth"]])
    fitted = table(["material", "k N/m", "paper k", "d N s/m", "paper d", "depth", "paper"], rows)
    rows = []
    for name, done in results.items():
        r = done["result"]
        cases = [c.get("name") or f"case {i + 1}" for i, c in enumerate(specs[name]["load_cases"])]
        for case, disc, steps in zip(cases, r["discrepancy"], r["settle_steps"], strict=True):
            rows.append([name, case, disc, steps])
        rows.append([name, "mean", sum(r["discrepancy"]) / len(r["discrepancy"]), "-"])
    per_case = table(["material", "load case", "discrepancy % h", "settle steps"], rows)
    return f"{fitted}\n\n{per_case}\n({PAPER_DISCREPANCY})"


def main() -> None:
    url = os.environ.get("FPM_URL")
    stack = nullcontext(url) if url else local_stack(workers=2, port=free_port(), log_dir=LOG_DIR)
    with stack as base_url:
        print(f"service: {base_url}" + ("" if url else f" (logs in {LOG_DIR}/)"), flush=True)
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


if __name__ == "__main__":
    main()
