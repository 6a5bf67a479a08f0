"""``ede-pipeline task-code``: what defines each task of a family, for DVC to depend on.

A stage that steps a task depends on that task's record
(``data/families/<family>/code/<task>.json``, or a copy of it) instead of on all of ``envs/``:
the ``task_code`` stage reruns on any edit of ``envs/`` (it is cheap), but rewrites only the
records whose files changed, so DVC reruns only the stages of the tasks that really changed (see :func:`ede_pipeline.closure.task_code`).
"""

from __future__ import annotations

import json
from pathlib import Path

import click

from ede.config import Params
from ede.io.atomic import write_atomically
from ede_pipeline import layout
from ede_pipeline.closure import task_code as describe
from ede_pipeline.common import check_family, family_option, holding, params_option

KIND = "folder of task records"


@click.command("task-code")
@family_option
@click.option(
    "--out",
    type=click.Path(path_type=Path),
    help="Folder of one JSON record per task  [default: data/families/<family>/code]",
)
@params_option
def task_code(params: Params, family: str, out: Path | None) -> None:
    """Record the files and registration that define each task of a family."""
    check_family(params, family)
    out = out or layout.code(family)
    records = {task: describe(task) for task in params.families[family].tasks}

    def write(folder: Path) -> None:
        for task, record in records.items():
            path = folder / f"{task}.json"
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_text(json.dumps(record, indent=2, allow_nan=False) + "\n")

    with holding((out, KIND)):
        write_atomically(out, write, KIND)
    click.echo(f"{family}: {len(records)} task records in {out}")
