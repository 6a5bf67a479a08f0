"""``ede-pipeline task-inputs``: what a task's runs read from its family, in the task's folder.

``dvc.yaml`` has one ``train`` stage over every run (task × algorithm × seed of ``runs``), so a
run's dependencies cannot name its family's folder: DVC's templates give a matrix the keys of
``runs.tasks``, not the family each maps to. The ``task_inputs`` stage, one per key (where DVC
does give the family), copies the family's encoder and decoder and the task's code record into
``data/tasks/<task>/``, which the task's runs depend on and read. Editing one family's embedding
then reruns that family's runs only.
"""

from __future__ import annotations

import shutil
from pathlib import Path

import click

from ede.config import Params
from ede.io.atomic import write_atomically
from ede.run.artifacts import ArtifactError, load_action_embedding
from ede_pipeline import layout
from ede_pipeline.common import BadInput, holding, params_option

KIND = "task's inputs"
CODE = "code.json"  # the task's record in its folder (``ede-pipeline task-code``)


@click.command("task-inputs")
@click.option("--task", required=True, help="A task of params.yaml's runs.tasks.")
@click.option(
    "--embedding",
    type=click.Path(path_type=Path),
    help="The family's embedding folder  [default: data/families/<family>/embedding]",
)
@click.option(
    "--code",
    type=click.Path(path_type=Path),
    help="The family's task records  [default: data/families/<family>/code]",
)
@click.option(
    "--out", type=click.Path(path_type=Path), help="The task's folder  [default: data/tasks/<task>]"
)
@params_option
def task_inputs(
    params: Params, task: str, embedding: Path | None, code: Path | None, out: Path | None
) -> None:
    """Copy the task's family's encoder and decoder, and the task's code record, into its folder."""
    if task not in params.runs.tasks:
        raise BadInput(
            f"--task {task!r}: not in params.yaml's runs.tasks ({', '.join(params.runs.tasks)})"
        )
    family = params.runs.tasks[task]
    embedding = embedding or layout.embedding(family)
    record = (code or layout.code(family)) / f"{task}.json"
    try:
        meta, _ = load_action_embedding(embedding / layout.ENCODER, embedding / layout.DECODER)
    except ArtifactError as error:
        raise BadInput(
            f"--embedding {embedding}: {error} (the {family} family's, from "
            "`ede-pipeline pretrain`)"
        ) from None
    if meta.family != family:
        raise BadInput(
            f"--embedding {embedding}: the embedding of family {meta.family}, but "
            f"runs.tasks.{task} is {family}"
        )
    if not record.is_file():
        raise BadInput(
            f"--code {record.parent}: no record of {task}; expected {record} "
            "(`ede-pipeline task-code`)"
        )
    out = out or layout.task_inputs(task)

    def write(folder: Path) -> None:
        for name in (layout.ENCODER, layout.DECODER):
            shutil.copytree(embedding / name, folder / name)
        shutil.copyfile(record, folder / CODE)

    with holding((out, KIND), inputs=(embedding, record.parent)):
        write_atomically(out, write, KIND)
    click.echo(f"{task}: the {family} family's embedding ({meta.identity[:12]}) in {out}")
