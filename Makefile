PYTHON ?= python3
VENV ?= .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed

.PHONY: venv docs test lint bench replicate demo run clean

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q -e '.[dev]'
	touch $(STAMP)

venv: $(STAMP)

# The manual (docs/ -> site/, served at /guide): --strict turns every warning (a broken link, an
# unresolved reference) into a failure. `make test` builds it first, so CI (.ci/run) checks it
# and the tests of /guide have a site to serve.
docs: $(STAMP)
	NO_MKDOCS_2_WARNING=1 $(VENV)/bin/mkdocs build --strict -q

test: docs
	$(PY) -m pytest -q

lint: $(STAMP)
	$(VENV)/bin/ruff check fpm fpmcal store worker service stack client tests bench research manual
	$(VENV)/bin/ruff format --check fpm fpmcal store worker service stack client tests bench research manual
	$(VENV)/bin/mypy fpm fpmcal store worker service stack client

bench: $(STAMP)
	$(PY) -m bench

replicate: $(STAMP)
	$(PY) -m bench.replicate

demo: $(STAMP)
	$(PY) -m client.demo

run: $(STAMP)
	$(VENV)/bin/fpmcal up

clean:
	rm -rf $(VENV) site .pytest_cache .mypy_cache .ruff_cache
