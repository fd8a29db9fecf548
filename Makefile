# lerobot-suture: `make demo` runs the main job on a small default; `make test` runs the tests.
# Both set up first (`make install`): a .venv with Python >= 3.12, the seven distributions in
# editable mode with the test, viz (rerun) and teleop (keyboard, gamepad) extras, and the system libraries headless rendering needs.

SHELL := /bin/bash
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
PYTHON ?= $(shell command -v python3.12 || command -v python3)
APT_PACKAGES := libegl1 libgl1-mesa-dri libglib2.0-0
# Disk space (GiB) the install takes: torch's CUDA build and its libraries.
INSTALL_GIB := 7
export MUJOCO_GL ?= egl
export PYOPENGL_PLATFORM ?= egl

.PHONY: install test test-slow demo reproduce bench lint clean

install: $(STAMP)

$(STAMP): pyproject.toml envs/pyproject.toml policies/pyproject.toml robots/pyproject.toml teleoperators/pyproject.toml chain/pyproject.toml studies/pyproject.toml
	@missing=""; for p in $(APT_PACKAGES); do dpkg -s $$p >/dev/null 2>&1 || missing="$$missing $$p"; done; \
	if [ -n "$$missing" ]; then \
	  echo "installing system packages:$$missing"; \
	  SUDO=$$([ "$$(id -u)" = 0 ] || echo sudo); \
	  $$SUDO apt-get update -qq && DEBIAN_FRONTEND=noninteractive $$SUDO apt-get install -y -qq $$missing; \
	fi
	@test -x $(BIN)/python || { \
	  $(PYTHON) -c 'import sys; sys.exit(sys.version_info < (3, 12))' || \
	    { echo "Python >= 3.12 is required (found $$($(PYTHON) --version)); set PYTHON=/path/to/python3.12"; exit 1; }; \
	  $(PYTHON) -m venv $(VENV); }
	@free=$$(df -Pk . | awk 'NR==2 {print int($$4 / 1048576)}'); \
	if [ "$${free:-0}" -lt $(INSTALL_GIB) ]; then \
	  echo "warning: $${free:-?} GiB free here; the install needs about $(INSTALL_GIB) GiB (torch's CUDA build and its libraries). Free some space if pip fails with 'No space left on device'."; \
	fi
	$(BIN)/python -m pip install -q --upgrade pip
	$(BIN)/python -m pip install -q -e ".[test,viz,teleop]" -e ./envs -e ./policies -e ./robots -e ./teleoperators -e ./chain -e ./studies
	@touch $(STAMP)

test: install
	$(BIN)/python -m pytest

test-slow: install
	$(BIN)/python -m pytest -m slow

demo: install
	$(BIN)/lerobot-suture demo

# The reference from nothing (dataset, training, calibration, experiments) and its table beside the
# committed one; resumes after an interruption. About an hour on 2 CPU cores.
reproduce: install
	$(BIN)/lerobot-suture reproduce

# A script that needs a trained policy or a dataset declares it in a top-level NEEDS = "..." line
# (tests/test_layout.py holds every script to it with the same pattern).
bench: install
	@for b in benchmarks/[!_]*.py studies/benchmarks/[!_]*.py; do \
	  needs=$$(sed -n 's/^NEEDS = "\(.*\)"$$/\1/p' $$b); \
	  if [ -n "$$needs" ]; then echo "== $$b: needs $$needs, skipped ($(BIN)/python $$b --help)"; continue; fi; \
	  echo "== $$b"; $(BIN)/python $$b; done

lint: install
	$(BIN)/ruff check lerobot_suture envs policies robots teleoperators chain studies tests benchmarks
	$(BIN)/ruff format --check lerobot_suture envs policies robots teleoperators chain studies tests benchmarks

clean:
	rm -rf $(VENV) outputs .pytest_cache
