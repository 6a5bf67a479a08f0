# The two commands of the README: `make repro` and `make test`. Both create .venv when missing
# and (re)install the project into it when requirements.lock or pyproject.toml changed;
# `make lock` refreshes requirements.lock from pyproject.toml.

PYTHON ?= python3
VENV ?= .venv
BIN := $(VENV)/bin
PIP := $(BIN)/python -m pip --disable-pip-version-check
STAMP := $(VENV)/.installed
# Every package the venv and the image install, pinned with its hashes (`make lock` writes it),
# and the simulator's pins from it, which the stages that step an environment depend on.
LOCK := requirements.lock
SIMULATOR_LOCK := simulator.lock
# torch is installed first, by itself. Empty: from pip's own configuration (on our machines the
# local CPU wheel), checked against the lock's hash. Elsewhere name PyTorch's index, e.g.
# https://download.pytorch.org/whl/cpu (or a CUDA one): the locked version, in that index's build.
TORCH_INDEX_URL ?=
# `make lock` keeps every pin pyproject.toml still allows; LOCK_UPGRADE=all re-resolves everything
# at today's versions, LOCK_UPGRADE="mujoco gymnasium" just those.
LOCK_UPGRADE ?=
PIP_TOOLS := pip-tools==7.6.2
# MuJoCo renders headless through EGL (Mesa's software EGL works with no GPU); set MUJOCO_GL=osmesa
# to use OSMesa instead.
export MUJOCO_GL ?= egl
PYTEST_ARGS ?=
# The suite runs across this many processes (pytest-xdist; `auto`: one per core); 0 runs it in one.
PYTEST_WORKERS ?= auto
# Stages call `ede-pipeline` and `dvc` by name.
export PATH := $(abspath $(BIN)):$(PATH)

.PHONY: install lock repro quick experiment experiments lint test test-fast container-test clean-venv

install: $(STAMP)

$(STAMP): $(LOCK) pyproject.toml scripts/lock.py
	@$(PYTHON) -c 'import sys; sys.exit(sys.version_info < (3, 11))' \
		|| { echo "error: $(PYTHON) is older than 3.11; set PYTHON=python3.11 or newer" >&2; exit 2; }
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python scripts/lock.py select $(LOCK) --only torch >$(VENV)/torch.lock
	$(BIN)/python scripts/lock.py select $(LOCK) --without torch >$(VENV)/rest.lock
ifeq ($(TORCH_INDEX_URL),)
	$(PIP) install --quiet --require-hashes --no-deps -r $(VENV)/torch.lock \
		|| { echo "error: no torch wheel with the locked hash here; set TORCH_INDEX_URL" >&2; exit 2; }
else
	$(PIP) install --quiet --extra-index-url $(TORCH_INDEX_URL) \
		"torch==$$($(BIN)/python scripts/lock.py version $(LOCK) torch | cut -d+ -f1)"
endif
	$(PIP) install --quiet --require-hashes --no-deps -r $(VENV)/rest.lock
	$(PIP) install --quiet --no-deps --no-build-isolation -e .
	$(PIP) check
	touch $(STAMP)

# Re-resolve pyproject.toml (every extra, the build requirements) into requirements.lock with
# pip-tools, and copy the simulator's pins out of it. Review the diff; commit both files.
lock:
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(PIP) install --quiet $(PIP_TOOLS)
	CUSTOM_COMPILE_COMMAND="make lock" $(BIN)/pip-compile --quiet --all-extras --all-build-deps \
		--generate-hashes --strip-extras --allow-unsafe --no-emit-index-url --no-emit-find-links \
		$(if $(filter all,$(LOCK_UPGRADE)),--upgrade,$(addprefix --upgrade-package=,$(LOCK_UPGRADE))) \
		--output-file $(LOCK) pyproject.toml
	$(BIN)/python scripts/lock.py simulator $(LOCK) $(SIMULATOR_LOCK)

# The pipeline through the sweep (README.md, "Sweeps: in parallel and on a cluster"): every
# out-of-date stage in dependency order, side by side on every core where they do not depend on
# each other (the families' collect and pretrain stages, then the runs, seeds grouped into one
# process where that is faster, then the report), with one overall progress line. Plain
# `dvc repro` is the serial way, with the same record.
repro: install
	$(BIN)/ede-pipeline sweep

# The quick look (experiments/quick.yaml), run as every committed experiment is (below): the runs
# side by side on every core, in a working copy of its own, saved as the DVC experiment `quick`;
# `dvc exp apply quick` brings its params, dvc.lock and outputs (the report) into the workspace.
# Run again, it resumes, or reruns what your changes to the code touch (--update-code).
quick: install
	$(BIN)/ede-pipeline experiment run quick --update-code $(ARGS)

# One committed experiment (experiments/NAME.yaml), e.g. `make experiment NAME=reacher-vertical
# ARGS="--jobs 2"`: run by the sweep in its own working copy, resumable, saved as a DVC experiment
# (docs/parameters.md, "The committed experiments").
experiment: install
	@test -n "$(NAME)" || { echo "error: NAME=<an experiment of experiments/>; they are:" >&2; \
		$(BIN)/ede-pipeline experiment list >&2; exit 2; }
	$(BIN)/ede-pipeline experiment run $(NAME) $(ARGS)

# The experiments of this commit in 80 columns: per experiment its changed params and the report's
# final return and area under the curve per task and algorithm (README.md, "Comparing experiments").
experiments: install
	$(BIN)/ede-pipeline experiment show

# What every change must pass before its tests: ruff's lint and format check (the rules are
# pyproject.toml's [tool.ruff]; `ruff check --fix .` and `ruff format .` mend most findings), and
# mypy's type check of the packages, the benchmarks and the tests ([tool.mypy]). The packages
# install under other names than their folders (pyproject.toml's package-dir: envs/ is
# ede_envs), which mypy cannot map: it reads them through links of those names in $(TYPING).
TYPING := $(VENV)/typing
lint: install
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .
	mkdir -p $(TYPING)
	ln -sfn $(CURDIR)/envs $(TYPING)/ede_envs
	ln -sfn $(CURDIR)/pipeline $(TYPING)/ede_pipeline
	MYPYPATH=$(TYPING) $(BIN)/mypy ede $(TYPING)/ede_envs $(TYPING)/ede_pipeline benchmarks tests

# The whole suite, its tests spread over the cores (each works in its own scratch directory).
test: lint
	$(BIN)/pytest -n $(PYTEST_WORKERS) --dist worksteal $(PYTEST_ARGS)

# The tests not marked slow (no end-to-end pipeline, sweep or cluster), for the edit-test loop.
test-fast: install
	$(BIN)/pytest -n $(PYTEST_WORKERS) --dist worksteal -m "not slow" $(PYTEST_ARGS)

# The image, built with podman and run for real (README.md, "Batch jobs"); needs root, installs
# podman, runc and debootstrap with apt when missing.
container-test: install
	scripts/container-test.sh

clean-venv:
	rm -rf $(VENV)
