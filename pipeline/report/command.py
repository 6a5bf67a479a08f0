"""The ``ede-pipeline report`` command: its options, the page built (:func:`build`) and its
files written, each whole or not at all.

Its inputs come from its command line, as ``dvc.yaml`` writes them: the folder of the runs, and per
family the embedding and the rollouts store (the families of Figures 6 and 7 from the params).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import click
import torch

from ede.analysis.probes import effect_space, exploration
from ede.config import Params
from ede.io.atomic import write_atomically, write_json
from ede_pipeline import layout
from ede_pipeline.common import holding, params_option
from ede_pipeline.report import numbers, sections
from ede_pipeline.report.inputs import Inputs, read_inputs, read_runs
from ede_pipeline.report.page import Page


def build(
    params: Params, params_text: str, inputs: Inputs
) -> tuple[Page, dict[str, Any], dict[str, str], list[str]]:
    """The page, the DVC metrics, the curve CSVs of the report, and one line per finished run
    left out of it (and why): the runs read (:mod:`.inputs`), their numbers computed
    (:mod:`.numbers`) and drawn (:mod:`.sections`), section by section."""
    page = Page()
    sections.intro(page, params)
    runs = read_runs(params, inputs)
    families = numbers.families(params, runs)
    metrics = numbers.task_metrics(families)
    curve_files = {
        task: numbers.curve_csv(task, params.runs.algos, runs.curves, params)
        for family in families
        for task in family.tasks
    }
    sections.learning_curves(page, params, families)
    found = numbers.across(params, runs.curves)
    if found is not None:
        metrics["across_tasks"] = numbers.across_metrics(found)
    sections.across_tasks(page, found, params.report)
    figure_6 = numbers.pictured(params, inputs, params.report.effect_space_family, effect_space)
    if figure_6 is not None:
        metrics["effect_space_affine_r2"] = figure_6[1].r_squared
    sections.effect_space(page, figure_6)
    figure_7 = numbers.pictured(params, inputs, params.report.exploration_family, exploration)
    if figure_7 is not None:
        metrics["coverage"] = {"raw": figure_7[1].raw_coverage, "ede": figure_7[1].ede_coverage}
    sections.exploration(page, figure_7)
    clips = numbers.clips(params, inputs, runs.curves) if params.report.videos else None
    sections.videos(page, clips)
    sections.missing(page, runs, params.runs.count)
    metrics["missing_runs"] = len(runs.absent)
    metrics["excluded_runs"] = len(runs.excluded)
    sections.provenance(page, params, params_text, inputs, runs.software)
    return page, metrics, curve_files, runs.excluded


@click.command()
@click.option(
    "--runs",
    type=click.Path(path_type=Path),
    default=layout.RUNS,
    show_default=True,
    help="The folder of the runs (<task>/<algo>/seed<N>/); the params say which to read.",
)
@click.option(
    "--families",
    type=click.Path(file_okay=False, path_type=Path),
    default=layout.FAMILIES,
    show_default=True,
    help="The folder of every family's outputs (<family>/embedding, "
    "<family>/rollouts.zarr): the provenance lists each family found there, Figures 6 "
    "and 7 draw report.effect_space_family's and report.exploration_family's.",
)
@click.option(
    "--embedding",
    "embeddings",
    metavar="FAMILY=DIR",
    multiple=True,
    help="A family's embedding folder (encoder/ and decoder/), once per family, "
    "instead of those in --families.",
)
@click.option(
    "--rollouts",
    metavar="FAMILY=STORE",
    multiple=True,
    help="A family's rollouts store, once per family, instead of those in --families  "
    "[default: <families>/<family>/rollouts.zarr for each family of the embeddings]",
)
@click.option(
    "--out",
    type=click.Path(path_type=Path),
    default=layout.REPORT,
    show_default=True,
    help="Report directory: index.html and its PNG figures.",
)
@click.option(
    "--metrics",
    type=click.Path(path_type=Path),
    default=layout.REPORT_METRICS,
    show_default=True,
    help="Summary metrics (DVC metrics): mean final return and AUC per task and algorithm.",
)
@click.option(
    "--curves",
    type=click.Path(path_type=Path),
    default=layout.REPORT_CURVES,
    show_default=True,
    help="Mean learning curve per task, one CSV each (DVC plots).",
)
@params_option
def report(
    params: Params,
    runs: Path,
    families: Path,
    embeddings: tuple[str, ...],
    rollouts: tuple[str, ...],
    out: Path,
    metrics: Path,
    curves: Path,
) -> None:
    """Stage 5: learning curves, tables, the EDE pictures and provenance in one HTML page."""
    torch.set_num_threads(params.embedding.threads)  # it only encodes and decodes small batches
    given = (Path(path) for pair in (*embeddings, *rollouts) if (path := pair.partition("=")[2]))
    with holding(
        (out, "report"),
        files=((metrics, "report metrics"),),
        dirs=((curves, "report curves"),),
        inputs=(runs, families, *given),
    ):
        _report(
            params, read_inputs(params, runs, embeddings, rollouts, families), out, metrics, curves
        )


def _report(params: Params, inputs: Inputs, out: Path, metrics: Path, curves: Path) -> None:
    params_path = Path(click.get_current_context().params.get("params_path") or "params.yaml")
    params_text = params_path.read_text() if params_path.is_file() else ""
    page, summary, curve_files, excluded = build(params, params_text, inputs)
    for line in excluded:
        click.echo(f"left out: {line}", err=True)

    def write_page(tmp: Path) -> None:
        (tmp / "index.html").write_text(page.html("EDE report"))
        for name, data in page.images.items():
            (tmp / f"{name}.png").write_bytes(data)
        for name, data in page.videos.items():
            (tmp / f"{name}.mp4").write_bytes(data)

    def write_curves(tmp: Path) -> None:
        for task, text in curve_files.items():
            (tmp / f"{task.replace('/', '_')}.csv").write_text(text)

    write_atomically(out, write_page, kind="report")  # the largest first: a full disk stops it
    write_atomically(curves, write_curves, kind="report curves")
    write_json(metrics, summary)
    click.echo(
        f"{out / 'index.html'}: {summary['missing_runs']} of {params.runs.count} runs "
        f"missing, {summary['excluded_runs']} left out"
    )
