"""requirements.lock against pyproject.toml, simulator.lock, dvc.yaml, the Dockerfile and this
interpreter (README.md, "Locked dependencies"). A failure here means: run `make lock` (or
`make install`) and commit what it changes."""

from __future__ import annotations

import importlib.metadata
import importlib.util
import re
import sys
import tomllib
from dataclasses import replace
from pathlib import Path
from typing import Any

import pytest
import yaml
from packaging.requirements import Requirement
from packaging.utils import canonicalize_name
from packaging.version import Version

REPO = Path(__file__).resolve().parents[1]
# What pip-compile writes after a requirement pyproject.toml names directly.
FROM_PYPROJECT = "ede (pyproject.toml)"
FROM_BUILD_SYSTEM = "ede (pyproject.toml::build-system.requires)"
# The build (CPU or CUDA, the local label of "2.13.0+cpu") is the install's choice
# (TORCH_INDEX_URL); the version is the lock's.
BUILD_CHOSEN_AT_INSTALL = {"torch"}
# The stages that step an environment, which must rerun when the simulator changes.
STEPPING_STAGES = ("collect", "train", "report")


def _lock_script():
    spec = importlib.util.spec_from_file_location("ede_lock_script", REPO / "scripts" / "lock.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses look their module up by name
    spec.loader.exec_module(module)
    return module


lock_script = _lock_script()


@pytest.fixture(scope="module")
def lock() -> dict:
    return lock_script.read(REPO / "requirements.lock")


@pytest.fixture(scope="module")
def pyproject() -> dict:
    return tomllib.loads((REPO / "pyproject.toml").read_text())


def _requirements(pyproject: dict) -> tuple[list[Requirement], list[Requirement]]:
    """The project's requirements (its dependencies and every extra) and its build requirements."""
    project = pyproject["project"]
    listed = [
        *project["dependencies"],
        *(r for rs in project["optional-dependencies"].values() for r in rs),
    ]
    return [Requirement(r) for r in listed], [
        Requirement(r) for r in pyproject["build-system"]["requires"]
    ]


def test_every_requirement_of_pyproject_is_locked_at_a_version_it_allows(lock, pyproject):
    requirements, build = _requirements(pyproject)
    problems = []
    for req in [*requirements, *build]:
        name = canonicalize_name(req.name)
        if name not in lock:
            problems.append(f"{name}: pyproject.toml asks {req}, requirements.lock has no {name}")
        elif not req.specifier.contains(lock[name].version, prereleases=True):
            problems.append(
                f"{name}: pyproject.toml asks {req}, requirements.lock has {lock[name].version}"
            )
    assert not problems, "run `make lock`:\n" + "\n".join(problems)


def test_the_lock_holds_no_direct_requirement_pyproject_dropped(lock, pyproject):
    requirements, build = _requirements(pyproject)
    for source, reqs in ((FROM_PYPROJECT, requirements), (FROM_BUILD_SYSTEM, build)):
        asked = {canonicalize_name(r.name) for r in reqs}
        locked_for = {n for n, entry in lock.items() if source in entry.via}
        stale = [
            f"{n}: requirements.lock has {lock[n].version} for {source}, which asks for none"
            for n in sorted(locked_for - asked)
        ]
        assert not stale, "run `make lock`:\n" + "\n".join(stale)


def test_simulator_lock_holds_the_locks_simulator_pins(lock):
    path = REPO / "simulator.lock"
    pins = dict(
        line.split("==")
        for line in path.read_text().splitlines()
        if line and not line.startswith("#")
    )
    expected = {name: lock[name].version for name in lock_script.SIMULATOR if name in lock}
    assert {"mujoco", "gymnasium", "numpy"} <= expected.keys()
    problems = [
        f"{name}: requirements.lock has {version}, simulator.lock has {pins.get(name)}"
        for name, version in expected.items()
        if pins.get(name) != version
    ]
    problems += [
        f"{name}: simulator.lock has {pins[name]}, which is not a simulator package"
        for name in pins.keys() - expected.keys()
    ]
    assert not problems, "run `make lock`:\n" + "\n".join(problems)
    assert path.read_text() == lock_script.simulator(lock), "run `make lock`: simulator.lock edited"


def test_simulator_pins_do_not_move_with_the_rest_of_the_lock(lock):
    moved = {
        name: replace(entry, version=entry.version + ".post99") for name, entry in lock.items()
    }
    for name in lock_script.SIMULATOR:
        moved.pop(name, None)
        if name in lock:
            moved[name] = lock[name]
    assert lock_script.simulator(moved) == lock_script.simulator(lock)


def test_the_stages_that_step_an_environment_depend_on_the_simulator_pins():
    stages = yaml.safe_load((REPO / "dvc.yaml").read_text())["stages"]
    for name in STEPPING_STAGES:
        stage = stages[name].get("do", stages[name])
        assert "simulator.lock" in stage["deps"], (
            f"dvc.yaml: {name} does not depend on simulator.lock"
        )
    for name in ("pretrain_encoder", "pretrain_decoder"):
        assert "simulator.lock" not in stages[name]["do"]["deps"], f"{name} steps no environment"


def test_the_images_torch_is_the_locked_one(lock):
    dockerfile = (REPO / "Dockerfile").read_text()
    image = re.search(r"^ARG TORCH_VERSION=(\S+)", dockerfile, re.MULTILINE)
    assert image, "Dockerfile: no ARG TORCH_VERSION"
    locked = lock["torch"].version
    assert Version(image[1]) == Version(Version(locked).public), (
        f"torch: requirements.lock has {locked}, the Dockerfile's TORCH_VERSION is {image[1]}"
    )


def test_this_interpreter_has_exactly_the_locked_versions(lock: Any) -> None:
    installed: dict[str, str] = {}
    for dist in importlib.metadata.distributions():  # sys.path order: the first one imports
        installed.setdefault(canonicalize_name(dist.metadata["Name"]), dist.version)
    problems = []
    for name, entry in lock.items():
        have = installed.get(name)
        if have is None:
            problems.append(f"{name}: requirements.lock has {entry.version}, not installed")
            continue
        want_v, have_v = Version(entry.version), Version(have)
        if name in BUILD_CHOSEN_AT_INSTALL:
            want_v, have_v = Version(want_v.public), Version(have_v.public)
        if want_v != have_v:
            problems.append(f"{name}: requirements.lock has {entry.version}, installed is {have}")
    assert not problems, f"{sys.prefix} differs from the lock (`make install`):\n" + "\n".join(
        problems
    )
