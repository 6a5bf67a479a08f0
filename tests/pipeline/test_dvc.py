"""The DVC pipeline runs the same commands as a shell would, in a scratch copy of the repo."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from ede.rollouts import Rollouts
from tests.conftest import REPO


@pytest.fixture
def repo_copy(tmp_path: Path) -> Path:
    """The tracked files of this repo in a fresh git repository, with tiny params."""
    files = subprocess.run(
        ["git", "ls-files", "--cached", "--others", "--exclude-standard"],
        cwd=REPO, capture_output=True, text=True, check=True,
    ).stdout.split()
    copy = tmp_path / "repo"
    for name in files:
        if (REPO / name).is_file():
            (copy / name).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(REPO / name, copy / name)
    params = yaml.safe_load((copy / "params.yaml").read_text())
    params["collect"].update(steps=200, num_envs=1)
    (copy / "params.yaml").write_text(yaml.safe_dump(params, sort_keys=False))
    for command in (["git", "init", "-q"], ["git", "add", "-A"]):
        subprocess.run(command, cwd=copy, check=True)
    return copy


def dvc(copy: Path, *args: str) -> subprocess.CompletedProcess[str]:
    bin_dir = str(Path(sys.executable).parent)
    env = {**os.environ, "PATH": f"{bin_dir}{os.pathsep}{os.environ['PATH']}"}
    return subprocess.run(
        [str(Path(bin_dir) / "dvc"), *args], cwd=copy, env=env, capture_output=True, text=True
    )


def test_dvc_collect_stage_writes_the_store_and_is_then_up_to_date(repo_copy: Path) -> None:
    result = dvc(repo_copy, "repro", "collect@point")
    assert result.returncode == 0, result.stdout + result.stderr
    rollouts = Rollouts.open(repo_copy / "data/point/rollouts.zarr", env_id="ede/Point-v0")
    assert len(rollouts) == 200
    again = dvc(repo_copy, "repro", "collect@point")
    assert "didn't change, skipping" in again.stdout or "up to date" in again.stdout, again.stdout
    lock = yaml.safe_load((repo_copy / "dvc.lock").read_text())
    assert lock["stages"]["collect@point"]["params"]["params.yaml"]["collect"]["steps"] == 200
