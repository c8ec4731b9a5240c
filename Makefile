# The README names these targets. `make test` works on a fresh machine: it creates
# .venv, installs the package with its test dependencies, lints, and runs pytest.
VENV ?= .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed
BENCH_STAMP := $(VENV)/.installed-bench

.PHONY: install sparse browser nginx wrk test test-fast lint audit demo bench clean

$(PY):
	python3 -m venv $(VENV)

$(STAMP): pyproject.toml | $(PY)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q -e '.[dev]'
	touch $(STAMP)

install: $(STAMP)

# the benchmarks' peers (scikit-learn, CHOLMOD)
$(BENCH_STAMP): $(STAMP) | sparse
	$(PY) -m pip install -q -e '.[dev,bench]'
	touch $(BENCH_STAMP)

# scikit-sparse (CHOLMOD, the benchmarks' peer of bdf.sparse) builds against Debian's
# SuiteSparse 5; installed here when we may (root with apt-get), else a clear stop
sparse:
	@[ -e /usr/include/suitesparse/cholmod.h ] || { [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null && \
	  { apt-get install -y -q libsuitesparse-dev libopenblas0-pthread >/dev/null || \
	    { apt-get update -q && apt-get install -y -q libsuitesparse-dev libopenblas0-pthread >/dev/null; }; }; } || \
	  { echo "CHOLMOD headers missing: apt-get install libsuitesparse-dev libopenblas0-pthread, then make again"; exit 1; }

# the viewer test drives Debian's Chromium; installed here when we may (root with apt-get)
browser:
	@command -v chromium >/dev/null || { [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null && \
	  { apt-get install -y -q chromium >/dev/null || { apt-get update -q && apt-get install -y -q chromium >/dev/null; }; }; } || \
	  echo "chromium is not installed: the viewer test skips (fails under BDF_TEST_BROWSER=required)"

# the production edge's test runs docker/nginx.conf in Debian's nginx; installed here when we may
nginx:
	@command -v nginx >/dev/null || [ -x /usr/sbin/nginx ] || { [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null && \
	  { apt-get install -y -q nginx-light >/dev/null || { apt-get update -q && apt-get install -y -q nginx-light >/dev/null; }; }; } || \
	  echo "nginx is not installed: the edge test skips (fails under BDF_TEST_NGINX=required)"

# bench_service drives its load with wrk (a C load generator); installed here when we may
wrk:
	@command -v wrk >/dev/null || { [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null && \
	  { apt-get install -y -q wrk >/dev/null || { apt-get update -q && apt-get install -y -q wrk >/dev/null; }; }; } || \
	  { echo "wrk is not installed: apt-get install wrk (Debian/Ubuntu), then make bench again"; exit 1; }

lint: install
	$(VENV)/bin/ruff check .
	$(VENV)/bin/ruff format --check .
	$(VENV)/bin/hadolint docker/Dockerfile

# known vulnerabilities of what is installed (PyPI's advisory data, through the registry)
audit: install
	$(VENV)/bin/pip-audit --progress-spinner off --skip-editable

test: lint browser nginx
	$(PY) -m pytest

# the tests not marked slow (no servers, subprocesses or real samples): under two minutes
test-fast: lint
	$(PY) -m pytest -m 'not slow'

demo: install
	$(VENV)/bin/bdf demo --out demo-output

bench: $(BENCH_STAMP) wrk
	$(PY) bench/bench_core.py
	$(PY) bench/bench_tiles.py
	$(PY) bench/bench_lattice.py
	$(PY) bench/bench_service.py
	$(PY) bench/bench_planner.py
	$(PY) bench/bench_build.py
	$(PY) bench/bench_load.py
	$(PY) bench/bench_fuzz.py

clean:
	rm -rf $(VENV) .pytest_cache .ruff_cache
