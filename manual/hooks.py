"""mkdocs hooks (mkdocs.yml, ``hooks:``): the reference pages' generated parts
(:mod:`manual.reference`)."""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from manual.reference import expand  # noqa: E402


def on_page_markdown(markdown: str, **kwargs: Any) -> str:
    return expand(markdown)
