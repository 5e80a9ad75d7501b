# The README's first two commands are `make demo` and `make test`.
# Each one creates (or refreshes, when pyproject.toml changed) .venv and installs jmocap into it.
PYTHON ?= python3
VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.jmocap-installed

.PHONY: demo test test-slow test-all lint bench clean

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e '.[test]'
	touch $(STAMP)

demo: $(STAMP)
	$(PY) -m jmocap.cli demo --out demo_out

test: $(STAMP)
	$(PY) -m pytest -q

test-slow: $(STAMP)
	$(PY) -m pytest -q -m slow

test-all: $(STAMP)
	$(PY) -m pytest -q -m 'slow or not slow'

lint: $(STAMP)
	$(PY) -m pip install --quiet ruff
	$(PY) -m ruff check src tests experiments

bench: $(STAMP)
	$(PY) experiments/bench_physics.py
	$(PY) experiments/bench_projection.py
	$(PY) experiments/bench_reconstruct.py

clean:
	rm -rf $(VENV) .pytest_cache
