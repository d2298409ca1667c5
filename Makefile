# Two commands do everything on a fresh machine (Python 3.11, Debian):
#   make demo   -- set up .venv, then run the demo on built-in synthetic data
#   make test   -- set up .venv, then run the test suite
PYTHON ?= python3
VENV   ?= .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed

.PHONY: setup demo test bench clean sysdeps

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

test: setup
	$(BIN)/python -m pytest -q

bench: setup
	$(BIN)/python benchmarks/run_all.py

clean:
	rm -rf $(VENV) results .pytest_cache
