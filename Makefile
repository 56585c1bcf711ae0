# ShapeGen: two commands do everything on a fresh machine.
#   make demo   builds .venv (pinned) + the extension, runs the main job headless -> demo_output/
#   make test   builds what is missing and runs every test tier
# Requires python3.11 (Blender 4.2-5.0's Python) on PATH.
# requirements/dask.txt: the optional Dask engine (pyproject extra "dask"), installed for its tests.

PYTHON      ?= python3.11
VENV        := .venv
VENV_NP2    := .venv-np2
PY          := $(VENV)/bin/python
PY_NP2      := $(VENV_NP2)/bin/python
BPY_DIR      = $(VENV)/lib/python3.11/site-packages/bpy/5.0
BLENDER_EXT  = $(PY) $(BPY_DIR)/scripts/addons_core/bl_pkg/cli/blender_ext.py
VALID_TAGS   = $(BPY_DIR)/scripts/modules/_bpy_internal/extensions/tags.py
export OPENBLAS_NUM_THREADS := 1
# pytest runs on Blender-as-a-module must end on their own; this is the backstop
BLENDER_TEST_TIMEOUT ?= 1800
# every tier runs on all cores (pytest-xdist); a test file stays on one worker, so its
# module-scoped fixtures are built once (each Blender worker is its own Blender-as-a-module
# with its own throwaway user folder). TEST_WORKERS=0 runs them in this process.
TEST_WORKERS ?= $(shell nproc 2>/dev/null || echo 2)
PYTEST       := -m pytest -q -p no:cacheprovider
PARALLEL     := -n $(TEST_WORKERS) --dist loadfile

EXTENSION_SOURCES := blender_manifest.toml __init__.py $(shell find core shapegen_addon -name '*.py' -not -path '*/__pycache__/*')

.PHONY: all demo test test-core test-blender build wheels clean bench setup

all: test

# --no-compile: Python compiles what the tests import when they first import it (pip would
# compile all ~6000 files of the two environments, ~25 s of CPU)
$(VENV)/.installed: requirements/blender.txt requirements/dask.txt pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(VENV)/bin/pip install --disable-pip-version-check -q --no-compile -r requirements/blender.txt -r requirements/dask.txt
	$(VENV)/bin/pip install --disable-pip-version-check -q --no-deps --no-build-isolation -e .
	touch $@

$(VENV_NP2)/.installed: requirements/numpy2.txt requirements/dask.txt pyproject.toml
	$(PYTHON) -m venv $(VENV_NP2)
	$(VENV_NP2)/bin/pip install --disable-pip-version-check -q --no-compile -r requirements/numpy2.txt -r requirements/dask.txt
	$(VENV_NP2)/bin/pip install --disable-pip-version-check -q --no-deps --no-build-isolation -e .
	touch $@

wheels/.fetched: blender_manifest.toml scripts/fetch_wheels.py | $(VENV)/.installed
	$(PY) scripts/fetch_wheels.py
	touch $@

wheels: wheels/.fetched

# Blender's own extension builder (from the bpy wheel): validate, then build one zip per platform.
dist/.built: $(EXTENSION_SOURCES) wheels/.fetched | $(VENV)/.installed
	rm -rf dist && mkdir -p dist
	$(BLENDER_EXT) validate . --valid-tags $(VALID_TAGS)
	$(BLENDER_EXT) build --source-dir . --output-dir dist --split-platforms --valid-tags $(VALID_TAGS)
	touch $@

build: dist/.built

demo: dist/.built
	$(PY) scripts/demo.py --output demo_output

test-core: $(VENV)/.installed $(VENV_NP2)/.installed
	$(PY) $(PYTEST) $(PARALLEL) tests/core
	$(PY_NP2) $(PYTEST) $(PARALLEL) tests/core -m numpy_sensitive

test-blender: dist/.built
	timeout $(BLENDER_TEST_TIMEOUT) $(PY) $(PYTEST) $(PARALLEL) tests/blender

# the two environments (and the extension, once .venv is there) are built side by side:
# mostly download and unpacking, so they overlap well
setup:
	$(MAKE) --no-print-directory -j2 dist/.built $(VENV_NP2)/.installed

test: setup
	$(MAKE) --no-print-directory test-core test-blender

bench: $(VENV)/.installed
	$(PY) bench/correspondence.py --quick

clean:
	rm -rf dist build demo_output bench_output wheels/*.whl wheels/.fetched
