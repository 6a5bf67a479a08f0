"""Each DVC stage depends on all of our code it runs: its import closure, found statically.

A stage runs ``ede-pipeline <command>``: the stage's own module of ``pipeline/`` and everything of
ours it imports, transitively (imports inside functions too; ``ede_pipeline.closure``). The CLI's
dispatcher imports every stage module but runs only one, so it contributes only its own imports
of ``ede``. The code of ``envs/`` runs through gymnasium's entry points, one task at a time: a
stage covers it by depending on the record of each task it steps
(``data/families/<family>/code/<task>.json``, written by the ``task_code`` stage, which itself
depends on all of ``envs/``, or a folder that holds it). Importing
``ede_envs`` only registers the tasks (``envs/__init__.py``): that
changes nothing a stage computes unless it makes a task, and a task's record holds its registration.
"""

from __future__ import annotations

import pytest
import yaml

from ede_pipeline.closure import closure, imports_of, package_dirs
from tests.support import REPO

DIRS = package_dirs()
ENVS = DIRS["ede_envs"]
REGISTRATION = {ENVS / "__init__.py"}
STAGE_MODULES = {
    "task_code": "ede_pipeline.task_code",
    "collect": "ede_pipeline.collect",
    "pretrain_encoder": "ede_pipeline.pretrain",
    "pretrain_decoder": "ede_pipeline.pretrain",
    "task_inputs": "ede_pipeline.task_inputs",
    "train": "ede_pipeline.train",
    "report": "ede_pipeline.report.command",
}
# The stages that step tasks, and what holds the record of each task they step, as dvc.yaml
# writes it: the record itself, the task's folder (a copy of it, ``ede-pipeline task-inputs``) or
# every family's folder (all records).
TASK_RECORDS = {
    "collect": "data/families/${key}/code/${item.source}.json",
    "train": "data/tasks/${item.task}",
    "report": "data/families",
}


def stage(name: str) -> dict:
    definition = yaml.safe_load((REPO / "dvc.yaml").read_text())["stages"][name]
    return definition.get("do", definition)


def dispatcher_imports() -> list[str]:
    cli = DIRS["ede_pipeline"] / "cli.py"
    return [m for m in imports_of(cli, "ede_pipeline.cli") if m.partition(".")[0] == "ede"]


def test_the_checkout_is_what_is_imported() -> None:
    assert DIRS == {
        "ede": REPO / "ede",
        "ede_envs": REPO / "envs",
        "ede_pipeline": REPO / "pipeline",
    }


@pytest.mark.parametrize("name", list(STAGE_MODULES))
def test_a_stages_deps_cover_the_code_it_runs(name: str) -> None:
    deps = stage(name)["deps"]
    paths = [REPO / d for d in deps]
    records = TASK_RECORDS.get(name) in deps
    needed = closure([STAGE_MODULES[name], *dispatcher_imports()], DIRS) | {
        DIRS["ede_pipeline"] / "cli.py"
    }
    missing = sorted(
        str(p.relative_to(REPO))
        for p in needed
        if not any(p == d or p.is_relative_to(d) for d in paths)
        and not (p.is_relative_to(ENVS) and (records or p in REGISTRATION))
    )
    assert not missing, (
        f"dvc.yaml: stage {name} runs {', '.join(missing)} but does not depend on it"
    )


@pytest.mark.parametrize("name", list(TASK_RECORDS))
def test_a_stage_that_steps_a_task_depends_on_its_record_not_on_all_of_envs(name: str) -> None:
    deps = stage(name)["deps"]
    assert TASK_RECORDS[name] in deps
    assert "envs" not in deps, f"stage {name}: an edit to any task would rerun it"


def test_the_task_code_stage_reads_all_of_envs() -> None:
    assert "envs" in stage("task_code")["deps"] and "simulator.lock" in stage("task_code")["deps"]


def test_the_closure_follows_imports_inside_functions() -> None:
    files = closure(["ede_pipeline.train"], DIRS)
    assert REPO / "ede/method/td3.py" in files and REPO / "ede/method/nets.py" in files
    assert not any(file.is_relative_to(REPO / "pipeline/sweep") for file in files)
    task = closure(["ede_envs.reacher_push"], DIRS)
    assert task == {
        REPO / "envs/reacher_push.py",
        REPO / "envs/reacher.py",
        REPO / "envs/_numerics.py",
        REPO / "envs/_actions.py",
    }
