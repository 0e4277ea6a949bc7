"""Figures that cannot go stale: the benchmark pages of the manual and the README's
headline figures are what ``python -m bench.render`` makes of the committed
``bench/results/*.json``, and each results file says how, when, where and on which commit it was
measured."""

from __future__ import annotations

import json
import re

import pytest

from bench import render, results


def test_committed_figures_are_what_the_committed_json_renders():
    stale = [str(p.relative_to(results.ROOT)) for p in render.stale()]
    assert not stale, (
        f"these files differ from what bench/results/*.json renders: {stale}; "
        "run `python -m bench.render` (and never edit a rendered figure by hand)"
    )


def test_the_readme_carries_the_headline_block():
    text = render.README.read_text()
    block = re.search(r"<!-- bench:headline -->\n(.*?)<!-- /bench:headline -->", text, re.S)
    assert block and block.group(1).count("\n- ") + block.group(1).startswith("- ") == 5
    assert "docs/bench/" in block.group(1)


@pytest.mark.parametrize("path", sorted(results.RESULTS.glob("*.json")), ids=lambda p: p.stem)
def test_each_results_file_says_how_it_was_measured(path):
    document = json.loads(path.read_text())
    assert document["benchmark"] == path.stem and document["records"]
    for part, run in document["runs"].items():
        assert re.fullmatch(r"[0-9a-f]{40}", run["commit"]), part
        assert re.fullmatch(r"\d{4}-\d\d-\d\dT\d\d:\d\d:\d\dZ", run["date"]), part
        assert run["command"].startswith("python -m bench")
        assert run["machine"]["cores"] >= 1 and run["machine"]["cpu"]
        assert len(run["load_average"]["before"]) == 3
    assert {r["part"] for r in document["records"]} == set(document["runs"])


def test_a_saved_run_replaces_only_its_own_parts(tmp_path, monkeypatch):
    monkeypatch.setattr(results, "RESULTS", tmp_path)
    results.record("demo", "one", value=1.0)
    results.record("demo", "two", value=[2, 3])
    results.save("demo", "python -m bench demo")
    results.record("demo", "two", value=[4])
    path = results.save("demo", "python -m bench demo two")
    assert path is not None
    document = json.loads(path.read_text())
    assert [(r["part"], r["value"]) for r in document["records"]] == [("one", 1.0), ("two", [4])]
    assert document["runs"]["two"]["command"] == "python -m bench demo two"
    assert document["runs"]["one"]["command"] == "python -m bench demo"


def test_a_changed_figure_is_caught(monkeypatch):
    real = render.results()
    changed = json.loads(json.dumps(real))
    changed["replicate"]["records"][0]["k"] *= 1.01
    monkeypatch.setattr(render, "results", lambda: changed)
    assert render.PAGES / "replicate.md" in render.stale()


def test_the_readme_links_resolve_and_it_stays_short():
    """The README is the front door (at most 250 lines); every relative link or picture in it
    names a file of the repository (the manual's own links are checked by mkdocs --strict)."""
    text = render.README.read_text()
    assert len(text.splitlines()) <= 250
    targets = re.findall(r"\]\(([^)\s]+)\)", text)
    assert targets
    for target in targets:
        if re.match(r"[a-z]+://", target):
            continue
        path = (render.README.parent / target.split("#", 1)[0]).resolve()
        assert path.exists(), target
