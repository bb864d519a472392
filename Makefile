# dualscale: two commands set up a fresh machine (Debian/Ubuntu):
#   make demo   the main job, on the simulated rig
#   make test   everything CI runs
# Both install what they need: Debian packages (apt-get), the virtualenv and the pip packages.

SHELL := /bin/bash
PYTHON ?= python3
VENV ?= .venv
PY := $(VENV)/bin/python
BUILD := build
FUZZ_SECONDS ?= 20

# Debian packages: ARM toolchain + newlib, QEMU, an independent Modbus peer (mbpoll),
# C test framework (cmocka), clang + its runtime for libFuzzer, the GL/GLib runtime OpenCV's
# wheel loads, headless Chromium for the HTML report's and the viewer's browser tests, Node (npm
# comes with NodeSource's nodejs, else Debian's npm package) for the Khronos glTF-Validator and three.js (package.json, pinned by package-lock.json),
# Aravis 0.8 for the genicam camera backend: its GObject introspection data, the tools with the
# GigE Vision camera emulator the tests start (arv-fake-gv-camera-0.8), and what PyGObject
# (pyproject extra "cameras") builds from source against: girepository-1.0, cairo, pkg-config,
# the Python headers; Xvfb (xvfb, xauth) for MaterialX's GLSL renderer in the export tests (Mesa's
# llvmpipe comes with libgl1).
APT_PKGS := gcc-arm-none-eabi libnewlib-arm-none-eabi qemu-system-arm mbpoll libmodbus-dev \
            libcmocka-dev clang libclang-rt-14-dev make gcc g++ python3-venv libgl1 libglib2.0-0 \
            chromium nodejs \
            gir1.2-aravis-0.8 aravis-tools libgirepository1.0-dev libcairo2-dev pkg-config python3-dev \
            xvfb xauth
SUDO := $(shell [ "$$(id -u)" = 0 ] || echo sudo)

.PHONY: all deps apt venv blender node gen gen-check firmware sim test test-fast test-slow demo bench fuzz fuzz-long clean

all: firmware sim

deps: apt venv node

apt: $(BUILD)/.apt-stamp
$(BUILD)/.apt-stamp: Makefile
	@mkdir -p $(BUILD)
	@missing=$$(for p in $(APT_PKGS); do dpkg-query -W -f='$${Status}' $$p 2>/dev/null | grep -q "ok installed" || echo $$p; done); \
	if [ -n "$$missing" ]; then \
	  echo "installing Debian packages: $$missing"; \
	  $(SUDO) apt-get update -qq && DEBIAN_FRONTEND=noninteractive $(SUDO) apt-get install -y -qq $$missing; \
	fi
	@touch $@

venv: $(VENV)/.stamp
$(VENV)/.stamp: pyproject.toml
	@test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q torch==2.13.0
	$(PY) -m pip install -q -e '.[dev,cameras,dask]'
	@touch $@

# Blender as a Python module (PyPI bpy 5.0.1, cp311 only; `dualscale export --format blend` and the
# tests that render our exports in Cycles, tests/export/test_blender.py).  Its own venv: bpy needs
# numpy < 2 and the project's venv has numpy 2.  Measured here (3 Dec 2026, 2 shared cores, load
# 2.6-3.6): `make blender` from nothing 38 s (the 374 MB wheel downloads in 6.5 s), 967 MB on disk;
# small beside `make venv`, so `make test` installs it.
BLENDER_VENV ?= .venv-blender
blender: $(BLENDER_VENV)/.stamp
$(BLENDER_VENV)/.stamp: Makefile
	@test -x $(BLENDER_VENV)/bin/python || $(PYTHON) -m venv $(BLENDER_VENV)
	$(BLENDER_VENV)/bin/python -m pip install -q bpy==5.0.1
	@touch $@

# npm packages (package-lock.json): the glTF-Validator the tests run, and three.js, whose module
# build and the addons the viewer imports are copied into the package's static assets (nothing
# is fetched when the viewer runs).
VENDOR := host/dualscale/view/static/vendor
THREE_ADDONS := loaders/GLTFLoader.js controls/OrbitControls.js utils/BufferGeometryUtils.js utils/SkeletonUtils.js
node: node_modules/.stamp $(VENDOR)/.stamp
node_modules/.stamp: package.json package-lock.json | apt
	@command -v npm >/dev/null || { $(SUDO) apt-get update -qq && DEBIAN_FRONTEND=noninteractive $(SUDO) apt-get install -y -qq npm; }
	npm ci --no-audit --no-fund --loglevel=error
	@touch $@
$(VENDOR)/.stamp: node_modules/.stamp
	@mkdir -p $(VENDOR)/addons
	cp node_modules/three/build/three.module.js node_modules/three/build/three.core.js node_modules/three/LICENSE $(VENDOR)/
	@for f in $(THREE_ADDONS); do mkdir -p $(VENDOR)/addons/$$(dirname $$f); \
	  cp node_modules/three/examples/jsm/$$f $(VENDOR)/addons/$$f; done
	@touch $@

