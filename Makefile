# The README's first two commands are `make demo` and `make test`.
# Each one creates (or refreshes, when pyproject.toml changed) .venv and installs jmocap into it,
# editable, with the `test` extra (pytest, the reference QP solvers and the `viz` extra that
# the demo's video and the render tests need).
PYTHON ?= python3
VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.jmocap-installed

.PHONY: demo test test-slow test-all lint bench clean clean-cache wheel-smoke

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e '.[test]'
	touch $(STAMP)

# Build a wheel, install it (not editable) into a fresh venv and run the demo outside the tree.
wheel-smoke:
	PYTHON=$(PYTHON) .ci/wheel_smoke.sh

demo: $(STAMP)
	$(PY) -m jmocap.cli demo --out demo_out

# One pytest invocation for the whole suite, on PYTEST_WORKERS pytest-xdist workers (one per
# core; each takes whole files, so a module's fixtures and compiled programs stay in one
# process). tests/conftest.py gives every worker one persistent compilation cache
# (~/.cache/jmocap/xla-tests, or $JMOCAP_TEST_XLA_CACHE) and frees compiled programs after each module:
# a single long process used to run out of memory mappings (vm.max_map_count) and segfault in
# XLA's CPU compiler (docs/performance.md, section 5). PYTEST_WORKERS=0 runs in this process.
PYTEST_WORKERS ?= 2
PYTEST := $(PY) -m pytest -q -n $(PYTEST_WORKERS) --dist loadfile

test: $(STAMP)
	$(PYTEST)

test-slow: $(STAMP)
	$(PYTEST) -m slow

test-all: $(STAMP)
	$(PYTEST) -m 'slow or not slow'

lint: $(STAMP)
	$(PY) -m pip install --quiet ruff
	$(PY) -m ruff check src tests experiments

bench: $(STAMP)
	$(PY) experiments/bench_physics.py
	$(PY) experiments/bench_projection.py
	$(PY) experiments/bench_reconstruct.py

clean:
	rm -rf $(VENV) .pytest_cache

# the test suite's persistent XLA compilation cache (kept across clones: tests/conftest.py)
clean-cache:
	rm -rf "$${XDG_CACHE_HOME:-$$HOME/.cache}/jmocap/xla-tests"
