# Two entry points (see README): `make demo` and `make test`. Both create .venv/ when missing.
PYTHON ?= $(shell command -v python3.11 || command -v python3)
VENV   := .venv
BIN    := $(VENV)/bin
# The CPU build of torch. An unpinned torch from PyPI is a multi-GB CUDA build; this machine kind
# has torch 2.13.0's CPU wheel locally. Elsewhere, point pip at PyTorch's CPU wheel index.
TORCH  ?= torch==2.13.0
DEMO   := runs/demo

.PHONY: demo test test-fast docs install duckietown clean

$(BIN)/python:
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip

# pip byte-compiles the ~23,000 modules of torch, Ray, MLflow and MetaDrive on one core; compileall
# does it on every core (a module written for a newer Python fails to compile, as under pip: ignored).
# Left uncompiled, every fresh process (env workers, Ray workers) would compile what it imports.
# The packages' own test folders (4,000 of the 23,000 modules: pandas, sympy, scipy...) are skipped:
# nothing of drivelab imports them, and a module that is imported anyway is compiled when it is.
$(VENV)/.installed: pyproject.toml | $(BIN)/python
	@echo "== installing torch and drivelab's dependencies into $(VENV) (minutes, the first time; pip is --quiet) =="
	$(BIN)/pip install --quiet --no-compile "$(TORCH)"
	$(BIN)/pip install --quiet --no-compile -e ".[dev]"
	-$(BIN)/python -m compileall -q -j 0 -x '/tests?/' $(VENV)/lib > /dev/null 2>&1
	@touch $@

install: $(VENV)/.installed

# The drive recipe on TD3 (configs/drive_td3.yaml: its 10 minutes are the ones measured, README) for
# 10 minutes of training, then one table on 50 validation scenarios (0-49) that no training scenario
# and no checkpoint choice has seen: the demo's agent before and after training, the driver that
# ships with drivelab, MetaDrive's expert and random. benchmarks/demo.py measures the same into a
# results file (benchmarks/results/demo.json: decisions, minutes, CPU gauge, commit).
demo: install
	rm -rf $(DEMO)
	$(BIN)/drivelab train --config drive_td3 --max_minutes 10 --eval.every 0 --run-dir $(DEMO)
	@echo "== on 50 unseen validation scenarios: the demo agent before (step 0) and after training, the shipped driver, MetaDrive's expert, random =="
	$(BIN)/drivelab eval $(DEMO)/checkpoints/step_000000000000 $(DEMO) drivelab-driver --policy metadrive-expert \
		--policy random --env MetaDrive-validation-v0 --episodes 50 --num-envs 2

# Two pytest workers (pytest-xdist): most tests wait on subprocesses, servers or simulators part of
# the time, and the slow learning tests run beside the rest (worksteal balances them). The Ray
# tests take a machine-wide lock for their cluster (tests/test_ray.py).
test: install
	$(BIN)/python -m pytest -q -n 2 --dist worksteal --durations=12

# The documentation site (mkdocs.yml, pages in docs/): built offline into site/, strict, so a broken
# link, a missing anchor or a docstring that fails to render fails the build.
docs: install
	NO_MKDOCS_2_WARNING=1 $(BIN)/mkdocs build --strict --quiet

test-fast: install
	$(BIN)/python -m pytest -q -n 2 --dist worksteal -m "not slow"

# The Duckietown extra lives in its own environment: its pins (extras/duckietown-constraints.txt)
# would break the main one. Its OpenGL renderer needs a display: xvfb-run on headless machines.
DUCKIE := .venv-duckietown
$(DUCKIE)/.installed: pyproject.toml extras/duckietown-constraints.txt
	$(PYTHON) -m venv $(DUCKIE)
	$(DUCKIE)/bin/python -m pip install --quiet --upgrade pip
	$(DUCKIE)/bin/pip install --quiet "$(TORCH)"
	$(DUCKIE)/bin/pip install --quiet -c extras/duckietown-constraints.txt duckietown-gym-daffy -e ".[dev]"
	@command -v xvfb-run >/dev/null || (apt-get update -qq && apt-get install -y -qq xvfb) \
		|| echo "install xvfb (apt-get install xvfb) to run Duckietown without a display"
	@touch $@

duckietown: $(DUCKIE)/.installed
	xvfb-run -a $(DUCKIE)/bin/python -m pytest -q tests/test_driving.py -k duckietown

clean:
	rm -rf $(VENV) $(DUCKIE) runs
