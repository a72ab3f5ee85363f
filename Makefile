# graspcap: `make demo` and `make test` set everything up from scratch.
SHELL := /bin/bash
PYTHON ?= python3.11
VENV ?= .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed
DEMO_DIR ?= demo_out
# Two workers for the two cores; GTSAM/Open3D/BLAS stay single-threaded inside each.
PYTEST_WORKERS ?= 2
export OMP_NUM_THREADS ?= 1
export OPENBLAS_NUM_THREADS ?= 1
export MKL_NUM_THREADS ?= 1

.PHONY: help setup system-libs demo test test-all bench lint clean

help:  ## List the targets
	@grep -E '^[a-z-]+:.*## ' $(MAKEFILE_LIST) | awk -F':.*## ' '{printf "  make %-11s %s\n", $$1, $$2}'

system-libs:  ## Install the system libraries the wheels need (Open3D: libusb-1.0) and, where apt can, chromium-headless-shell (browser tests)
	@if ! ldconfig -p | grep -q 'libusb-1.0.so.0'; then \
		echo "installing libusb-1.0-0 (needed by Open3D)"; \
		SUDO=$$( [ "$$(id -u)" = 0 ] || echo sudo ); \
		$$SUDO apt-get update -qq && $$SUDO apt-get install -y -qq libusb-1.0-0 >/dev/null; \
	fi
	@if ! command -v chromium-headless-shell >/dev/null && ! command -v chromium >/dev/null; then \
		echo "installing chromium-headless-shell (the browser tests; they skip without it)"; \
		SUDO=$$( [ "$$(id -u)" = 0 ] || echo sudo ); \
		{ $$SUDO apt-get update -qq && $$SUDO apt-get install -y -qq --no-install-recommends \
			chromium-headless-shell >/dev/null; } \
		|| echo "chromium-headless-shell not installed: the browser tests will be skipped"; \
	fi

$(STAMP): pyproject.toml constraints.txt
	$(MAKE) system-libs
	@test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q -c constraints.txt -e '.[dev,mediapipe]'
	$(PY) -m pip install -q -c constraints.txt --no-deps mediapipe==0.10.21
	@touch $(STAMP)

setup: $(STAMP)  ## Create .venv and install graspcap with everything it needs

demo: setup  ## Generate synthetic sessions, validate them and run the pipeline on them
	$(VENV)/bin/graspcap demo --out $(DEMO_DIR)

test: setup  ## Run the test suite (slow cases excluded)
	$(PY) -m pytest -n $(PYTEST_WORKERS) -q

test-all: setup  ## Run every test, slow ones included
	$(PY) -m pytest -n $(PYTEST_WORKERS) -q -m ''

bench: setup  ## Run the benchmarks under bench/ (numbers go to docs/benchmarks.md)
	$(PY) bench/run_all.py

lint: setup  ## ruff check
	$(VENV)/bin/ruff check .

clean:  ## Remove the virtualenv and generated outputs
	rm -rf $(VENV) $(DEMO_DIR) .pytest_cache
