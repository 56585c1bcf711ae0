# ShapeGen: two commands do everything on a fresh machine.
#   make demo   builds .venv (pinned) + the extension, runs the main job headless -> demo_output/
#   make test   builds what is missing and runs every test tier
# Requires python3.11 (Blender 4.2-5.0's Python) on the PATH, and Python 3.13 (Blender 5.1+'s)
# on the PATH as python3.13 or under ~/.pyenv/versions.
#
# Environments, each pinned in requirements/ (refresh the generated ones with `make pins`):
#   .venv         Python 3.11, Blender 5.0 as a module (blender.txt): builds the extension,
#                 runs the demo and the Blender tier
#   .venv-oldest  Python 3.11, the floors of pyproject.toml's ranges (oldest.txt): core tier
#   .venv-newest  Python 3.13, the newest releases the ranges allow, Blender 5.2 LTS as a
#                 module (newest.txt): core tier, Blender 5.2 smoke, the README's pip install
#   .venv-bpy42   Python 3.11, Blender 4.2 LTS as a module (blender-4.2.txt): Blender 4.2 smoke
# Each is a plain `python -m venv` filled by uv (requirements/uv.txt, installed into .uv/ by
# pip), which installs the pinned wheels with less than half of pip's CPU (most of it goes to
# unpacking the three Blender wheels).

PYTHON      ?= python3.11
PYTHON313   ?= $(shell python3.13 -c 'import sys; print(sys.executable)' 2>/dev/null || ls -d $${PYENV_ROOT:-$$HOME/.pyenv}/versions/3.13*/bin/python3.13 2>/dev/null | tail -1)
VENV        := .venv
VENV_OLDEST := .venv-oldest
VENV_NEWEST := .venv-newest
VENV_BPY42  := .venv-bpy42
PY          := $(VENV)/bin/python
PY_OLDEST   := $(VENV_OLDEST)/bin/python
PY_NEWEST   := $(VENV_NEWEST)/bin/python
PY_BPY42    := $(VENV_BPY42)/bin/python
BPY_DIR      = $(VENV)/lib/python3.11/site-packages/bpy/5.0
BLENDER_EXT  = $(PY) $(BPY_DIR)/scripts/addons_core/bl_pkg/cli/blender_ext.py
VALID_TAGS   = $(BPY_DIR)/scripts/modules/_bpy_internal/extensions/tags.py
UV_HOME     := .uv
UV          := $(UV_HOME)/bin/uv
# uv reads the system's certificates as pip does (pip.conf's cert), waits as long as pip is
# told to (PIP_DEFAULT_TIMEOUT), and never fetches a Python
export UV_NATIVE_TLS := 1
export UV_PYTHON_DOWNLOADS := never
export UV_HTTP_TIMEOUT ?= $(or $(PIP_DEFAULT_TIMEOUT),60)

# $(call install,PYTHON,ARGUMENTS): uv pip install ARGUMENTS into the environment of PYTHON;
# where uv cannot fetch (an index, proxy or certificate only pip's configuration knows),
# the machine's pip installs the same pins, and says so
define install
	$(UV) pip install -q --python $(1) $(2) || { echo "uv could not install $(2): pip installs it"; \
	  $(PYTHON) -m pip --python $(1) install --disable-pip-version-check --root-user-action=ignore -q \
	  --no-compile $(2); }
endef
export OPENBLAS_NUM_THREADS := 1
# pytest runs on Blender-as-a-module must end on their own; this is the backstop
BLENDER_TEST_TIMEOUT ?= 1800
# every tier runs on all cores (pytest-xdist); a test file stays on one worker, so its
# module-scoped fixtures are built once (each Blender worker is its own Blender-as-a-module
# with its own throwaway user folder). TEST_WORKERS=0 runs them in this process.
TEST_WORKERS ?= $(shell nproc 2>/dev/null || echo 2)
PYTEST       := -m pytest -q -p no:cacheprovider --durations=10
PARALLEL     := -n $(TEST_WORKERS) --dist loadfile
# the interpreters of the Blender smoke tier (tests/blender/test_releases.py): release=python
export SHAPEGEN_BLENDER_RELEASES := 4.2=$(abspath $(PY_BPY42)) 5.2=$(abspath $(PY_NEWEST))

