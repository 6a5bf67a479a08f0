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


def stale(copy: Path) -> set[str]:
    """The stages ``dvc status`` reports out of date."""
    result = dvc(copy, "status")
    assert result.returncode == 0, result.stdout + result.stderr
    return {line[:-1] for line in result.stdout.splitlines() if line and not line[0].isspace()
            and line.endswith(":")}


def tiny_pipeline(params: dict) -> None:
    """Every stage at the smallest size that still exercises it."""
    params["collect"].update(steps=200, num_envs=1)
    small = {"hidden": [16, 16], "epochs": 1, "batch_size": 64}
    params["embedding"].update(small, holdout=0.5)
    params["decoder"].update(small)
    params["td3"].update(hidden=[16, 16], batch_size=32, start_steps=50, eval_every=100,
                         eval_episodes=1, checkpoint_every=1000, buffer_size=1000)
    params["runs"].update(seeds=[0], budgets={task: 200 for task in params["runs"]["budgets"]})
    params["report"].update(bootstrap_samples=100)


@pytest.mark.slow
def test_dvc_repro_runs_every_stage_then_reruns_only_what_a_td3_param_touches(
    repo_copy: Path,
) -> None:
    params_file = repo_copy / "params.yaml"
    params = yaml.safe_load(params_file.read_text())
    tiny_pipeline(params)
    params_file.write_text(yaml.safe_dump(params, sort_keys=False))

    first = dvc(repo_copy, "repro")
    assert first.returncode == 0, first.stdout[-3000:] + first.stderr[-3000:]
    page = (repo_copy / "data/report/index.html").read_text()
    for section in ("Learning curves", "Figure 6", "Figure 7", "Missing runs", "Provenance"):
        assert section in page
    assert "None: every run the params name is here." in page
    assert page.count("data:image/png;base64,") == 6  # curves and diagnostics per family, Figures 6, 7
    assert "diagnostics-reacher" in page and "diagnostics-sevendof" in page

    # Where and how fast runs go changes no result: nothing is stale.
    faster = {**params, "td3": {**params["td3"], "threads": 2, "checkpoint_every": 50}}
    params_file.write_text(yaml.safe_dump(faster, sort_keys=False))
    assert stale(repo_copy) == set()
    # One task's budget: that task's runs and the report, nothing else.
    longer = {**params, "runs": {**params["runs"], "budgets": {**params["runs"]["budgets"],
                                                               "ede/ReacherTurn-v0": 300}}}
    params_file.write_text(yaml.safe_dump(longer, sort_keys=False))
    assert stale(repo_copy) == {"report"} | {
        f"train_reacher@ede/ReacherTurn-v0-{algo}-0" for algo in params["runs"]["algos"]}

    params["td3"]["tau"] = 0.01
    params_file.write_text(yaml.safe_dump(params, sort_keys=False))
    second = dvc(repo_copy, "repro")
    assert second.returncode == 0, second.stdout[-3000:] + second.stderr[-3000:]
    ran = {line.split("'")[1] for line in second.stdout.splitlines() if line.startswith("Running stage")}
    runs = sum(len(tasks) for tasks in params["runs"]["tasks"].values()) * 2
    assert len(ran) == runs + 1 and "report" in ran, sorted(ran)
    assert all(stage.startswith("train_") for stage in ran - {"report"}), sorted(ran)


# Settings that change how fast or where a stage runs, never its result: DVC does not track them.
UNTRACKED = {"td3.threads", "td3.device", "td3.checkpoint_every", "embedding.threads",
             "embedding.device", "decoder.threads", "decoder.device"}


def test_every_param_that_changes_a_result_is_tracked_by_key() -> None:
    from ede.config import Params

    stages = yaml.safe_load((REPO / "dvc.yaml").read_text())["stages"]
    tracked = {key for stage in stages.values() for key in stage.get("do", stage).get("params", [])}
    for section in ("embedding", "decoder", "td3", "ede_td3"):
        model = Params.model_fields[section].annotation
        for field in model.model_fields:
            key = f"{section}.{field}"
            if key in UNTRACKED:
                assert key not in tracked, f"{key} changes no result but dvc.yaml tracks it"
            else:
                assert key in tracked or section in tracked, f"dvc.yaml does not track {key}"
