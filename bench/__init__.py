"""Benchmarks: `make bench` runs every bench_*.py module's main() and prints its tables."""

import json
import subprocess
import sys
from typing import Any


def child_json(module: str, *args: str) -> dict[str, Any]:
    """Run ``python -m module args...`` in a fresh process (its own memory peak, no warm
    caches) and return the JSON object its last line of output prints."""
    out = subprocess.run(
        [sys.executable, "-m", module, *args], capture_output=True, text=True, check=True
    )
    return json.loads(out.stdout.strip().splitlines()[-1])
