# One entry for newcomers and CI: `make demo`, `make test` (README, .ci/run).
# Both install the Debian build dependencies, build the wheel, install it into a fresh-ish
# virtual environment (.venv) and run from there, so what is tested is what users install.
SHELL := /bin/bash
PYTHON ?= python3
VENV ?= .venv
PY := $(VENV)/bin/python
SUDO := $(shell [ "$$(id -u)" = 0 ] || echo sudo)
APT_PACKAGES := libceres-dev libeigen3-dev cmake g++ python3-dev python3-venv

.PHONY: deps venv install test demo wheel-check dev bench clean

deps:
	@if dpkg -s $(APT_PACKAGES) >/dev/null 2>&1; then echo "Debian packages present"; else \
	  $(SUDO) apt-get update -qq && \
	  DEBIAN_FRONTEND=noninteractive $(SUDO) apt-get install -y -qq $(APT_PACKAGES); fi

$(PY):
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip

venv: $(PY)

# Build the wheel (with build isolation), install it with its runtime + test dependencies.
install: deps venv
	rm -rf dist
	$(PY) -m pip wheel -q --no-deps -w dist .
	whl=$$(ls dist/fusedmosaic-*.whl) && \
	  $(PY) -m pip install -q "$$whl[test]" && \
	  $(PY) -m pip install -q --force-reinstall --no-deps "$$whl"

# The wheel imports its compiled core from a fresh virtual environment.
wheel-check: install
	cd /tmp && $(CURDIR)/$(PY) -c "import fusedmosaic._core as c; print('fusedmosaic._core', c.__version__, 'from', c.__file__)"

# The test files on 2 workers (pytest-xdist; a file's tests stay together, so its module
# fixtures are computed once), then alone the tests marked realtime (live replays that measure
# their processing time, sockets: beside another worker's load they drop frames, and once a
# start-up failed in CI). The same tests serially: python -m pytest -q.
test: wheel-check
	$(PY) -m pytest -q -n 2 --dist loadfile -m "not realtime"
	$(PY) -m pytest -q -m realtime

demo: install
	$(VENV)/bin/fusedmosaic demo --out demo_out

# Benchmarks (issue 7, bench/run_all.py): the papers' tables, the peers and the C++ solver core in
# one run from the installed wheel, <= 20 min on 2 cores; writes bench/results/*.json,
# bench/results/summary.md and README's "## Performance". Smoke run: make bench BENCH_ARGS=--quick
bench: install
	$(PY) bench/run_all.py $(BENCH_ARGS)

# Developer loop: editable install with an incremental C++ build in build/dev.
# Into the Python given (an active virtual environment, or e.g. PYTHON=.venv/bin/python after
# make venv: Debian's own python3 is externally managed); no build isolation, so the build
# requirements are installed first.
dev: deps
	$(PYTHON) -m pip install -q "scikit-build-core>=0.10" "pybind11>=2.12"
	$(PYTHON) -m pip install --no-build-isolation -e ".[test]" -C build-dir=build/dev

clean:
	rm -rf build dist $(VENV) demo_out
