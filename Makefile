# Set-up and developer commands. Every target installs what it needs into project-local venvs.
PYTHON ?= python3
VENV := .venv
VENV_LTS := .venv42
VENV_LTS45 := .venv45
PY := $(VENV)/bin/python
PY_LTS := $(VENV_LTS)/bin/python
PY_LTS45 := $(VENV_LTS45)/bin/python
# Blender 5.1 and newer ship as bpy wheels for Python 3.13 only: their venvs are made from the Python
# 3.13 that tools/find_python.sh finds (on PATH or pyenv's); PYTHON313=/path/to/python3.13 overrides.
PYTHON313 ?= $(shell tools/find_python.sh 3.13)
VENV51 := .venv51
VENV52 := .venv52
VENV53 := .venv53
VENV_NEWEST := .venv-newest
PY51 := $(VENV51)/bin/python
PY52 := $(VENV52)/bin/python
PY53 := $(VENV53)/bin/python
# What each Blender suite records (tests/blender/conftest.py) for README's table of tested versions.
SUITES := build/suites
DIST := dist
# The compiled kernel: C sources and everything its build reads (tools/build_native.py).
NATIVE := build/native
NATIVE_INPUTS := $(wildcard csrc/*.c csrc/*.h) \
	tools/build_native.py \
	affine_deformers/accel/native.py blender_manifest.toml

.PHONY: all demo test test-core test-blender test-newest bench pipeline build release lint venv venv-lts \
	venv-313 native native-all samples clean python313

all: test

$(VENV)/.installed: tools/requirements-dev.txt
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --disable-pip-version-check -q -r tools/requirements-dev.txt
	touch $@

$(VENV_LTS)/.installed: tools/requirements-lts.txt
	$(PYTHON) -m venv $(VENV_LTS)
	$(PY_LTS) -m pip install --disable-pip-version-check -q -r tools/requirements-lts.txt
	touch $@

$(VENV_LTS45)/.installed: tools/requirements-lts45.txt
	$(PYTHON) -m venv $(VENV_LTS45)
	$(PY_LTS45) -m pip install --disable-pip-version-check -q -r tools/requirements-lts45.txt
	touch $@

python313:
	@test -n "$(PYTHON313)" || { echo "make: Blender 5.1 and newer need Python 3.13, and none was found" \
		"(neither python3.13 on PATH nor in pyenv): install it (e.g. \`pyenv install 3.13\`, or your" \
		"system's python3.13 package) or set PYTHON313=/path/to/python3.13" >&2; exit 1; }

# The Python 3.13 venvs: $(1) the venv, $(2) its requirements file.
define VENV313
$(1)/.installed: $(2)
	@$$(MAKE) --no-print-directory python313
	@echo "--- installing $$$$(grep -o 'bpy==[0-9.]*' $(2)) into $(1) (Python 3.13: $(PYTHON313); ~1 GB) ---"
	$(PYTHON313) -m venv $(1)
	$(1)/bin/python -m pip install --disable-pip-version-check -q -r $(2)
	touch $$@
endef
$(eval $(call VENV313,$(VENV51),tools/requirements-51.txt))
$(eval $(call VENV313,$(VENV52),tools/requirements-52.txt))
$(eval $(call VENV313,$(VENV53),tools/requirements-53.txt))

venv: $(VENV)/.installed

venv-lts: $(VENV_LTS)/.installed $(VENV_LTS45)/.installed

venv-313: $(VENV51)/.installed $(VENV52)/.installed $(VENV53)/.installed

# The C kernel for this machine (build/native/<platform>/ and its wheel in build/native/wheels/), with
# zig's clang from the venv; rebuilt when its inputs or the venv change. native-all: all four platforms.
$(NATIVE)/.host-built: $(NATIVE_INPUTS) $(VENV)/.installed
	$(PY) tools/build_native.py --platform host --output $(NATIVE)
	touch $@

$(NATIVE)/.all-built: $(NATIVE_INPUTS) $(VENV)/.installed
	$(PY) tools/build_native.py --platform all --output $(NATIVE)
	touch $@ $(NATIVE)/.host-built

native: venv $(NATIVE)/.host-built

native-all: venv $(NATIVE)/.all-built

# Validate the manifest and build the extension .zip with the CLI that ships inside the bpy wheel:
# this machine's platform, with its compiled-kernel wheel.
build: native
	$(PY) tools/build_extension.py --output-dir $(DIST)

# One package per platform in the manifest (Linux, Windows, macOS arm64/x64), for a release.
release: native-all
	$(PY) tools/build_extension.py --output-dir $(DIST) --platform all

# The main job: render every sample scene at a few frames into out/ (PNG + one contact sheet each).
demo: build
	$(PY) samples/render_samples.py --output-dir out

# The committed samples are saved by Blender 4.2 LTS: files saved by 5.0 do not open in 4.2.
samples: build venv-lts
	$(PY_LTS) samples/build_samples.py

# Every Blender suite gets the same variables: the 4.2 interpreter (tests that run 4.2 in a
# subprocess), the interpreters whose Blenders save the files the newest ones must open
# (test_cross_version.py), and where to record its counts for README's table of tested versions.
SAVERS := 4.2=$(abspath $(PY_LTS)),4.5=$(abspath $(PY_LTS45)),5.0=$(abspath $(PY))
SUITE_ENV = AFFINE_LTS_PYTHON=$(abspath $(PY_LTS)) AFFINE_SAVING_PYTHONS=$(SAVERS) AFFINE_SUITE_RECORD=$(abspath $(SUITES))
BLENDER_SUITE := -m pytest tests/blender -q -p no:cacheprovider
AGAIN_ENV := AFFINE_DEFORMERS_OUTPUT_STORE=POSITIONS AFFINE_DEFORMERS_READ_AHEAD=always

test: build venv-lts venv-313
	@start=$$(date +%s); rm -rf $(SUITES); mkdir -p $(SUITES); \
	echo "--- ruff, then the Blender suite on 4.2, 4.5, 5.0, 5.1, 5.2 and 5.3 (about 30 min on 2 cores) ---"; \
	$(PY) -m ruff check . && \
	echo "--- the core tests and the Blender suite on Blender 5.0 ---" && \
	$(SUITE_ENV) AFFINE_SUITE_LABEL="5.0 + core" $(PY) -m pytest tests && \
	echo "--- the Blender suite again on 5.0: every frame read ahead, every output in a position carrier ---" && \
	$(SUITE_ENV) $(AGAIN_ENV) AFFINE_SUITE_LABEL="5.0, read ahead + position carriers" $(PY) $(BLENDER_SUITE) && \
	echo "--- the Blender suite on Blender 5.3, with files saved by 4.2, 4.5 and 5.0 ---" && \
	$(SUITE_ENV) $(PY53) $(BLENDER_SUITE) && \
	echo "--- the Blender suite again on 5.3: every frame read ahead, every output in a position carrier ---" && \
	$(SUITE_ENV) $(AGAIN_ENV) AFFINE_SUITE_LABEL="5.3, read ahead + position carriers" $(PY53) $(BLENDER_SUITE) && \
	echo "--- the Blender suite on Blender 5.2 LTS, with files saved by 4.2, 4.5 and 5.0 ---" && \
	$(SUITE_ENV) $(PY52) $(BLENDER_SUITE) && \
	echo "--- the Blender suite on Blender 5.1 ---" && \
	$(SUITE_ENV) $(PY51) $(BLENDER_SUITE) && \
	echo "--- the Blender suite on Blender 4.5 LTS ---" && \
	$(SUITE_ENV) $(PY_LTS45) $(BLENDER_SUITE) && \
	echo "--- the Blender suite on Blender 4.2 LTS ---" && \
	$(SUITE_ENV) $(PY_LTS) $(BLENDER_SUITE) && \
	$(PY) tools/tested_versions.py $(SUITES) README.md && \
	echo "--- make test: all green in $$(( ($$(date +%s) - start) / 60 )) min $$(( ($$(date +%s) - start) % 60 )) s ---"

# The newest bpy PyPI offers (for Python 3.13), installed afresh, and the Blender suite on it: the next
# API change is found the day it ships.
test-newest: build
	@$(MAKE) --no-print-directory python313
	rm -rf $(VENV_NEWEST)
	$(PYTHON313) -m venv $(VENV_NEWEST)
	$(VENV_NEWEST)/bin/python -m pip install --disable-pip-version-check -q --upgrade bpy numpy pytest
	@echo "--- the Blender suite on the newest bpy: $$($(VENV_NEWEST)/bin/python -m pip show bpy | grep ^Version) ---"
	$(if $(wildcard $(PY_LTS)),AFFINE_LTS_PYTHON=$(abspath $(PY_LTS))) $(VENV_NEWEST)/bin/python $(BLENDER_SUITE)

test-core: native
	$(PY) -m pytest tests/core

test-blender: build
	$(PY) -m pytest tests/blender

# Every part on Blender 5.0 (docs/benchmarks.md), then the 130k, crowd and big-scene parts (a, m, w) on
# Blender 5.3, the version artists use (docs/benchmarks_5.3.md): its own evaluation may cost otherwise.
bench: build $(VENV53)/.installed
	$(PY) bench/run.py --markdown docs/benchmarks.md
	$(PY53) bench/run.py --only a,m,w --markdown docs/benchmarks_5.3.md

# The pipeline matrix of issue 47 (tests/blender/test_pipeline_matrix.py) into docs/pipeline.md: the
# same test `make test` runs, told where to write its tables; it fails when a cell is wrong.
pipeline: build
	AFFINE_PIPELINE_MARKDOWN=$(abspath docs/pipeline.md) $(PY) -m pytest tests/blender/test_pipeline_matrix.py \
		-q -p no:cacheprovider

lint: venv
	$(PY) -m ruff check .

clean:
	rm -rf $(DIST) out $(NATIVE) .pytest_cache .ruff_cache
