"""``ede-pipeline``: one command per pipeline stage, each a thin layer over the ``ede`` library.

Every command validates the whole params file first; bad input ends with one line per problem on
stderr and exit code 2, before anything is written.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from pathlib import Path
from typing import Any

import click

from ede.config import Params, ParamsError, load_params

DEFAULT_PARAMS = Path("params.yaml")


class BadInput(click.ClickException):
    """Input the user must fix: printed as ``Error: <message>``, exit code 2, no traceback."""

    exit_code = 2

    def show(self, file: Any = None) -> None:
        for line in self.format_message().splitlines():
            click.echo(f"Error: {line}", err=True)


def params_option(command: Callable[..., Any]) -> Callable[..., Any]:
    """Add ``--params FILE`` to a command and hand it the validated :class:`Params`."""

    @click.option(
        "--params",
        "params_path",
        type=click.Path(dir_okay=False, path_type=Path),
        default=DEFAULT_PARAMS,
        show_default=True,
        help="The parameters file.",
    )
    @functools.wraps(command)
    def wrapper(params_path: Path, **kwargs: Any) -> Any:
        return command(params=read_params(params_path), **kwargs)

    return wrapper


def read_params(path: Path) -> Params:
    try:
        return load_params(path)
    except ParamsError as error:
        raise BadInput(str(error)) from None


@click.group(context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(package_name="ede")
def main() -> None:
    """The EDE pipeline: collect → pretrain → train → report (see README.md)."""


@main.command()
@params_option
def validate(params: Params) -> None:
    """Check a params file; print one line per problem, exit 2 if there is any."""
    families = ", ".join(params.families)
    runs = len(params.runs.tasks) * len(params.runs.algos) * len(params.runs.seeds)
    click.echo(f"ok: {len(params.families)} families ({families}), {runs} runs")


@main.command()
def envs() -> None:
    """List every task this package provides: family, spaces and episode length."""
    from ede.envs import describe_tasks

    rows = [("task", "family", "role", "observation", "action", "steps")]
    rows += [
        (t.id, t.family, t.role, str(t.observation_shape), t.action_space, str(t.max_episode_steps))
        for t in describe_tasks()
    ]
    widths = [max(len(row[i]) for row in rows) for i in range(len(rows[0]))]
    for row in rows:
        click.echo("  ".join(cell.ljust(width) for cell, width in zip(row, widths)).rstrip())
