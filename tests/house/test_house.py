"""The repository reads as what the code is, not how it was reached: no text names a sitting, a
round, a session, a branch or an issue number; no page of the manual and no Python module is
longer than one idea needs; the product never imports the research; and every file, page,
anchor and section that a page or a docstring cites exists.

The research record (what was tried, measured and rejected) lives in dated design notes under
docs/notes/; they are held to the same rules. mkdocs --strict checks the manual's own links and
anchors when it builds; these tests also check what it does not read: README.md, the paths and
sections named in prose (``docs/physics.md, *Topic*``, ``fpm/model/spec/``), and the docstrings
and comments of every Python file.
"""

from __future__ import annotations

import ast
import io
import re
import subprocess
import tokenize
import unicodedata
from functools import cache
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
DOCS = ROOT / "docs"
HERE = Path(__file__).resolve().relative_to(ROOT).as_posix()

MAX_WORDS = 2500
"""The most words (``wc -w``) a page under docs/ may have: one idea, said shortly."""
MAX_LINES = 600
"""The most lines (``wc -l``) a Python module of ours may have: one idea, in modules of its own."""
CODE = ("fpm", "worker", "service", "client", "fpmcal", "bench", "research", "store", "stack",
        "manual")  # fmt: skip
"""The packages whose modules are held to MAX_LINES."""
PRODUCT = ("fpm", "worker", "service", "client", "fpmcal", "bench", "store", "stack")
"""The packages of the product: research (the studies behind the notes) sits beside them."""

ORDINALS = (
    "first|second|third|fourth|fifth|sixth|seventh|eighth|ninth|tenth|eleventh|twelfth|"
    "thirteenth|fourteenth|fifteenth|sixteenth|seventeenth|eighteenth|nineteenth|twentieth|"
    r"[0-9]+(?:st|nd|rd|th)"
)
MARKERS = re.compile(
    "|".join(
        [
            r"\bround[\s-]+[0-9]+",  # "round 5", "round-2", "(round 4's seventh stop ...)"
            rf"\b(?:{ORDINALS})\s+(?:session|sitting|stop)s?\b",  # "thirteenth session"
            r"\b(?:session|sitting|stop)\s+[0-9]+\b",  # "session 2", "stop 57"
            r"\bsittings?\b",
            r"\b(?:this|that|another|other|last|previous|next|earlier)\s+sessions?(?:'s?)?\s",
            r"\bon\s+(?:the\s+)?branch\b",  # "Written on branch `real-organs`"
            r"\bissues?\s+#?[0-9]+",  # "issue 43", "issue #32"
            r"(?<![\w&/#])#[0-9]{1,2}\b",  # "#43" (a colour, #111 or #243447, has more digits)
        ]
    ),
    re.IGNORECASE,
)
"""Words that date a text by the work that made it rather than say what is."""

TEXT_SUFFIXES = {
    ".py", ".md", ".js", ".html", ".css", ".toml", ".yml", ".yaml", ".txt", ".cfg", ".ini",
    ".json", ".svg", ".c", ".h", ".sh", ".in", "",
}  # fmt: skip
"""Tracked files read as text (others, e.g. images and meshes, are skipped)."""


@cache
def tracked() -> tuple[str, ...]:
    """The repository's tracked files (``git ls-files``), as paths from its root."""
    out = subprocess.run(
        ["git", "ls-files", "-z"], cwd=ROOT, capture_output=True, check=True
    ).stdout
    return tuple(p for p in out.decode().split("\0") if p)


def is_vendored(path: str) -> bool:
    """Third-party files kept as they came: anything under a vendor/ directory, minified code."""
    return "/vendor/" in f"/{path}" or path.endswith((".min.js", ".min.css"))


def text_files() -> list[str]:
    """Tracked text files of the project's own (not vendored, not this file), that exist."""
    files = []
    for path in tracked():
        full = ROOT / path
        if path == HERE or is_vendored(path) or Path(path).suffix not in TEXT_SUFFIXES:
            continue
        if not full.is_file():
            continue
        head = full.read_bytes()[:8192]
        if b"\0" in head:  # binary
            continue
        files.append(path)
    return files


def read(path: str | Path) -> str:
    return (ROOT / path).read_text(encoding="utf-8", errors="replace")


