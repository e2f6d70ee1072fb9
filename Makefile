# Set-up and developer commands. Every target installs what it needs into project-local venvs.
PYTHON ?= python3
VENV := .venv
VENV_LTS := .venv42
VENV_LTS45 := .venv45
PY := $(VENV)/bin/python
PY_LTS := $(VENV_LTS)/bin/python
PY_LTS45 := $(VENV_LTS45)/bin/python
DIST := dist
# The compiled kernel: C sources and everything its build reads (tools/build_native.py).
NATIVE := build/native
NATIVE_INPUTS := $(wildcard csrc/*.c csrc/*.h) \
	tools/build_native.py \
	affine_deformers/accel/native.py blender_manifest.toml

.PHONY: all demo test test-core test-blender bench pipeline build release lint venv venv-lts native \
	native-all samples clean

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

venv: $(VENV)/.installed

venv-lts: $(VENV_LTS)/.installed $(VENV_LTS45)/.installed

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

test: build venv-lts
	$(PY) -m ruff check .
	AFFINE_LTS_PYTHON=$(abspath $(PY_LTS)) $(PY) -m pytest tests
	@echo "--- the Blender suite again: every frame read ahead, every output in a position carrier ---"
	AFFINE_DEFORMERS_OUTPUT_STORE=POSITIONS AFFINE_DEFORMERS_READ_AHEAD=always \
		$(PY) -m pytest tests/blender -q -p no:cacheprovider
	@echo "--- the Blender suite again on Blender 4.5 LTS ---"
	$(PY_LTS45) -m pytest tests/blender -q -p no:cacheprovider
	@echo "--- the Blender suite again on Blender 4.2 LTS ---"
	$(PY_LTS) -m pytest tests/blender -q -p no:cacheprovider

test-core: native
	$(PY) -m pytest tests/core

test-blender: build
	$(PY) -m pytest tests/blender

bench: build
	$(PY) bench/run.py --markdown docs/benchmarks.md

# The pipeline matrix of issue 47 (tests/blender/test_pipeline_matrix.py) into docs/pipeline.md: the
# same test `make test` runs, told where to write its tables; it fails when a cell is wrong.
pipeline: build
	AFFINE_PIPELINE_MARKDOWN=$(abspath docs/pipeline.md) $(PY) -m pytest tests/blender/test_pipeline_matrix.py \
		-q -p no:cacheprovider

lint: venv
	$(PY) -m ruff check .

clean:
	rm -rf $(DIST) out $(NATIVE) .pytest_cache .ruff_cache
