# The README names these targets. `make test` works on a fresh machine: it creates
# .venv, installs the package with its test dependencies, lints, and runs pytest.
VENV ?= .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed

.PHONY: install test lint demo bench clean

$(PY):
	python3 -m venv $(VENV)

$(STAMP): pyproject.toml | $(PY)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q -e '.[dev,bench]'
	touch $(STAMP)

install: $(STAMP)

lint: install
	$(VENV)/bin/ruff check .
	$(VENV)/bin/ruff format --check .

test: lint
	$(PY) -m pytest

demo: install
	$(VENV)/bin/bdf demo --out demo-output

bench: install
	$(PY) bench/bench_core.py
	$(PY) bench/bench_tiles.py
	$(PY) bench/bench_service.py
	$(PY) bench/bench_planner.py

clean:
	rm -rf $(VENV) .pytest_cache .ruff_cache