def markers_in(text: str) -> list[tuple[int, str]]:
    """(line, the marker's words) for every history marker in ``text``."""
    return [
        (text.count("\n", 0, m.start()) + 1, m.group(0).strip()) for m in MARKERS.finditer(text)
    ]


def test_no_text_names_a_sitting_a_round_a_branch_or_an_issue():
    found = [
        f"{path}:{line}: {words!r}"
        for path in text_files()
        for line, words in markers_in(read(path))
    ]
    assert found == [], "history markers (say what is, or date it in a note):\n" + "\n".join(found)


@pytest.mark.parametrize(
    "text",
    [
        "the organ at 6.5 mm (round 5, eighth session)",
        "Written on branch `real-organs`",
        "as issue 43 asked",
        "closes #43",
        "measured at the 57th stop",
        "on this session's machine",
        "stop 57",
    ],
)
def test_a_planted_marker_is_found(text):
    assert markers_in(f"A line.\n{text}.\n")


@pytest.mark.parametrize(
    "text",
    [
        'stroke: "#111"',
        "fill: #333;",
        "a session fixture of pytest, the browser tab's session storage",
        "the polish's first round",
        "the walk's first step",
    ],
)
def test_what_is_not_a_marker(text):
    assert markers_in(text) == []


def pages() -> list[Path]:
    """Every markdown page under docs/, design notes included."""
    return sorted(DOCS.rglob("*.md"))


def test_no_page_is_longer_than_one_idea_needs():
    long = {
        p.relative_to(ROOT).as_posix(): n
        for p in pages()
        if (n := len(p.read_text(encoding="utf-8").split())) > MAX_WORDS
    }
    assert long == {}, f"pages over {MAX_WORDS} words (split them: one idea a page): {long}"


# ----------------------------------------------------------------------------- citations

FENCE = re.compile(r"^(```|~~~).*?^\1\s*$", re.MULTILINE | re.DOTALL)
HEADING = re.compile(r"^(#{1,6})[ \t]+(.+?)[ \t]*#*[ \t]*$", re.MULTILINE)
LEAD = re.compile(r"(?:^|\n)\s*(?:[-*]|[0-9]+\.)?\s*\*\*(.+?)\*\*", re.DOTALL)
ITALIC_LEAD = re.compile(r"(?:^|\n)\s*(?:[-*]|[0-9]+\.)\s+\*([^*\n]+)\*")
LINK = re.compile(r"(?<!!)\[(?:[^\]]|\][^(])*?\]\(([^)\s]+)(?:\s+\"[^\"]*\")?\)")
ROOTS = "fpm|fpmcal|bench|research|tests|docs|service|worker|store|stack|client|manual|examples"
PATH = re.compile(rf"(?<![\w/.-])((?:{ROOTS})/[\w./-]*[\w/])")
CITED_SUFFIXES = (".py", ".md", ".json", ".js", ".vtu", ".yml", ".html", ".c", ".css")
SECTION = re.compile(
    r"((?:[\w.-]+/)*[\w.-]+\.md|README)(?:'s)?\)?[,:]?\s+(?:\([^()]*\)\s*)?"
    r"((?:[*\"][^*\"]{2,100}[*\"](?:\s*(?:,|;|and)\s*)?)+)"
)
NEARBY = re.compile(r"\*([^*]{3,100})\*,?\s+(?:below|above)\b")


def without_code(markdown: str) -> str:
    """The markdown with its fenced code blocks blanked (lines kept)."""
    return FENCE.sub(lambda m: "\n" * m.group(0).count("\n"), markdown)


def prose(path: str) -> str:
    """What a reader reads as text in ``path``: a markdown page without its code (fenced blocks
    and inline code spans), or a Python file's strings and comments (its docstrings), each on a
    line of its own."""
    text = read(path)
    if path.endswith(".md"):
        return re.sub(r"`[^`\n]*`", "", without_code(text))
    parts = []
    for token in tokenize.generate_tokens(io.StringIO(text).readline):
        if token.type == tokenize.COMMENT:
            parts.append(token.string.lstrip("#"))
        elif token.type == tokenize.STRING:
            parts.append(token.string)
    return "\n".join(parts)