gen: venv
	$(PY) protocol/gen.py

gen-check: venv
	$(PY) protocol/gen.py --check

firmware: apt
	$(MAKE) -C firmware stm32

sim: apt
	$(MAKE) -C firmware posix

test: deps blender gen-check
	$(MAKE) -C firmware all
	$(MAKE) -C firmware test
	$(MAKE) -C firmware fuzz FUZZ_SECONDS=$(FUZZ_SECONDS)
	$(PY) -m pytest -m "not slow" -q --durations=40

test-slow: deps blender
	$(MAKE) -C firmware all
	$(PY) -m pytest -m slow -q

# The main job on the simulated rig: the capture sequence on the firmware simulator, the
# calibration targets of the virtual rig and their calibration, then `dualscale digitize --rig sim`:
# the POSIX firmware simulator (the real C core) times every exposure, simulated micro and mid
# cameras on its trigger lines take a synthetic twill (camera counts: LED spectra and gains,
# vignetting, dark signal, noise; metered HDR brackets), and the run goes on through calibrate,
# fit, propagate, export and report.  Each step is skipped when its output exists, and digitize
# resumes by itself (the capture from its journal): rerunning `make demo` continues where it
# stopped.  To stay within 10 minutes on 2 cores the demo captures every 4th LED (the
# calibration covers the same LEDs), a micro field of 128 px of 7.2 um (the rig's 0.92 mm field
# binned 4x) and a guidance image of 512 px over 12.5 mm (24 um per pixel, the pitch of the
# rig's 4072 px mid-range camera), with the simulator as fast as it goes (speed 0);
# docs/DIGITIZE.md measures it.
DEMO ?= $(BUILD)/demo
DEMO_SIZE ?= 128
DEMO_ADAPTIVE_SIZE ?= 48
DEMO_TEXEL_UM ?= 7.2
DEMO_LED_STEP ?= 4
DEMO_MID_SIZE ?= 512
DEMO_MID_FIELD_MM ?= 12.5
DEMO_QUALITY ?= standard
DEMO_SIM_SPEED ?= 0
# one thread: on a shared 2-core machine a second torch thread per process costs far more than it gives
DEMO_THREADS ?= 1
DS := $(VENV)/bin/dualscale
demo: deps
	$(MAKE) -C firmware posix
	$(DS) demo
	@test -f $(DEMO)/targets/captures.json || $(DS) synth-targets -o $(DEMO)/targets --led-step $(DEMO_LED_STEP) \
	    --threads $(DEMO_THREADS)
	@test -f $(DEMO)/calibration.json || $(DS) calibrate $(DEMO)/targets -o $(DEMO)/calibration.json --threads $(DEMO_THREADS)
	@# the adaptive capture (docs/CAPTURE.md): the same rig and calibration, the demo's LEDs as candidates
	@test -f $(DEMO)/adaptive/capture.json || $(DS) capture micro --adaptive --port sim --sim-speed $(DEMO_SIM_SPEED) \
	    --rig-id virtual-dome-0 --lights MOD$(DEMO_LED_STEP) --calibration $(DEMO)/calibration.json \
	    --camera 'sim:micro?material=twill&size=$(DEMO_ADAPTIVE_SIZE)&texel_um=$(DEMO_TEXEL_UM)' \
	    -o $(DEMO)/adaptive --resume --budget 40 --threads $(DEMO_THREADS) --no-progress
	$(DS) digitize --rig sim --sim-speed $(DEMO_SIM_SPEED) --rig-id virtual-dome-0 --lights MOD$(DEMO_LED_STEP) \
	    --camera 'sim:micro?material=twill&size=$(DEMO_SIZE)&texel_um=$(DEMO_TEXEL_UM)' \
	    --camera 'sim:mid?material=twill&size=$(DEMO_MID_SIZE)&field_mm=$(DEMO_MID_FIELD_MM)' \
	    -o $(DEMO)/run --calibration $(DEMO)/calibration.json --name twill \
	    --quality $(DEMO_QUALITY) --tile --threads $(DEMO_THREADS)

# Every benchmark prints a markdown table for the doc it belongs to (see each script's docstring).
bench: deps
	$(MAKE) -C firmware all
	$(PY) -m pip install -q -e '.[bench]'
	@set -e; for b in bench/bench_*.py; do echo "== $$b"; $(PY) $$b; done

# 5 M inputs per harness (10 M in all), one process at a time; figures in firmware/README.md.
fuzz-long: apt
	$(MAKE) -C firmware fuzz-long

clean:
	$(MAKE) -C firmware clean || true
	rm -rf $(BUILD)
