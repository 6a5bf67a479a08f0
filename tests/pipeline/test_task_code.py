"""Task records: an edit to one task's files changes that task's record and no other's."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest
from click.testing import CliRunner

from ede.io.atomic import MARK
from ede_envs import TASKS
from ede_pipeline.cli import main
from ede_pipeline.closure import package_dirs, task_code, task_record

REACHER = ("ede/ReacherVertical-v0", "ede/ReacherTurn-v0", "ede/ReacherPush-v0")
MODELS = {
    "ede/ReacherVertical-v0": "reacher_vertical.xml",
    "ede/ReacherTurn-v0": "reacher_turn.xml",
    "ede/ReacherPush-v0": "reacher_push.xml",
    "ede/Point-v0": "point.xml",
}


@pytest.fixture
def envs_copy(tmp_path: Path) -> dict[str, Path]:
    """Our packages as installed, with ``ede_envs`` replaced by a copy that a test may edit."""
    dirs = package_dirs()
    copy = tmp_path / "envs"
    shutil.copytree(dirs["ede_envs"], copy, ignore=shutil.ignore_patterns("__pycache__"))
    return {**dirs, "ede_envs": copy}


def records(dirs: dict[str, Path]) -> dict[str, dict]:
    return {
        task: task_record(
            task, TASKS[task].entry_point, 100, {}, dirs["ede_envs"] / "assets" / model, dirs
        )
        for task, model in MODELS.items()
    }


def changed(before: dict[str, dict], after: dict[str, dict]) -> set[str]:
    return {task for task in before if before[task] != after[task]}


def test_a_record_names_the_tasks_module_its_imports_and_its_model_files() -> None:
    record = task_code("ede/ReacherPush-v0")
    assert set(record["files"]) == {
        "ede_envs/reacher_push.py",
        "ede_envs/reacher.py",
        "ede_envs/_numerics.py",
        "ede_envs/_actions.py",
        "ede_envs/assets/reacher_push.xml",
        "ede_envs/assets/reacher_arm.xml",
    }
    assert record["entry_point"] == TASKS["ede/ReacherPush-v0"].entry_point
    assert record["max_episode_steps"] == 100
    # gymnasium's own model file, named from its package
    assert "gymnasium/envs/mujoco/assets/pusher_v5.xml" in task_code("ede/Pusher-v0")["files"]


def test_the_records_of_the_copy_equal_the_installed_ones(envs_copy: dict[str, Path]) -> None:
    assert records(envs_copy) == {task: task_code(task) for task in MODELS}


@pytest.mark.parametrize(
    ("edited", "expected"),
    [
        ("reacher_push.py", {"ede/ReacherPush-v0"}),
        ("assets/reacher_turn.xml", {"ede/ReacherTurn-v0"}),
        ("reacher.py", set(REACHER)),
        ("assets/reacher_arm.xml", set(REACHER)),  # included by the three task models
        ("_numerics.py", set(MODELS)),
        ("point.py", {"ede/Point-v0"}),
        ("striker.py", set()),
    ],
)
def test_an_edit_changes_the_records_of_exactly_the_tasks_that_run_the_file(
    envs_copy: dict[str, Path], edited: str, expected: set[str]
) -> None:
    before = records(envs_copy)
    with open(envs_copy["ede_envs"] / edited, "a") as handle:
        handle.write("\n")
    assert changed(before, records(envs_copy)) == expected


def test_the_command_writes_one_record_per_task_of_the_family(tmp_path: Path, write_params) -> None:
    params = write_params()
    out = tmp_path / "code"
    result = CliRunner().invoke(
        main, ["task-code", "--family", "reacher", "--params", str(params), "--out", str(out)]
    )
    assert result.exit_code == 0, result.output
    written = sorted(str(p.relative_to(out)) for p in out.rglob("*.json") if p.name != MARK)
    assert written == sorted(f"{task}.json" for task in REACHER)
    assert json.loads((out / MARK).read_text())["kind"] == "folder of task records"
    assert json.loads((out / "ede/ReacherTurn-v0.json").read_text()) == task_code(
        "ede/ReacherTurn-v0"
    )
    assert not list(tmp_path.glob("code.tmp-*"))


def test_an_unknown_family_is_one_line_and_nothing_written(tmp_path: Path, write_params) -> None:
    result = CliRunner().invoke(
        main,
        [
            "task-code",
            "--family",
            "nope",
            "--params",
            str(write_params()),
            "--out",
            str(tmp_path / "code"),
        ],
    )
    assert result.exit_code == 2
    assert result.output.strip().count("\n") == 0 and "--family 'nope'" in result.output
    assert not (tmp_path / "code").exists()
