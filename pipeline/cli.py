"""``ede-pipeline``: one command per pipeline stage, each a thin layer over the ``ede`` library.

Every command validates the whole params file first; bad input ends with one line per problem on
stderr and exit code 2, before anything is written.
"""

from __future__ import annotations

import importlib

import click

from ede.config import Params
from ede_pipeline.common import check_mujoco_gl, follow_parent, params_option

# The stages' commands, each imported only when it runs: DVC starts a process per stage, and the
# stages' own dependencies (torch, matplotlib, rliable, DVC) cost seconds each to import.
STAGES = {
    "task-code": "ede_pipeline.task_code:task_code",
    "collect": "ede_pipeline.collect:collect",
    "task-inputs": "ede_pipeline.task_inputs:task_inputs",
    "inspect": "ede_pipeline.collect:inspect_rollouts",
    "pretrain": "ede_pipeline.pretrain:pretrain",
    "train": "ede_pipeline.train:train",
    "report": "ede_pipeline.report.command:report",
    "results": "ede_pipeline.results.command:results",
    "render": "ede_pipeline.render:render",
    "sweep": "ede_pipeline.sweep.command:sweep",
    "experiment": "ede_pipeline.experiments.command:experiment",
}


class _Pipeline(click.Group):
    """A click group whose stage commands (:data:`STAGES`) load on first use."""

    def list_commands(self, ctx: click.Context) -> list[str]:
        return sorted([*super().list_commands(ctx), *STAGES])

    def get_command(self, ctx: click.Context, name: str) -> click.Command | None:
        if name not in STAGES:
            return super().get_command(ctx, name)
        module, _, attribute = STAGES[name].partition(":")
        command: click.Command = getattr(importlib.import_module(module), attribute)
        return command


@click.group(cls=_Pipeline, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(package_name="ede")
def main() -> None:
    """The EDE pipeline: collect → pretrain → train → report (see README.md)."""
    follow_parent()
    check_mujoco_gl()


@main.command()
@params_option
def validate(params: Params) -> None:
    """Check a params file; print one line per problem, exit 2 if there is any."""
    families = ", ".join(params.families)
    runs = params.runs.count
    click.echo(f"ok: {len(params.families)} families ({families}), {runs} runs")


@main.command()
@params_option
def envs(params: Params) -> None:
    """List every task this package provides and every task of the params' families: its
    family (from the params), spaces and episode length."""
    from ede.tasks import describe_tasks

    rows = [("task", "family", "role", "observation", "action", "steps")]
    rows += [
        (t.id, t.family, t.role, str(t.observation_shape), t.action_space, str(t.max_episode_steps))
        for t in describe_tasks(params.families)
    ]
    widths = [max(len(row[i]) for row in rows) for i in range(len(rows[0]))]
    for row in rows:
        click.echo(
            "  ".join(cell.ljust(width) for cell, width in zip(row, widths, strict=True)).rstrip()
        )
