# Two commands do everything on a fresh machine (Python 3.11, Debian):
#   make demo   -- set up .venv with the package alone (no extras), then run the demo on built-in synthetic data
#   make test   -- set up .venv with the dev extra, then lint (ruff, mypy) and run the test suite on all cores (pytest-xdist;
#                  --dist loadfile: a test file's tests share one worker, so its module-scoped fixtures are built once)
#   make quick  -- the tests without the slow ones (pytest -m "not slow"), on all cores too, for a local loop
#   make data   -- render the synthetic benchmark sequences (docs/datasets.md) into results/data/
PYTHON ?= python3
VENV   ?= .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed
CORE_STAMP := $(VENV)/.installed-core

.PHONY: setup setup-core demo test quick lint bench clean sysdeps data

setup: sysdeps $(STAMP)
setup-core: sysdeps $(CORE_STAMP)

# open3d needs the system library libusb-1.0 (import fails without it on a fresh machine).
sysdeps:
	@bash scripts/ensure_sysdeps.sh

# The package was once installed with open3d's CUDA build, which shares its files with open3d-cpu:
# it goes first, or the two would overwrite each other.
define venv_ready
	@test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	@if $(BIN)/python -m pip show --quiet open3d >/dev/null 2>&1 && [ "$$(uname -sm)" = "Linux x86_64" ]; then \
		$(BIN)/python -m pip uninstall --quiet --yes open3d; fi
endef

# The dev extra (pytest, pytest-xdist, evo, ruff, mypy, rosbags, rerun-sdk, ray): what make test needs.
$(STAMP): pyproject.toml
	$(venv_ready)
	$(BIN)/python -m pip install --quiet -e ".[dev]"
	@touch $(STAMP) $(CORE_STAMP)

# The package alone (what make demo needs); nothing to do when the dev install is current.
$(CORE_STAMP): pyproject.toml
	@if [ -f $(STAMP) ] && [ $(STAMP) -nt pyproject.toml ]; then touch $(CORE_STAMP); else \
		$(MAKE) --no-print-directory core-install; fi

.PHONY: core-install
core-install:
	$(venv_ready)
	$(BIN)/python -m pip install --quiet -e .
	@touch $(CORE_STAMP)

demo: setup-core
	$(BIN)/snaps-graph demo --out results/demo --overwrite

lint: setup
	$(BIN)/ruff check snaps_graph tests benchmarks experiments
	$(BIN)/ruff format --check snaps_graph tests benchmarks experiments
	$(BIN)/mypy  # snaps_graph and tests: [tool.mypy] files in pyproject.toml

test: lint
	$(BIN)/python -m pytest -q -n auto --dist loadfile

quick: setup
	$(BIN)/python -m pytest -q -n auto --dist loadfile -m "not slow"

bench: setup
	$(BIN)/python benchmarks/run_all.py

# The benchmarks' synthetic sequences as named recipes (docs/datasets.md). KITTI_GT holds the
# ground-truth paths NN.txt (with NN_times.txt beside them, or the official KITTI layout's
# poses/NN.txt, whose times synth finds in ../sequences/NN/times.txt). A sequence already
# rendered is kept (synth never replaces a folder without --overwrite); pick some with
# `make data DATASETS="loop300 street00_1000"`.
KITTI_GT ?= ../shared/data/kitti_gt
DATA_DIR ?= results/data
DATASETS ?= loop300 street00_400 street00_1000 open00_1000 open00_1000_rect03 open00_1000_rect10 street07 hard07 street00
SYNTH    := $(BIN)/snaps-graph synth

data: $(DATASETS:%=$(DATA_DIR)/%/poses.txt)

$(DATA_DIR)/loop300/poses.txt: | sysdeps $(CORE_STAMP)
	$(SYNTH) --trajectory loop --out $(@D)
$(DATA_DIR)/street00_400/poses.txt: | sysdeps $(CORE_STAMP)
	$(SYNTH) --trajectory $(KITTI_GT)/00.txt --frames 0:400 --out $(@D)
$(DATA_DIR)/street00_1000/poses.txt: | sysdeps $(CORE_STAMP)
	$(SYNTH) --trajectory $(KITTI_GT)/00.txt --frames 0:1000 --out $(@D)
$(DATA_DIR)/open00_1000/poses.txt: | sysdeps $(CORE_STAMP)
	$(SYNTH) --trajectory $(KITTI_GT)/00.txt --frames 0:1000 --scene open --out $(@D)
$(DATA_DIR)/open00_1000_rect03/poses.txt: | sysdeps $(CORE_STAMP)
	$(SYNTH) --trajectory $(KITTI_GT)/00.txt --frames 0:1000 --scene open --rectification-error 0.3 --out $(@D)
$(DATA_DIR)/open00_1000_rect10/poses.txt: | sysdeps $(CORE_STAMP)
	$(SYNTH) --trajectory $(KITTI_GT)/00.txt --frames 0:1000 --scene open --rectification-error 1.0 --out $(@D)
$(DATA_DIR)/street07/poses.txt: | sysdeps $(CORE_STAMP)
	$(SYNTH) --trajectory $(KITTI_GT)/07.txt --out $(@D)
$(DATA_DIR)/hard07/poses.txt: | sysdeps $(CORE_STAMP)
	$(SYNTH) --trajectory $(KITTI_GT)/07.txt --aliasing --traffic --lighting --out $(@D)
# The other dev paths (bench_loops_dev.py): 02 and 09, plain and hard, and 00 hard.
$(DATA_DIR)/street02/poses.txt: | sysdeps $(CORE_STAMP)
	$(SYNTH) --trajectory $(KITTI_GT)/02.txt --out $(@D)
$(DATA_DIR)/street09/poses.txt: | sysdeps $(CORE_STAMP)
	$(SYNTH) --trajectory $(KITTI_GT)/09.txt --out $(@D)
$(DATA_DIR)/hard00/poses.txt: | sysdeps $(CORE_STAMP)
	$(SYNTH) --trajectory $(KITTI_GT)/00.txt --aliasing --traffic --lighting --out $(@D)
$(DATA_DIR)/hard02/poses.txt: | sysdeps $(CORE_STAMP)
	$(SYNTH) --trajectory $(KITTI_GT)/02.txt --aliasing --traffic --lighting --out $(@D)
$(DATA_DIR)/hard09/poses.txt: | sysdeps $(CORE_STAMP)
	$(SYNTH) --trajectory $(KITTI_GT)/09.txt --aliasing --traffic --lighting --out $(@D)
$(DATA_DIR)/street00/poses.txt: | sysdeps $(CORE_STAMP)
	$(SYNTH) --trajectory $(KITTI_GT)/00.txt --world-mesh $(DATA_DIR)/street00_world.ply --out $(@D)

clean:
	rm -rf $(VENV) results .pytest_cache .mypy_cache .ruff_cache
