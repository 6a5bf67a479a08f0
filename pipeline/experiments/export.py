"""``ede-pipeline experiment export``: an experiment's finished runs into the published layout
(what it publishes, checked: :mod:`.export_plan`; the writing, all or nothing: :mod:`.export_write`)."""

from __future__ import annotations

from pathlib import Path

import click

from ede.io.atomic import place, unwritable
from ede.io.locks import OutputBusy, exclusive
from ede_pipeline import layout
from ede_pipeline.common import (
    DEFAULT_PARAMS,
    BadInput,
    above_working_directory,
    overlap,
    read_params,
)
from ede_pipeline.experiments.export_plan import (
    EVERY_SEED,
    finished_runs,
    plan,
    policy_seeds,
    unplayable,
)
from ede_pipeline.experiments.export_write import put_back, write
from ede_pipeline.experiments.workspace import EXPERIMENTS, WORKSPACES, experiment_file


@click.command("export")
@click.argument("name")
@click.option(
    "--to",
    "to",
    type=click.Path(path_type=Path),
    default=layout.RESULTS_RUNS,
    show_default=True,
    help="The published runs' folder.",
)
@click.option(
    "--policies",
    "policies",
    is_flag=False,
    flag_value=EVERY_SEED,
    default=None,
    metavar="[SEEDS]",
    help="Publish each run's final policy too (policy/, about 0.5 MB a run), and the decoder "
    "its EDE-TD3 runs act through, so that `ede-pipeline render` plays them; followed by "
    "seeds (4 or 4,6), those seeds' policies only.",
)
def export(name: str, to: Path, policies: str | None) -> None:
    """Copy experiment NAME's finished runs into the published layout.

    Each finished run's eval.csv, diagnostics.csv, run.json and metrics.json go to
    TO/<task>/<algo>/seed<N>/, checked first (`ede.run.runs.read_run`: the run the experiment's
    params name, finished, its files whole), and the held-out metrics of the embedding its
    EDE-TD3 runs used to TO/<task>/embedding/<checksum>/. Each task's source.json names the
    experiment file, the commits its runs were made at (an earlier export's too), its seeds,
    and report.thresholds' returns for it. With --policies, each run's policy/ goes beside its
    files, and the embedding's decoder/ beside its metrics (its encoder is not needed to play a
    policy, and stays out); with --policies SEEDS, those seeds' runs' only (a results page's clip
    plays one seed's pair: each listed seed's runs must have finished), and a policy an earlier
    export put beside one of this export's other runs goes. Without --policies, the policies
    published beside its runs stay as they are. Where the task's folder already holds seeds from
    other experiments (an experiment adding seeds to a published task), source.json keeps their
    parts beside this one; seeds already published by another experiment are refused, and so
    are runs there that `ede-pipeline results` would refuse (a folder not named seed<N>, a file
    not the one its run.json records, a seed source.json does not name, one run copied as
    another) or that were made with other params than this export's.

    An export removes or replaces only what an export wrote: a policy/ or an embedding's folder
    of its mark (`ede.io.atomic.MARK`), a published run of the experiment's own seeds; anything else
    in its way (a user's folder among the embeddings, a file where a folder goes, a symbolic
    link in a task's folder) is refused. TO is never the working directory or a folder above it,
    nor the experiment's working copy. Nothing is written unless every task's runs pass, and
    then all or nothing: each task's folder is built beside the old one and takes its place
    once every one is whole (a full disk leaves TO as it was).
    """
    workspace = WORKSPACES / name
    if problem := (
        unwritable(to, directory=True)
        or above_working_directory(to)
        or overlap(to, (workspace, EXPERIMENTS / f"{name}.yaml"))
    ):
        raise BadInput(problem)
    experiment = experiment_file(name)
    if not (workspace / DEFAULT_PARAMS).is_file():
        raise BadInput(
            f"experiment {name}: not run here yet (no {workspace}); "
            f"`ede-pipeline experiment run {name}` first"
        )
    params = read_params(workspace / DEFAULT_PARAMS)
    playable = policy_seeds(policies, name, params.runs.seeds)  # None: no --policies
    listed = policies != EVERY_SEED  # seeds named, not every one whose runs finished
    finished, problems = finished_runs(workspace, params)
    if problems:
        raise BadInput(problems[0])
    if not finished:
        raise BadInput(f"experiment {name}: no run has finished yet")
    try:
        with exclusive(to):  # one export to a place at a time
            put_back(place(to))
            plans = []  # each task's, all checked before any is written
            for task in params.runs.tasks:
                runs = [
                    (algo, seed, folder, run)
                    for (t, algo, seed), (folder, run) in finished.items()
                    if t == task
                ]
                if not runs:  # none of this task's runs has finished yet
                    click.echo(f"{task}: no run finished yet; nothing exported", err=True)
                    continue
                if playable is not None and (
                    problem := unplayable(task, runs, playable, listed, params, workspace)
                ):
                    raise BadInput(problem)
                plans.append(
                    plan(task, runs, params, experiment, playable, policies, workspace, to)
                )
            said = write(plans, to)
    except OutputBusy as error:
        raise BadInput(str(error)) from None
    for line in said:
        click.echo(line, err=True)
