PYTHON ?= python3
VENV ?= .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed

.PHONY: venv test lint bench replicate demo run clean

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q -e '.[dev]'
	touch $(STAMP)

venv: $(STAMP)

test: $(STAMP)
	$(PY) -m pytest -q

lint: $(STAMP)
	$(VENV)/bin/ruff check fpm fpmcal store worker service stack client tests bench
	$(VENV)/bin/ruff format --check fpm fpmcal store worker service stack client tests bench
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
	rm -rf $(VENV) .pytest_cache .mypy_cache .ruff_cache