def plain(text: str) -> str:
    """Heading or citation text as the reader sees it: no markup, one space, no end stops."""
    text = re.sub(r"\[([^\]]*)\]\([^)]*\)", r"\1", text)  # links: their text
    text = re.sub(r"\{[#.][^}]*\}", "", text)  # attr_list
    text = text.replace("`", "").replace("*", "").replace("_", " ")
    return re.sub(r"\s+", " ", text).strip(" .:;,").lower()


def slugify(text: str) -> str:
    """Python-Markdown's toc slug (mkdocs' default) of a heading's text."""
    text = re.sub(r"\[([^\]]*)\]\([^)]*\)", r"\1", text).replace("`", "").replace("*", "")
    value = unicodedata.normalize("NFKD", text).encode("ascii", "ignore").decode("ascii")
    value = re.sub(r"[^\w\s-]", "", value).strip().lower()
    return re.sub(r"[-\s]+", "-", value)


@cache
def anchors(page: Path) -> frozenset[str]:
    """The anchors mkdocs gives ``page``'s headings (duplicates numbered _1, _2, ...)."""
    seen: dict[str, int] = {}
    out = set()
    for m in HEADING.finditer(without_code(page.read_text(encoding="utf-8"))):
        custom = re.search(r"\{#([\w-]+)\}", m.group(2))
        slug = custom.group(1) if custom else slugify(m.group(2))
        n = seen.get(slug, 0)
        seen[slug] = n + 1
        out.add(slug if n == 0 else f"{slug}_{n}")
    return frozenset(out)


@cache
def sections(page: Path) -> tuple[str, ...]:
    """What a citation may name in ``page``: its headings, and its paragraphs' and list items'
    bold (or, for list items, italic) leads, as plain text."""
    text = without_code(page.read_text(encoding="utf-8"))
    found = [m.group(2) for m in HEADING.finditer(text)]
    found += [m.group(1) for m in LEAD.finditer(text)]
    found += [m.group(1) for m in ITALIC_LEAD.finditer(text)]
    return tuple(plain(s) for s in found)


@cache
def linked_pages(page: Path) -> tuple[Path, ...]:
    """The markdown pages ``page`` links to (an index page's topics live there)."""
    out = []
    for m in LINK.finditer(without_code(page.read_text(encoding="utf-8"))):
        target = m.group(1).split("#")[0]
        if target.endswith(".md") and (page.parent / target).resolve().is_file():
            out.append((page.parent / target).resolve())
    return tuple(out)


def names_section(page: Path, cited: str) -> bool:
    """Whether ``cited`` is a section of ``page`` (or, on an index page, of a page it links):
    a heading or lead that is it, or holds it between word boundaries ("The volume term" in
    "The model's energy: springs and the volume term")."""
    want = plain(cited)
    if not want:
        return True

    def hit(candidates: tuple[str, ...]) -> bool:
        return any(re.search(rf"(?<!\w){re.escape(want)}(?!\w)", s) for s in candidates)

    return hit(sections(page)) or any(hit(sections(p)) for p in linked_pages(page))


def cited_file(source: str, target: str) -> Path | None:
    """The file a citation in ``source`` names: from the repository's root, from docs/, or
    from the citing page's folder; None if none exists."""
    here = (ROOT / source).parent
    for base in (ROOT, DOCS, here):
        full = (base / target).resolve()
        if full.exists():
            return full
    if target == "README":
        return ROOT / "README.md"
    return None


def flat(text: str) -> str:
    """Text with its line breaks (and the comment marks that continue a comment) as spaces, so
    that a citation wrapped over two lines reads as one."""
    return re.sub(r"[ \t]*\n[ \t]*(?:#+(?!#)[ \t]?|//[ \t]?)?", " ", text)


def citing_files() -> list[str]:
    """The project's own markdown pages and Python files, and the README."""
    return [p for p in text_files() if p.endswith((".md", ".py"))]


def test_every_cited_file_exists():
    missing = []
    for source in citing_files():
        text = read(source)
        for m in PATH.finditer(text):
            target = m.group(1).rstrip(".")
            if any(c in target for c in "{}<>*") or re.search(r"/[A-Z]+\.", target):
                continue  # a template (docs/bench/NAME.md, bench/results/{part}.json)
            if not (target.endswith("/") or target.endswith(CITED_SUFFIXES)):
                continue
            if cited_file(source, target) is None:
                line = text.count("\n", 0, m.start()) + 1
                missing.append(f"{source}:{line}: {target}")
    assert missing == [], "cited files that do not exist:\n" + "\n".join(missing)


