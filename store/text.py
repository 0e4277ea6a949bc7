"""User text (spec and load case names): what it may hold, and how it is logged.

A name ends up in Redis, in JSON answers and in RQ job descriptions, which RQ writes to the
worker log. A control character there forges log lines (CR LF) or drives a terminal (ESC),
and a lone surrogate cannot be encoded as UTF-8 (the Redis client and the JSON answer fail).
So the service refuses such text (:func:`refusal`), and whatever user text is logged goes
through :func:`escape` first (records stored before the check may still hold it).
"""

from __future__ import annotations

import unicodedata

REFUSED_CATEGORIES = {
    "Cc": "a control character",
    "Cs": "a lone surrogate",
    "Zl": "a line separator",
    "Zp": "a paragraph separator",
}
"""Unicode categories free text may not hold, and what to call them in an error."""


def refusal(text: str) -> str | None:
    """Why ``text`` is refused as free text (its first bad character), or None if it is fine."""
    for i, char in enumerate(text):
        what = REFUSED_CATEGORIES.get(unicodedata.category(char))
        if what is not None:
            return f"holds {what} ({escape(char)}) at position {i}"
    return None


def escape(text: str) -> str:
    """``text`` with every unprintable character (control, format, surrogate, separator other
    than the space) written as a Python escape (``\\r``, ``\\x1b``, ``\\ud800``): one log line,
    ASCII-safe where it matters, readable otherwise."""
    if text.isprintable():
        return text
    return "".join(c if c.isprintable() else repr(c)[1:-1] for c in text)
