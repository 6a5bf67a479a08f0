"""``ede-pipeline experiment``: the group, ``experiment list`` and ``experiment run``."""

from __future__ import annotations

import os
import textwrap
from contextlib import ExitStack
from pathlib import Path
from typing import Any

import click

from ede.config import ParamsError, read_yaml
from ede.errors import first_line
from ede.io.locks import OutputBusy, exclusive
from ede_pipeline.common import BadInput, Failed
from ede_pipeline.experiments.export import export
from ede_pipeline.experiments.show import WIDTH, show
from ede_pipeline.experiments.workspace import (
    EXPERIMENTS,
    WORKSPACES,
    check_code_keeps_runs,
    committed_params,
    experiment_file,
    experiment_params,
    git_identity,
    mend_records,
    prepare_workspace,
    run_tool,
    uncommitted_params,
    workspace_params,
)
from ede_pipeline.sweep.plan import pipeline_repo


@click.group()
def experiment() -> None:
    """The committed experiments (experiments/NAME.yaml): run, export, show."""


@experiment.command("list")
def list_experiments() -> None:
    """The experiment files, each with the first sentence of its description (its opening
    comment)."""
    # A file `run` refuses (another encoding, too large) is listed all the same: `run` says why.
    for path in sorted(p for p in EXPERIMENTS.glob("*.yaml") if p.is_file()):
        with path.open(errors="replace") as handle:
            lines = handle.read(4096).splitlines()  # its opening comment, and more
        comment = " ".join(
            line.lstrip("#").strip()
            for line in lines[
                : next((i for i, line in enumerate(lines) if not line.startswith("#")), len(lines))
            ]
        )
        first = comment.split(". ")[0].rstrip(".")
        click.echo(f"{path.stem:22s}{textwrap.shorten(first, WIDTH - 22, placeholder=' …')}")


@experiment.command("run", context_settings={"ignore_unknown_options": True})
@click.argument("name")
@click.option(
    "--push",
    is_flag=True,
    help="Then send its outputs to the artifact store (`dvc "
    "push`: the DVC remote, `store` by default).",
)
@click.option(
    "--keep-code/--update-code",
    default=None,
    help="Run again after the code changed: finish the experiment with the code its working "
    "copy holds (its finished runs' code, with the params.yaml of its commit), or bring the copy up to this checkout, which runs "
    "its finished runs again. Without either, a change to the code the runs depend on is "
    "refused while the experiment has finished runs.",
)
@click.option(
    "--workspace-params",
    "from_workspace",
    is_flag=True,
    help="Apply experiments/NAME.yaml to this checkout's params.yaml as it is, uncommitted "
    "edits (or the params `dvc exp apply` brought) included, rather than to its commit's.",
)
@click.argument("sweep_args", nargs=-1, type=click.UNPROCESSED)
def run_experiment(
    name: str,
    push: bool,
    keep_code: bool | None,
    from_workspace: bool,
    sweep_args: tuple[str, ...],
) -> None:
    """Run experiments/NAME.yaml in its working copy and record it as the DVC experiment NAME.

    SWEEP_ARGS go to `ede-pipeline sweep` as they are (e.g. `--jobs 2`, `--executor ray`).
    The experiment's file is applied to the params.yaml of this checkout's commit: an edit of
    the workspace's params.yaml, or the params `dvc exp apply` left there, is said in one line
    and not used (see --workspace-params). Run it again after a kill or a failure: finished runs
    are kept, the others resume from their checkpoints. The copy's code is brought up to this
    checkout's each time, unless that would run finished runs again (see --keep-code).
    """
    from ede_pipeline.sweep.command import sweep

    if not Path("dvc.yaml").exists() or not (Path(".dvc")).is_dir():
        raise BadInput(f"run from the repository root (no dvc.yaml and .dvc/ in {Path.cwd()})")
    if from_workspace and keep_code:
        raise BadInput(
            "--workspace-params and --keep-code: the code the working copy keeps runs with the "
            "params.yaml of its own commit"
        )
    try:  # bad sweep options end here, before anything is made
        targets = sweep.make_context("sweep", list(sweep_args)).params["targets"]
    except click.UsageError as error:
        raise BadInput(f"sweep options: {error.format_message()}") from None
    if targets:  # `dvc repro` would run the other runs after the sweep all the same
        raise BadInput(
            f"experiment {name}: stages ({', '.join(targets)}) are not taken: an experiment runs "
            f"all of experiments/{name}.yaml's runs (its runs.seeds and runs.algos choose them)"
        )
    workspace = WORKSPACES / name
    # An unknown name, one git refuses, and bad params end here, before the lock.
    params, applied_to, ignored = _params(name, workspace, keep_code, from_workspace)
    with pipeline_repo():  # and a dvc.yaml or dvc.lock DVC cannot read
        pass
    with ExitStack() as held:
        try:  # one writer per experiment: a second run of it is refused before it changes anything
            held.enter_context(exclusive(workspace))
        except OutputBusy as error:
            raise BadInput(f"experiment {name}: {error}") from None
        if keep_code is None:
            check_code_keeps_runs(name, workspace)
        prepare_workspace(name, params, update_code=not keep_code, applied_to=applied_to)
        mend_records(name, workspace)
        if ignored:
            click.echo(f"experiment {name}: {ignored}", err=True)
        _run_held(name, workspace, push, keep_code, sweep_args)


