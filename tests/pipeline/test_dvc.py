"""The DVC pipeline runs the same commands as a shell would, in a scratch copy of the repo."""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path

import pytest
import yaml
from pydantic import BaseModel

from ede.io.rollouts import Rollouts
from tests.support import REPO, dvc


def test_dvc_collect_stage_writes_the_store_and_is_then_up_to_date(repo_copy: Path) -> None:
    result = dvc(repo_copy, "repro", "collect@point")
    assert result.returncode == 0, result.stdout + result.stderr
    rollouts = Rollouts.open(repo_copy / "data/families/point/rollouts.zarr", env_id="ede/Point-v0")
    assert len(rollouts) == 200
    again = dvc(repo_copy, "repro", "collect@point")
    assert "didn't change, skipping" in again.stdout or "up to date" in again.stdout, again.stdout
    lock = yaml.safe_load((repo_copy / "dvc.lock").read_text())
    assert lock["stages"]["collect@point"]["params"]["params.yaml"]["collect"]["steps"] == 200


def stale(copy: Path) -> set[str]:
    """The stages ``dvc status`` reports out of date."""
    result = dvc(copy, "status")
    assert result.returncode == 0, result.stdout + result.stderr
    return {
        line[:-1]
        for line in result.stdout.splitlines()
        if line and not line[0].isspace() and line.endswith(":")
    }


@pytest.mark.slow
def test_dvc_repro_runs_every_stage_then_a_td3_param_stales_only_the_runs(
    repo_copy: Path, tiny_pipeline: Callable[[dict], None]
) -> None:
    params_file = repo_copy / "params.yaml"
    params = yaml.safe_load(params_file.read_text())
    tiny_pipeline(params)
    # Every family, and of the tasks those whose edits are tried below, a task of each family's
    # that is not its source (collect steps the source): every stage runs, at 6 runs of 10.
    params["runs"]["tasks"] = {
        task: family
        for task, family in params["runs"]["tasks"].items()
        if task in ("ede/ReacherTurn-v0", "ede/ReacherPush-v0", "ede/Striker-v0")
    }
    params_file.write_text(yaml.safe_dump(params, sort_keys=False))

    first = dvc(repo_copy, "repro")
    assert first.returncode == 0, first.stdout[-3000:] + first.stderr[-3000:]
    # Nothing a user cannot act on: DVC's and the libraries' warnings are dealt with at the source
    # (an empty __init__.py among the stages' dependencies once printed one per stage and file).
    warned = [line for line in (first.stdout + first.stderr).splitlines() if "warn" in line.lower()]
    assert warned == [], warned[:5]
    page = (repo_copy / "data/report/index.html").read_text()
    for section in (
        "Learning curves",
        "Across tasks",
        "Figure 6",
        "Figure 7",
        "Missing and excluded runs",
        "Provenance",
    ):
        assert section in page
    assert "None: every run the params name is here." in page
    # Per task, TD3 beside EDE-TD3 played from the policies the train stages wrote.
    assert page.count("<video") == len(params["runs"]["tasks"]), page.count("<video")
    # curves and diagnostics per family, the performance profile across tasks, Figures 6 and 7
    assert page.count("data:image/png;base64,") == 7
    assert "diagnostics-reacher" in page and "diagnostics-sevendof" in page

    # Where and how fast runs go changes no result: nothing is stale.
    faster = {**params, "td3": {**params["td3"], "threads": 2, "checkpoint_every": 50}}
    params_file.write_text(yaml.safe_dump(faster, sort_keys=False))
    assert stale(repo_copy) == set()
    # One task's budget: that task's runs and the report, nothing else.
    longer = {
        **params,
        "runs": {
            **params["runs"],
            "budgets": {**params["runs"]["budgets"], "ede/ReacherTurn-v0": 300},
        },
    }
    params_file.write_text(yaml.safe_dump(longer, sort_keys=False))
    assert stale(repo_copy) == {"report"} | {
        f"train@ede/ReacherTurn-v0-{algo}-0" for algo in params["runs"]["algos"]
    }

    params_file.write_text(yaml.safe_dump(params, sort_keys=False))
    # One task's code: the record task_code writes after an edit of envs/reacher_push.py (whose
    # effect on the records tests/pipeline/test_task_code.py shows) stales that task's inputs (the
    # copy its runs read, and so its runs only) and the report (which reads every family's folder).
    record = repo_copy / "data/families/reacher/code/ede/ReacherPush-v0.json"
    original = record.read_text()
    edited = json.loads(original)
    edited["files"]["ede_envs/reacher_push.py"] = "0" * 64
    record.write_text(json.dumps(edited, indent=2) + "\n")
    assert stale(repo_copy) == {"task_code@reacher", "task_inputs@ede/ReacherPush-v0", "report"}
    record.write_text(original)
    assert stale(repo_copy) == set()

    # A TD3 param: every run, nothing upstream (`dvc repro` runs what `dvc status` lists, and
    # after them the report, whose inputs they rewrite).
    params["td3"]["tau"] = 0.01
    params_file.write_text(yaml.safe_dump(params, sort_keys=False))
    tasks, algos = params["runs"]["tasks"], params["runs"]["algos"]
    assert stale(repo_copy) == {f"train@{task}-{algo}-0" for task in tasks for algo in algos}


def test_every_param_that_changes_a_result_is_tracked_by_key() -> None:
    """dvc.yaml lists its params by hand (DVC reads it literally): every key the config does not
    mark result-neutral (``ede.config.result_neutral``: threads, device, ...) and none that it does."""
    from ede.config import Params, result_neutral

    stages = yaml.safe_load((REPO / "dvc.yaml").read_text())["stages"]
    tracked = {key for stage in stages.values() for key in stage.get("do", stage).get("params", [])}
    untracked: set[str] = set()
    for section in ("embedding", "decoder", "td3", "ede_td3"):
        model = Params.model_fields[section].annotation
        assert isinstance(model, type) and issubclass(model, BaseModel), section
        neutral = result_neutral(model)
        untracked |= neutral
        for field in model.model_fields:
            key = f"{section}.{field}"
            if field in neutral:
                assert key not in tracked and section not in tracked, (
                    f"{key} changes no result but dvc.yaml tracks it"
                )
            else:
                assert key in tracked or section in tracked, f"dvc.yaml does not track {key}"
    assert {"threads", "device"} <= untracked  # the marks are read at all
