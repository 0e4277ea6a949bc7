"""Plain-text tables for the command line and the demo."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any


def printable(text: str) -> str:
    """``text`` with unprintable characters escaped (``\\x1b``, ``\\r``): names come from the
    server, and one stored before it refused control characters could drive the terminal."""
    if text.isprintable():
        return text
    return "".join(c if c.isprintable() else repr(c)[1:-1] for c in text)


def cell(value: Any) -> str:
    """A readable cell: floats to 5 significant digits, None as '-', text escaped
    (:func:`printable`)."""
    if value is None:
        return "-"
    if isinstance(value, float):
        return f"{value:.5g}"
    return printable(str(value))


def table(headers: Sequence[str], rows: Sequence[Sequence[Any]]) -> str:
    """Columns padded to their widest cell; numbers right-aligned (None cells, shown as '-',
    do not make a column text)."""
    cells = [[cell(v) for v in row] for row in rows]
    widths = [max([len(h)] + [len(r[i]) for r in cells]) for i, h in enumerate(headers)]
    numeric = [
        all(isinstance(row[i], int | float) for row in rows if row[i] is not None)
        for i in range(len(headers))
    ]

    def line(values: Sequence[str]) -> str:
        columns = zip(values, widths, numeric, strict=True)
        return "  ".join(v.rjust(w) if num else v.ljust(w) for v, w, num in columns).rstrip()

    out = [line(headers), line(["-" * w for w in widths])]
    out += [line(r) for r in cells]
    return "\n".join(out)


def verdict_lines(verdict: dict[str, Any] | None, indent: str = "") -> list[str]:
    """The fit's verdict (a result's ``verdict``) as lines: the grade in capitals with its
    summary, then each parameter at a bound and each likely cause with its action; none for a
    result stored before verdicts."""
    if not verdict:
        return []
    grade = verdict["grade"]
    summary = printable(verdict["summary"])
    lines = [f"verdict: {grade.upper()}{summary[len(grade) :]}"]
    floor = verdict.get("floor") or {}
    if floor:
        lines.append(f"  floor: {printable(floor['what'])} ({floor['source']})")
    lines += [
        f"  cause: {printable(c['cause'])}: {printable(c['detail'])}; "
        f"action: {printable(c['action'])}"
        for c in verdict.get("causes") or []
    ]
    return [indent + line for line in lines]
