# grainpipe — the two commands a fresh Debian machine needs:
#   make demo   build and run the demo pipelines (outputs under out/)
#   make test   install what is missing, then format check, clippy, all tests, interop tests
# `make bench` runs the benchmarks recorded in BENCHMARKS.md.

SHELL := /bin/bash
CARGO ?= cargo
VENV ?= .venv
PYTHON ?= python3
APT_PACKAGES := libhdf5-dev libnetcdf-dev pkg-config python3-venv chromium fonts-dejavu-core g++
PIPE := $(CURDIR)/target/release/pipe
DEMO_PIPELINES := pipelines/sandcore.yaml
MORE_PIPELINES := pipelines/spheres.yaml pipelines/powderbed.yaml pipelines/clumps.yaml pipelines/mcm.yaml \
	pipelines/binder.yaml pipelines/elasticity.yaml pipelines/permeability.yaml pipelines/sandcore-quick.yaml \
	pipelines/sandcore-spheres.yaml pipelines/sandcore-paper.yaml pipelines/cemented2d.yaml pipelines/cemented3d.yaml

.PHONY: all sysdeps pydeps build demo demo-all test lint rust-test interop python python-test docs-test bench readme-stages clean test-cluster validate-sandcore validate-sandcore-unseen validate-sandcore-synthetic validate-sandcore-ablation

all: build

# System libraries for the HDF5 and NetCDF writers (and g++ for the meshoptimizer sources the
# `decimate` option of surface meshes compiles); installed only when missing.
sysdeps:
	@missing=""; \
	for p in $(APT_PACKAGES); do dpkg -s $$p >/dev/null 2>&1 || missing="$$missing $$p"; done; \
	if [ -n "$$missing" ]; then \
	  echo "installing:$$missing"; \
	  sudo=""; [ "$$(id -u)" = 0 ] || sudo=sudo; \
	  $$sudo apt-get update -qq && DEBIAN_FRONTEND=noninteractive $$sudo apt-get install -y -qq $$missing; \
	fi

# Python packages for the interop tests (pyvista, h5py, netCDF4) in a local venv.
$(VENV)/.installed: tests/interop/requirements.txt
	$(PYTHON) -m venv $(VENV)
	$(VENV)/bin/pip install -q --upgrade pip
	$(VENV)/bin/pip install -q -r tests/interop/requirements.txt
	touch $@

pydeps: $(VENV)/.installed

# grainpipe-python in the same build: one feature set (pyo3 turns on syn features), so the
# wheel build below only compiles and links the extension instead of the whole tree again.
build: sysdeps
	$(CARGO) build --release -p grainpipe-cli -p grainpipe-python

demo: build
	@for p in $(DEMO_PIPELINES); do echo "== $(PIPE) run $$p --report"; $(PIPE) run $$p --report || exit $$?; done
	@echo "outputs are under out/ (open out/sandcore/report.html in a browser; .vti/.vtp/.pvd/.vtkhdf in ParaView or pyvista)"

# Every shipped pipeline.
demo-all: build
	@for p in $(DEMO_PIPELINES) $(MORE_PIPELINES); do echo "== $(PIPE) run $$p"; $(PIPE) run $$p || exit $$?; done

lint: sysdeps
	$(CARGO) fmt --all --check
	$(CARGO) clippy --workspace --all-targets -- -D warnings

# Release profile: the test binaries share every dependency build with `build` (one optimised
# build of the tree instead of two, about a third of a clean `make test` on 2 cores); the cost
# is that debug assertions are off in tests, so invariants that matter are checked with
# assert!, not debug_assert!.
rust-test: sysdeps
	$(CARGO) test --workspace --release

interop: sysdeps pydeps build
	PIPE=$(PIPE) $(VENV)/bin/python -m pytest -q tests/interop

# The `grainpipe` Python package (python/): an abi3 wheel built by maturin into target/wheels
# (the workspace target dir), installed into .venv. `--auditwheel skip`: the wheel links the
# system libhdf5/libnetcdf instead of bundling them.
$(VENV)/.python-deps: $(VENV)/.installed tests/python/requirements.txt
	$(VENV)/bin/pip install -q -r tests/python/requirements.txt
	touch $@

python: sysdeps build $(VENV)/.python-deps
	rm -f target/wheels/grainpipe-*.whl
	$(VENV)/bin/maturin build --release -q -m python/Cargo.toml -i $(VENV)/bin/python --auditwheel skip -o target/wheels
	$(VENV)/bin/pip install -q --force-reinstall --no-deps target/wheels/grainpipe-*.whl

python-test: python
	$(CARGO) build --release -q -p grainpipe-plugin-example
	PIPE=$(PIPE) GRAINPIPE_PLUGIN_EXAMPLE=$(CURDIR)/target/release/libgrainpipe_plugin_example.so \
	  $(VENV)/bin/python -m pytest -q tests/python

# Every yaml, sh and python block of README.md and docs/ as written (tests/docs/run_snippets.py);
# python blocks import the `grainpipe` package, hence `python`.
docs-test: sysdeps build pydeps python
	$(VENV)/bin/python -m pytest -q tests/docs
	PIPE=$(PIPE) $(VENV)/bin/python tests/docs/run_snippets.py

test: lint rust-test interop python-test docs-test

# Sweeps on a real one-node Slurm cluster (slurm-wlm + munge, installed and started by the
# script; skipped with a message where they cannot be installed).
test-cluster: build
	tests/cluster/run.sh

# The sand-core validation ensembles of docs/VALIDATION.md (validate/sandcore.sh; results
# under out/validate-sandcore/, tables in its tables.md). Not part of `make test`.
VALIDATE_VENV ?= .venv-validate
$(VALIDATE_VENV)/.installed: validate/requirements.txt
	$(PYTHON) -m venv $(VALIDATE_VENV)
	$(VALIDATE_VENV)/bin/pip install -q -r validate/requirements.txt
	touch $@

validate-sandcore: build $(VALIDATE_VENV)/.installed
	PIPE=$(PIPE) PYTHON=$(VALIDATE_VENV)/bin/python validate/sandcore.sh paper

validate-sandcore-unseen: build $(VALIDATE_VENV)/.installed
	PIPE=$(PIPE) PYTHON=$(VALIDATE_VENV)/bin/python validate/sandcore.sh unseen

validate-sandcore-synthetic: build $(VALIDATE_VENV)/.installed
	PIPE=$(PIPE) PYTHON=$(VALIDATE_VENV)/bin/python validate/sandcore.sh synthetic

validate-sandcore-ablation: build $(VALIDATE_VENV)/.installed
	PIPE=$(PIPE) PYTHON=$(VALIDATE_VENV)/bin/python validate/sandcore.sh ablation

bench: build
	@for d in plugins/*/examples/*_bench.rs; do \
	  crate=grainpipe-$$(basename $$(dirname $$(dirname $$d))); \
	  echo "== $$crate"; $(CARGO) run --release -q -p $$crate --example $$(basename $$d .rs) || exit $$?; \
	done

# Regenerates the stage table in README.md from the registry.
readme-stages: build
	@$(PIPE) list --markdown > /tmp/grainpipe-stages.md
	@awk 'BEGIN{skip=0} /<!-- stages:begin -->/{print; system("cat /tmp/grainpipe-stages.md"); skip=1; next} /<!-- stages:end -->/{skip=0} !skip{print}' README.md > README.md.tmp && mv README.md.tmp README.md

clean:
	$(CARGO) clean
	rm -rf out .grainpipe-cache