def test_every_markdown_link_resolves_to_a_page_and_an_anchor():
    broken = []
    for source in citing_files():
        if not source.endswith(".md"):
            continue
        page = ROOT / source
        text = without_code(read(source))
        for m in LINK.finditer(text):
            target = m.group(1)
            if re.match(r"[a-z]+:", target) or target.startswith("/"):
                continue  # a URL, or the served site's own absolute path
            path, _, anchor = target.partition("#")
            full = (page.parent / path).resolve() if path else page
            line = text.count("\n", 0, m.start()) + 1
            if not full.exists():
                broken.append(f"{source}:{line}: {target} (no such file)")
            elif anchor and full.suffix == ".md" and anchor not in anchors(full):
                broken.append(f"{source}:{line}: {target} (no such heading)")
    assert broken == [], "links that do not resolve:\n" + "\n".join(broken)


def test_every_cited_section_is_a_heading_of_its_page():
    stale = []
    for source in citing_files():
        text = flat(prose(source))
        for m in SECTION.finditer(text):
            page = cited_file(source, m.group(1))
            if page is None or page.suffix != ".md":
                continue  # the file itself is checked by test_every_cited_file_exists
            for cited in re.findall(r"[*\"]([^*\"]{2,100})[*\"]", m.group(2)):
                if not names_section(page, cited):
                    where = page.relative_to(ROOT).as_posix()
                    stale.append(f"{source}: {where}, *{cited}*")
        if source.endswith(".md") and source.startswith("docs/"):
            for m in NEARBY.finditer(text):
                if not names_section(ROOT / source, m.group(1)):
                    stale.append(f"{source}: *{m.group(1)}* (below/above, on the same page)")
    assert stale == [], "cited sections that no heading names:\n" + "\n".join(stale)


def test_the_citation_checks_find_what_is_stale(tmp_path):
    """The checks above on planted text: a stale section, a stale anchor."""
    page = DOCS / "physics.md"
    assert names_section(page, "Annealing machinery")
    assert names_section(page, "d from the spectrum")
    assert not names_section(page, "Round 2")
    assert "annealing-machinery" in anchors(DOCS / "explanation" / "physics" / "calibration.md")
    assert slugify("Caps: `fpm.max_steps`") == "caps-fpmmax_steps"
    assert cited_file("README.md", "fpm/io/meshes.py") is None
    assert cited_file("README.md", "fpm/io/meshes/") is not None


# ----------------------------------------------------------------------------- modules


def modules(package: str) -> list[Path]:
    """The Python modules of ``package`` (a folder at the repository's root)."""
    return sorted(p for p in (ROOT / package).rglob("*.py") if "__pycache__" not in p.parts)


def test_no_module_is_longer_than_one_idea_needs():
    long = {
        p.relative_to(ROOT).as_posix(): n
        for package in CODE
        for p in modules(package)
        if (n := p.read_text(encoding="utf-8").count("\n")) > MAX_LINES
    }
    assert long == {}, f"modules over {MAX_LINES} lines (split them: one idea a module): {long}"


def imported(path: Path) -> set[str]:
    """The top-level names of the modules ``path`` imports, lazy imports in functions included
    (a relative import is its own package's, never another's)."""
    names = set()
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.Import):
            names.update(a.name.split(".")[0] for a in node.names)
        elif isinstance(node, ast.ImportFrom) and not node.level and node.module:
            names.add(node.module.split(".")[0])
    return names


def test_the_product_never_imports_the_research():
    found = [
        p.relative_to(ROOT).as_posix()
        for package in PRODUCT
        for p in modules(package)
        if "research" in imported(p)
    ]
    assert found == [], (
        "product modules that import research (it may import them, not back):\n" + "\n".join(found)
    )


def test_the_module_checks_find_what_they_look_for(tmp_path):
    """The checks above on planted modules: a lazy import of research, a relative one."""
    lazy = tmp_path / "lazy.py"
    lazy.write_text("def f():\n    from research import graded\n")
    relative = tmp_path / "relative.py"
    relative.write_text("from .research import x\nimport researchers\n")
    assert "research" in imported(lazy)
    assert "research" not in imported(relative)
    assert len(modules("research")) > 0
