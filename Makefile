# One entry point for people and CI: `make demo` and `make test` set up what they need first.
SHELL := /bin/bash
.DEFAULT_GOAL := help

VENV ?= .venv
PY := $(VENV)/bin/python
PIP := $(PY) -m pip --disable-pip-version-check -q
# Node 20 is past jsii's support window; the banner on every CDK call drowns real output.
export JSII_SILENCE_WARNING_END_OF_LIFE_NODE_VERSION := 20
# No GPU here or in CI: MuJoCo renders offscreen through EGL (Mesa surfaceless here, NVIDIA on the instance).
export MUJOCO_GL ?= egl
export PYOPENGL_PLATFORM ?= $(MUJOCO_GL)

APT_PACKAGES := mosquitto xvfb xauth libosmesa6 libgl1-mesa-dri libglfw3 shellcheck
SETUP_STAMP := $(VENV)/.setup-stamp
NODE_STAMP := node_modules/.setup-stamp

.PHONY: help setup system-packages test lint demo bench usd-asset clean

help:
	@echo "make demo   - set up, then run the twin end to end locally (broker, edge simulator, agent)"
	@echo "make test   - set up, then run every check CI runs"
	@echo "make setup  - system packages (apt), .venv, CDK CLI; idempotent"
	@echo "make bench  - run the benchmarks and print figures (docs/performance.md)"
	@echo "make usd-asset - regenerate robots/so101 USD asset from the MJCF"

setup: system-packages $(SETUP_STAMP) $(NODE_STAMP)

# apt only when a tool is missing, so a second `make setup` does no network work.
system-packages:
	@missing=""; \
	for bin in mosquitto Xvfb shellcheck; do command -v $$bin >/dev/null 2>&1 || missing=1; done; \
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
	@$(PIP) install --upgrade pip 2>&1 | grep -v '^WARNING: Location' || true
	@$(PIP) install -e '.[dev]' 2>&1 | grep -v '^WARNING: Location' || true
	@$(PY) -c "import twin, mujoco, pxr, awscrt, aws_cdk, cdk_nag" || { echo "setup: Python install failed" >&2; exit 1; }
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

demo: setup
	$(VENV)/bin/twin demo --out out/demo

bench: setup
	$(VENV)/bin/twin bench all

clean:
	rm -rf out cdk.out .pytest_cache