def _params(
    name: str, workspace: Path, keep_code: bool | None, from_workspace: bool
) -> tuple[dict[str, Any], str, str | None]:
    """The experiment's params: its file applied to the ``params.yaml`` of this checkout's
    commit (with --keep-code, of its working copy's: the keys that copy's code knows), or to the
    workspace's with --workspace-params; to which, in words; and the line that says the
    workspace's ``params.yaml`` differs from its commit's and is not used (``None`` where it does
    not, or is used)."""
    try:  # an unknown name, one that is not a name, and a file that is not YAML: before git
        read_yaml(experiment_file(name))
    except ParamsError as error:
        raise BadInput(first_line(error)) from None
    if from_workspace:
        return experiment_params(name, workspace_params()), "this checkout's", None
    committed = committed_params()
    edited = uncommitted_params(committed)
    ignored = None
    if edited:
        listed = ", ".join(edited[:3]) + (f" and {len(edited) - 3} more" if len(edited) > 3 else "")
        ignored = (
            f"this checkout's params.yaml differs from its commit's ({listed}) and is not used: "
            "the experiment runs with the commit's (--workspace-params: with this one)"
        )
    if keep_code and (workspace / ".git").exists():
        committed = committed_params(workspace)
    try:
        return experiment_params(name, committed), "its commit's", ignored
    except BadInput as error:  # the workspace's edit may be what the checkout's code needs
        raise BadInput(f"{error.format_message()}{f' ({ignored})' if ignored else ''}") from None


def _run_held(
    name: str, workspace: Path, push: bool, keep_code: bool | None, sweep_args: tuple[str, ...]
) -> None:
    """:func:`run_experiment`'s work once its working copy is ready, its lock held."""
    kept = " with the code it started with" if keep_code else ""
    click.echo(f"experiment {name}: in {workspace}{kept}", err=True)
    if code := run_tool(workspace, "ede-pipeline", "sweep", *sweep_args):
        raise Failed(f"experiment {name}: the sweep failed (exit {code}); run it again to resume")
    # Nothing is left after the sweep, unless the copy's code predates the sweep of every stage
    # (--keep-code: its sweep may have run the runs alone); quiet, so that a check prints nothing.
    if keep_code and (code := run_tool(workspace, "dvc", "repro", "--quiet")):
        raise Failed(f"experiment {name}: dvc repro failed (exit {code}); run it again to resume")
    os.environ.update(git_identity())
    if code := run_tool(workspace, "dvc", "exp", "save", "--name", name, "--force"):
        raise Failed(f"experiment {name}: dvc exp save failed (exit {code})")
    if push and (code := run_tool(workspace, "dvc", "push")):
        raise Failed(
            f"experiment {name}: dvc push failed (exit {code}); it is recorded here, "
            "run it again to push"
        )
    click.echo(
        f"experiment {name}: recorded (`dvc exp show`, `ede-pipeline experiment show`); "
        f"export its runs with `ede-pipeline experiment export {name}`",
        err=True,
    )


experiment.add_command(export)
experiment.add_command(show)
