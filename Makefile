# Two commands do everything on a fresh machine (Python 3.11, Debian):
#   make demo   -- set up .venv, then run the demo on built-in synthetic data
#   make test   -- set up .venv, then lint (ruff, mypy) and run the test suite
#   make quick  -- the tests without the slow ones (pytest -m "not slow"), for a local loop
PYTHON ?= python3
VENV   ?= .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed

.PHONY: setup demo test quick lint bench clean sysdeps

setup: sysdeps $(STAMP)

# open3d needs the system library libusb-1.0 (import fails without it on a fresh machine).
sysdeps:
	@bash scripts/ensure_sysdeps.sh

$(STAMP): pyproject.toml
	@test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e ".[dev]"
	@touch $(STAMP)

demo: setup
	$(BIN)/snaps-graph demo --out results/demo

lint: setup
	$(BIN)/ruff check snaps_graph tests benchmarks experiments
	$(BIN)/ruff format --check snaps_graph tests benchmarks experiments
	$(BIN)/mypy

test: lint
	$(BIN)/python -m pytest -q

quick: setup
	$(BIN)/python -m pytest -q -m "not slow"

bench: setup
	$(BIN)/python benchmarks/run_all.py

clean:
	rm -rf $(VENV) results .pytest_cache .mypy_cache .ruff_cache
