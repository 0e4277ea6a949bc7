"""The example specs shown in the OpenAPI docs (from the repository's examples/ folder)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

EXAMPLES_DIR = Path(__file__).resolve().parents[1] / "examples"


def openapi_examples() -> dict[str, Any]:
    """{name: {summary, value}} for every examples/*.json (none if the folder is absent)."""
    return {
        path.stem: {"summary": json.loads(path.read_text()).get("name", path.stem), "value": spec}
        for path in sorted(EXAMPLES_DIR.glob("*.json"))
        if (spec := json.loads(path.read_text()))
    }