EXTENSION_SOURCES := blender_manifest.toml __init__.py $(shell find core shapegen_addon -name '*.py' -not -path '*/__pycache__/*')

.PHONY: all demo test test-core test-core-oldest test-core-newest test-blender build wheels clean bench pins

all: test

# uv itself, pinned, into .uv/ (one download, no environment of its own)
$(UV): requirements/uv.txt
	rm -rf $(UV_HOME)
	$(PYTHON) -m pip install --disable-pip-version-check --root-user-action=ignore -q --no-compile --target $(UV_HOME) -r requirements/uv.txt
	touch $@

# Python compiles what the tests import when they first import it (uv compiles nothing by
# default; compiling all ~6000 files of the environments would cost ~25 s of CPU). The
# environments keep pip (`python -m venv`): the packaging test builds a wheel with it, and
# fetch_wheels.py downloads the extension's wheels with it.
$(VENV)/.installed: requirements/blender.txt pyproject.toml $(UV)
	$(PYTHON) -m venv $(VENV)
	$(call install,$(PY),-r requirements/blender.txt)
	$(call install,$(PY),--no-deps --no-build-isolation -e .)
	touch $@

$(VENV_OLDEST)/.installed: requirements/oldest.txt pyproject.toml $(UV)
	$(PYTHON) -m venv $(VENV_OLDEST)
	$(call install,$(PY_OLDEST),-r requirements/oldest.txt)
	$(call install,$(PY_OLDEST),--no-deps --no-build-isolation -e .)
	touch $@

$(VENV_NEWEST)/.installed: requirements/newest.txt pyproject.toml $(UV)
	@test -n "$(PYTHON313)" || { echo "Python 3.13 not found: put python3.13 on the PATH (or PYTHON313=...)"; exit 2; }
	$(PYTHON313) -m venv $(VENV_NEWEST)
	$(call install,$(PY_NEWEST),-r requirements/newest.txt)
	$(call install,$(PY_NEWEST),--no-deps --no-build-isolation -e .)
	touch $@

# only Blender 4.2 and its numpy: nothing here installs with pip
$(VENV_BPY42)/.installed: requirements/blender-4.2.txt $(UV)
	$(PYTHON) -m venv --without-pip $(VENV_BPY42)
	$(call install,$(PY_BPY42),-r requirements/blender-4.2.txt)
	touch $@

# requirements/oldest.txt, newest.txt and blender-4.2.txt, resolved anew (scripts/refresh_pins.py)
pins:
	$(PYTHON) scripts/refresh_pins.py --python313 $(PYTHON313)

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

# the core tier at both ends of the declared ranges
test-core: test-core-oldest test-core-newest

# the floors run every test but the quality figures on whole collections (pyproject.toml's
# `quality` marker), which run on the newest pins: the floors check that the declared oldest
# releases run the code, and the smaller tests run the same code
test-core-oldest: $(VENV_OLDEST)/.installed
	$(PY_OLDEST) $(PYTEST) $(PARALLEL) -m "not quality" tests/core

test-core-newest: $(VENV_NEWEST)/.installed
	$(PY_NEWEST) $(PYTEST) $(PARALLEL) tests/core

# the full Blender tier on Blender 5.0, and the smoke on Blender 4.2 and 5.2 LTS
test-blender: dist/.built $(VENV_NEWEST)/.installed $(VENV_BPY42)/.installed
	timeout $(BLENDER_TEST_TIMEOUT) $(PY) $(PYTEST) $(PARALLEL) tests/blender

# the three tiers side by side, each on all cores: one after another, each tier's startup
# (Blender's import in every worker) and its tail (the last file on one worker, the release
# smokes' subprocesses) left cores idle. Each tier starts as soon as its own environment is
# built: the building is mostly download and unpacking, and the core tiers' tests fill the
# cores it leaves idle. -Otarget prints each tier's output in one piece when it ends.
test:
	$(MAKE) --no-print-directory -j4 -Otarget test-core-oldest test-core-newest test-blender

bench: $(VENV)/.installed
	$(PY) bench/correspondence.py --quick

clean:
	rm -rf dist build demo_output bench_output wheels/*.whl wheels/.fetched $(UV_HOME)
