"""Fixtures shared by every test package.

Tests take what they share from fixtures here and in each package's ``conftest.py``, never from
another test module; the checkout's root (``REPO``) and scratch copies of it come from
``tests.support``, which the benchmarks use too.
"""

from __future__ import annotations

import copy
import os
import shutil
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
import yaml

from tests.support import REPO, dvc, ok, one_task_upstream, train_record

# Render headless (Mesa's EGL needs no GPU or display); `MUJOCO_GL=osmesa pytest` overrides.
os.environ.setdefault("MUJOCO_GL", "egl")
# DVC runs a stage's command with $SHELL, /bin/sh where it is unset: in CI, in containers, under
# cron. Run it so here too: dash does not become the command it runs, and a stage must work so.
os.environ.pop("SHELL", None)


@pytest.fixture(scope="session")
def committed_params() -> dict[str, Any]:
    """The committed ``params.yaml`` as plain data."""
    return yaml.safe_load((REPO / "params.yaml").read_text())


@pytest.fixture
def write_params(tmp_path: Path, committed_params: dict[str, Any]) -> Callable[..., Path]:
    """Write the committed params with changes applied; returns the file's path.

    ``write_params(edit)`` calls ``edit(data)`` on a deep copy of the committed params.
    """

    def write(
        edit: Callable[[dict[str, Any]], None] | None = None, name: str = "params.yaml"
    ) -> Path:
        data = copy.deepcopy(committed_params)
        if edit is not None:
            edit(data)
        path = tmp_path / name
        path.write_text(yaml.safe_dump(data, sort_keys=False))
        return path

    return write


@pytest.fixture(scope="session")
def built_once(
    tmp_path_factory: pytest.TempPathFactory,
) -> Callable[[str, Callable[[Path], None]], Path]:
    """``built_once(name, build)``: a folder ``build(folder)`` filled once for the whole session,
    whichever of pytest-xdist's worker processes asks first; the others wait for it and get the
    same folder (a session fixture alone runs once a worker). Its users only read it: a test that
    writes copies it first."""
    root = tmp_path_factory.getbasetemp()
    if os.environ.get("PYTEST_XDIST_WORKER"):  # each worker's basetemp is a folder of the run's
        root = root.parent

    def get(name: str, build: Callable[[Path], None]) -> Path:
        from filelock import FileLock

        folder, done = root / name, root / f"{name}.built"
        with FileLock(root / f"{name}.lock"):
            if not done.exists():
                shutil.rmtree(folder, ignore_errors=True)  # a build that failed before
                folder.mkdir()
                build(folder)
                done.touch()
        return folder

    return get


@pytest.fixture(scope="session")
def point_store(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A small rollouts store of ``ede/Point-v0`` (40 episodes), written once per session."""
    from ede.io.rollouts import write_store
    from ede.run.collect import collect

    path = tmp_path_factory.mktemp("point") / "rollouts.zarr"
    arrays = collect("ede/Point-v0", steps=4_000, num_envs=1, seed=0, workers=1)
    attrs = {
        "env_id": "ede/Point-v0",
        "family": "point",
        "seed": 0,
        "num_envs": 1,
        "steps": 4_000,
        "spaces": {"action_low": [-1.0, -1.0], "action_high": [1.0, 1.0]},
        "params": {},
    }
    write_store(path, arrays, attrs)
    return path


def _tiny_pipeline(params: dict[str, Any]) -> None:
    params["collect"].update(steps=200, num_envs=1)
    small: dict[str, Any] = {"hidden": [16, 16], "epochs": 1, "batch_size": 64}
    params["embedding"].update(small, holdout=0.5)
    params["decoder"].update(small)
    params["td3"].update(
        hidden=[16, 16],
        batch_size=32,
        start_steps=50,
        eval_every=100,
        eval_episodes=1,
        checkpoint_every=1000,
        buffer_size=1000,
    )
    params["runs"].update(seeds=[0], budgets={task: 200 for task in params["runs"]["budgets"]})
    params["report"].update(bootstrap_samples=100)


@pytest.fixture(scope="session")
def tiny_pipeline() -> Callable[[dict[str, Any]], None]:
    """Shrinks params (plain data, in place) to every stage at the smallest size that still
    exercises it."""
    return _tiny_pipeline


REACHER = "ede/ReacherVertical-v0"  # the task of the sweeps' runs below


@pytest.fixture(scope="session")
def reacher_upstream(
    built_once: Callable[[str, Callable[[Path], None]], Path],
    tiny_pipeline: Callable[[dict[str, Any]], None],
) -> Path:
    """A scratch copy at the tiny pipeline whose runs, both algorithms on ``REACHER`` (1,000 steps,
    a checkpoint every 200), have their embedding made and no run yet
    (:func:`tests.support.one_task_upstream`); made once a session, and copied by whoever runs."""

    def make(folder: Path) -> None:
        one_task_upstream(folder / "repo", tiny_pipeline, REACHER)

    return built_once("reacher-upstream", make) / "repo"


@pytest.fixture(scope="session")
def reacher_reference(
    built_once: Callable[[str, Callable[[Path], None]], Path], reacher_upstream: Path
) -> tuple[dict[str, Any], float]:
    """What ``dvc repro train`` of :func:`reacher_upstream`'s runs records
    (:func:`tests.support.train_record`), and the seconds it took; made once a session."""

    def train(folder: Path) -> None:
        copy = folder / "repo"
        shutil.copytree(reacher_upstream, copy, symlinks=True)
        start = time.perf_counter()
        ok(dvc(copy, "repro", "train"))
        (folder / "seconds").write_text(str(time.perf_counter() - start))

    folder = built_once("reacher-reference", train)
    return train_record(folder / "repo"), float((folder / "seconds").read_text())
