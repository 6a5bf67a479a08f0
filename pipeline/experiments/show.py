"""``ede-pipeline experiment show``: DVC's experiments, readably, a block each."""

from __future__ import annotations

import json
import subprocess
import sys
import textwrap
from collections.abc import Iterable
from typing import Any

import click
import yaml

from ede.config import (
    ALGO_LABELS,
)
from ede_pipeline import layout

WIDTH = 80
PARAMS_FILE = "params.yaml"


def flatten(tree: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    """Dotted keys to leaves; lists are leaves."""
    flat: dict[str, Any] = {}
    for key, value in tree.items():
        if isinstance(value, dict) and value:
            flat.update(flatten(value, f"{prefix}{key}."))
        else:
            flat[f"{prefix}{key}"] = value
    return flat


def _params(entry: dict[str, Any]) -> dict[str, Any]:
    files = (entry.get("data") or {}).get("params") or {}
    return flatten((files.get(PARAMS_FILE) or {}).get("data") or {})


def _headline(entry: dict[str, Any]) -> dict[str, dict[str, dict[str, Any]]]:
    """{task: {algo: {"final_return", "auc", "seeds"}}} from the report's metrics, if it ran."""
    files = (entry.get("data") or {}).get("metrics") or {}
    report = (files.get(layout.REPORT_METRICS.as_posix()) or {}).get("data") or {}
    return {
        task: per_algo
        for task, per_algo in report.items()
        if isinstance(per_algo, dict) and any(a in per_algo for a in ALGO_LABELS)
    }


def _number(value: Any, digits: int = 2) -> str:
    return f"{value:.{digits}f}" if isinstance(value, (int, float)) else "–"


def _changes(params: dict[str, Any], baseline: dict[str, Any]) -> list[str]:
    def shown(value: Any) -> str:  # as params.yaml spells it: null, true, false
        return (
            yaml.safe_dump(value, default_flow_style=True, width=1_000_000)
            .strip()
            .removesuffix("\n...")
        )

    return [
        f"{key}: {shown(baseline.get(key))} → {shown(value)}"
        for key, value in params.items()
        if value != baseline.get(key)
    ]


def _block(entry: dict[str, Any], base: str, baseline: dict[str, Any]) -> list[str]:
    rev = str(entry.get("rev"))[:7]
    lines = [f"{entry.get('name') or rev}  ({rev}, from {base})"]
    changed = _changes(_params(entry), baseline)
    lines += textwrap.wrap(
        f"changed: {'; '.join(changed) if changed else 'none'}",
        WIDTH,
        initial_indent="  ",
        subsequent_indent="    ",
        break_on_hyphens=False,
    )
    tasks = _headline(entry)
    if not tasks:
        lines.append("  no report yet" if entry.get("error") is None else "  failed")
        return lines
    algos = [a for a in ALGO_LABELS if any(a in per_algo for per_algo in tasks.values())]
    header = "".join(f"{ALGO_LABELS[a] + ' final':>15s}{'AUC':>8s}" for a in algos)
    lines.append(f"  {'task':24s}{header}{'seeds':>7s}")
    for task, per_algo in tasks.items():
        cells = "".join(
            f"{_number(per_algo.get(a, {}).get('final_return')):>15s}"
            f"{_number(per_algo.get(a, {}).get('auc')):>8s}"
            for a in algos
        )
        seeds = "/".join(_number(per_algo.get(a, {}).get("seeds"), 0) for a in algos)
        lines.append(f"  {task[-24:]:24s}{cells}{seeds:>7s}")
    lines += _across_tasks(entry)
    return lines


def _across_tasks(entry: dict[str, Any]) -> list[str]:
    """One line: P(EDE-TD3 > TD3) across tasks, over final returns and areas, with intervals."""
    files = (entry.get("data") or {}).get("metrics") or {}
    report = (files.get(layout.REPORT_METRICS.as_posix()) or {}).get("data") or {}
    across = report.get("across_tasks")
    if not isinstance(across, dict):
        return []
    cells = []
    for score, label in (("final_return", "final"), ("auc", "AUC")):
        p = (across.get(score) or {}).get("probability_of_improvement") or {}
        cells.append(
            f"{label} {_number(p.get('value'))} [{_number(p.get('low'))}, {_number(p.get('high'))}]"
        )
    count = _number(across.get("task_count"), 0)
    return [f"  P(EDE-TD3 > TD3), {count} task{'s' * (count != '1')}: {'; '.join(cells)}"]


def experiment_blocks(commits: Iterable[dict[str, Any]]) -> list[str]:
    """The printed lines for ``dvc exp show --json``: one block per experiment.

    An experiment's changes are against the commit it started from; the workspace is skipped.
    """
    lines: list[str] = []
    for commit in commits:
        if commit.get("rev") == "workspace":
            continue
        base, baseline = commit.get("name") or str(commit.get("rev"))[:7], _params(commit)
        for experiment in commit.get("experiments") or []:
            for entry in experiment.get("revs") or []:
                if lines:
                    lines.append("")
                lines += _block(entry, base, baseline)
    return lines


@click.command()
@click.option(
    "--num",
    "-n",
    type=int,
    default=1,
    show_default=True,
    help="The experiments of the last N commits (first parents); -1: all of them.",
)
def show(num: int) -> None:
    """The DVC experiments, in 80 columns: name, changed params, headline returns per task."""
    command = [sys.executable, "-m", "dvc", "exp", "show", "--json", "--num", str(num)]
    shown = subprocess.run(command, capture_output=True, text=True)
    if shown.returncode:
        raise click.ClickException(f"dvc exp show failed: {shown.stderr.strip()}")
    lines = experiment_blocks(json.loads(shown.stdout))
    click.echo(
        "\n".join(lines)
        if lines
        else "no experiments yet (`ede-pipeline experiment run NAME` or `make quick` makes one)"
    )
