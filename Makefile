# The two commands of the README: `make repro` and `make test`. Both create .venv when missing
# and (re)install the project into it when pyproject.toml or setup.py changed.

PYTHON ?= python3
VENV ?= .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
# MuJoCo renders headless through EGL (Mesa's software EGL works with no GPU); set MUJOCO_GL=osmesa
# to use OSMesa instead.
export MUJOCO_GL ?= egl
PYTEST_ARGS ?=
# Stages call `ede-pipeline` and `dvc` by name.
export PATH := $(abspath $(BIN)):$(PATH)

.PHONY: install repro quick test container-test clean-venv

install: $(STAMP)

$(STAMP): pyproject.toml setup.py
	@$(PYTHON) -c 'import sys; sys.exit(sys.version_info < (3, 11))' \
		|| { echo "error: $(PYTHON) is older than 3.11; set PYTHON=python3.11 or newer" >&2; exit 2; }
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --disable-pip-version-check -e '.[dev]'
	touch $(STAMP)

repro: install
	$(BIN)/dvc repro

# The quick look (params-quick.yaml) as a DVC experiment: params.yaml is left with its values.
quick: install
	$(BIN)/ede-pipeline set-params params-quick.yaml | xargs -d '\n' $(BIN)/dvc exp run

test: install
	$(BIN)/pytest $(PYTEST_ARGS)

# The image, built with podman and run for real (README.md, "Batch jobs"); needs root, installs
# podman, runc and debootstrap with apt when missing.
container-test: install
	scripts/container-test.sh

clean-venv:
	rm -rf $(VENV)
