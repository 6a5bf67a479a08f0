"""Stage 5, ``ede-pipeline report``: one self-contained HTML page of every result.

Its inputs come from its command line, as ``dvc.yaml`` writes them: the folder of the runs, and per
family the embedding and the rollouts store (the families of Figures 6 and 7 from the params).
"""

from __future__ import annotations

import base64
import hashlib
import html
import io
import json
import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import click
import numpy as np
import torch
from matplotlib.figure import Figure

from ede.analysis import figures
from ede.analysis.probes import effect_space, exploration, random_policy_return
from ede.analysis.results import RANDOM_EPISODES, SCORES, Arm, across_tasks, arm, fresh
from ede.analysis.stats import Band, curve_band
from ede.config import ALGO_LABELS, Algo, Params
from ede.io.atomic import write_atomically, write_json
from ede.io.provenance import describe_software, software_versions
from ede.method.embedding import ActionEmbedding
from ede.run.artifacts import ArtifactError, load_action_embedding
from ede.run.runs import Curve, RunRejected, RunSpec, read_run
from ede_pipeline import layout
from ede_pipeline.common import BadInput, holding, params_option
from ede_pipeline.render import fps_of, side_by_side, video_bytes

STYLE = """
body { font-family: system-ui, sans-serif; max-width: 1100px; margin: 2em auto; color: #222; }
table { border-collapse: collapse; margin: 1em 0; font-size: 0.9em; }
th, td { border: 1px solid #ccc; padding: 0.3em 0.6em; text-align: right; }
th:first-child, td:first-child { text-align: left; }
img { max-width: 100%; }
.missing { color: #b00; }
code { font-size: 0.85em; }
"""


def _png(figure: Figure) -> bytes:
    """The figure's PNG."""
    buffer = io.BytesIO()
    figure.savefig(buffer, format="png", dpi=110)
    return buffer.getvalue()


def _interval(interval: Any) -> str:
    if interval.n == 0:
        return '<span class="missing">missing</span>'
    return str(interval)


def _steps(interval: Any) -> str:
    return _interval(interval) if interval.n == 0 else interval.steps()


class Page:
    """Sections of HTML and the PNG and MP4 files beside them."""

    def __init__(self) -> None:
        self.parts: list[str] = []
        self.images: dict[str, bytes] = {}
        self.videos: dict[str, bytes] = {}

    def add(self, text: str) -> None:
        self.parts.append(text)

    def figure(self, name: str, figure: Figure, alt: str) -> None:
        data = _png(figure)
        self.images[name] = data
        encoded = base64.b64encode(data).decode()
        self.add(
            f'<img src="data:image/png;base64,{encoded}" alt="{html.escape(alt)}" id="{name}">'
        )

    def video(self, name: str, data: bytes, alt: str) -> None:
        self.videos[name] = data
        encoded = base64.b64encode(data).decode()
        self.add(
            f'<video controls loop muted autoplay playsinline id="{name}" '
            f'title="{html.escape(alt)}" src="data:video/mp4;base64,{encoded}"></video>'
        )

    def html(self, title: str) -> str:
        return (
            f"<!DOCTYPE html>\n<html><head><meta charset='utf-8'><title>{title}</title>"
            f"<style>{STYLE}</style></head><body>\n" + "\n".join(self.parts) + "\n</body></html>\n"
        )


def _table(rows: list[tuple[str, Arm, list[int]]], thresholds: list[float]) -> str:
    """Per algorithm (its statistics, its missing seeds): final return, area and steps to each
    threshold with their intervals, and its seeds."""
    reach = "".join(f"<th>steps to {t:g}</th>" for t in thresholds)
    head = (
        f"<tr><th>algorithm</th><th>final return</th><th>area under curve</th>{reach}"
        "<th>seeds</th></tr>"
    )
    body = []
    for algo, row, absent in rows:
        missing = (
            f' <span class="missing">(missing: {", ".join(map(str, absent))})</span>'
            if absent
            else ""
        )
        steps = "".join(f"<td>{_steps(row.to_thresholds[t])}</td>" for t in thresholds)
        body.append(
            f"<tr><td>{ALGO_LABELS[algo]}</td><td>{_interval(row.final)}</td>"
            f"<td>{_interval(row.area)}</td>{steps}<td>{len(row.seeds)}{missing}</td></tr>"
        )
    return f"<table>{head}{''.join(body)}</table>"


FIGURE_FAMILIES = {"effect_space_family": "Figure 6", "exploration_family": "Figure 7"}


@dataclass(frozen=True)
class Inputs:
    """What the report reads, as its command line names it, checked."""

    runs: Path  # the folder of every run: <task>/<algo>/seed<N>/
    embeddings: dict[str, Path]  # per family, the folder of its encoder and decoder
    loaded: dict[str, ActionEmbedding]
    rollouts: dict[str, dict[str, Any]]  # per family, the store's attributes
    embedding_ids: dict[str, str]  # per family, its decoder's identity, which EDE-TD3 runs record


def _by_family(
    option: str,
    values: tuple[str, ...],
    params: Params,
    default: Callable[[str], Path],
    default_families: list[str],
) -> dict[str, Path]:
    """The ``FAMILY=PATH`` values of a repeatable option; none given, ``default_families`` at
    their ``default`` paths."""
    if not values:
        return {family: default(family) for family in default_families}
    found: dict[str, Path] = {}
    for value in values:
        family, equals, path = value.partition("=")
        if not (family and equals and path):
            raise BadInput(
                f"{option} {value!r}: expected FAMILY=PATH, e.g. {option} point={default('point')}"
            )
        if family not in params.families:
            raise BadInput(
                f"{option} {value!r}: unknown family {family!r}; params.yaml's families "
                f"are {', '.join(params.families)}"
            )
        if family in found:
            raise BadInput(f"{option} {value!r}: the {family} family is given twice")
        found[family] = Path(path)
    return found


def _store_attributes(store: Path) -> dict[str, Any]:
    """A Zarr v3 store's attributes, read from its header alone; empty if there is none."""
    try:
        return json.loads((store / "zarr.json").read_text()).get("attributes", {})
    except (OSError, ValueError, AttributeError):
        return {}


def read_inputs(
    params: Params,
    runs: Path,
    embeddings: tuple[str, ...],
    rollouts: tuple[str, ...],
    families: Path = layout.FAMILIES,
) -> Inputs:
    """Check every input before anything is written.

    Without ``--embedding``, every family of the params whose embedding is in ``families`` (and
    the pictured ones, which must be); without ``--rollouts``, those families' stores there.

    Raises:
        BadInput: naming the option (or params key) and what it expects.
    """
    if not runs.is_dir():
        raise BadInput(
            f"--runs {runs}: no such directory; expected the folder of the runs "
            "(<task>/<algo>/seed<N>/, written by `ede-pipeline train`)"
        )
    figures = {key: getattr(params.report, key) for key in FIGURE_FAMILIES}
    pictured = list(dict.fromkeys(family for family in figures.values() if family is not None))
    found = [
        family
        for family in params.families
        if family in pictured or layout.embedding(family, families).is_dir()
    ]
    folders = _by_family(
        "--embedding", embeddings, params, lambda family: layout.embedding(family, families), found
    )
    stores = _by_family(
        "--rollouts",
        rollouts,
        params,
        lambda family: layout.rollouts(family, families),
        list(folders),
    )
    loaded: dict[str, ActionEmbedding] = {}
    embedding_ids: dict[str, str] = {}
    trained_on: dict[
        str, str
    ] = {}  # per family, the rollouts' fingerprint its embedding learned from
    for family, folder in folders.items():
        given = f"--embedding {family}={folder}"
        if not folder.is_dir():
            raise BadInput(
                f"{given}: no such directory; expected the {family} family's embedding "
                f"folder ({layout.ENCODER}/ and {layout.DECODER}/, from `ede-pipeline "
                "pretrain`)"
            )
        try:
            meta, loaded[family] = load_action_embedding(
                folder / layout.ENCODER, folder / layout.DECODER
            )
        except ArtifactError as error:
            raise BadInput(f"{given}: {error}") from None
        if meta.family != family:
            raise BadInput(f"{given}: the embedding of family {meta.family}, not {family}")
        trained_on[family] = meta.data_fingerprint
        embedding_ids[family] = meta.identity
    for key, family in figures.items():
        if family is not None and family not in folders:
            raise BadInput(
                f"report.{key}: {family}, but no --embedding {family}=DIR is given; "
                f"{FIGURE_FAMILIES[key]} needs that family's embedding"
            )
    attributes: dict[str, dict[str, Any]] = {}
    for family, store in stores.items():
        given = f"--rollouts {family}={store}"
        attrs = _store_attributes(store)
        if "fingerprint" not in attrs:
            raise BadInput(
                f"{given}: no rollouts store here; expected the Zarr store that "
                "`ede-pipeline collect` writes"
            )
        if trained_on.get(family, attrs["fingerprint"]) != attrs["fingerprint"]:
            raise BadInput(
                f"{given}: rollouts {attrs['fingerprint'][:12]}, but the {family} "
                f"embedding was trained on {trained_on[family][:12]}"
            )
        attributes[family] = attrs
    return Inputs(runs, folders, loaded, attributes, embedding_ids)


def build(
    params: Params, params_text: str, inputs: Inputs
) -> tuple[Page, dict[str, Any], dict[str, str], list[str]]:
    """The page, the DVC metrics, the curve CSVs of the report, and one line per finished run
    left out of it (and why)."""
    config = params.report
    page = Page()
    page.add("<h1>Effect-Dependent Embeddings: EDE-TD3 against TD3</h1>")
    page.add(
        f"<p>{params.runs.count} runs expected: {len(params.runs.all_tasks)} tasks × "
        f"{len(params.runs.algos)} algorithms × {len(params.runs.seeds)} seeds. Intervals are "
        f"{100 * config.confidence:.0f}% percentile bootstrap intervals of the mean over seeds "
        f"({config.bootstrap_samples} resamples).</p>"
    )
    metrics: dict[str, Any] = {}
    curve_files: dict[str, str] = {}
    missing_runs: list[str] = []
    excluded: list[str] = []  # one line per finished run that cannot be averaged, and why
    software: list[dict[str, Any] | None] = []  # of each run averaged
    all_curves: dict[tuple[str, str], list[Curve]] = {}  # every task's, for the aggregates

    page.add("<h2>Learning curves</h2>")
    for family, tasks in params.runs.by_family().items():
        curves: dict[tuple[str, str], list[Curve]] = {}
        diagnostics: dict[tuple[str, str], list[dict[str, np.ndarray]]] = {}
        rows: dict[str, list[tuple[str, Arm, list[int]]]] = {}
        bands: dict[tuple[str, str], Band] = {}
        for task in tasks:
            for algo in params.runs.algos:
                found, missing = [], []
                for seed in params.runs.seeds:
                    run = layout.run(task, algo, seed, inputs.runs)
                    try:
                        record = read_run(run, _expected(params, inputs, task, algo, seed))
                    except RunRejected as error:
                        record = None
                        excluded.append(str(error))
                    else:
                        if record is None:
                            missing_runs.append(str(run))
                    if record is None:
                        missing.append(seed)
                        continue
                    found.append(record.curve)
                    software.append(record.software)
                    if record.diagnostics is not None:
                        diagnostics.setdefault((task, algo), []).append(record.diagnostics)
                curves[(task, algo)] = found
                all_curves[(task, algo)] = found
                row = arm(found, config.thresholds.get(task, []), _width(params, task), config)
                rows.setdefault(task, []).append((algo, row, missing))
                if row.band is not None:
                    bands[(task, algo)] = row.band
                metrics.setdefault(task, {})[algo] = {
                    "final_return": None if row.final.n == 0 else row.final.mean,
                    "auc": None if row.area.n == 0 else row.area.mean,
                    "seeds": row.final.n,
                }
            curve_files[task] = _curve_csv(task, params.runs.algos, curves, params)
        source = params.families[family].source
        page.add(f"<h3>{family} family (embedding learned on {source})</h3>")
        page.figure(
            f"curves-{family}",
            figures.learning_curves(
                family,
                tasks,
                bands,
                {key: len(runs) for key, runs in curves.items()},
                config.confidence,
                config.bin_steps or {task: _width(params, task) for task in tasks},
            ),
            f"learning curves of the {family} family",
        )
        if diagnostics:
            page.figure(
                f"diagnostics-{family}",
                figures.diagnostics(family, tasks, diagnostics),
                f"training diagnostics of the {family} family",
            )
        for task in tasks:
            thresholds = config.thresholds.get(task, [])
            note = f" (thresholds {', '.join(f'{t:g}' for t in thresholds)})" if thresholds else ""
            page.add(f"<h4>{task}{note}</h4>" + _table(rows[task], thresholds))
            page.add(_fell_back(rows[task]))

    _across_tasks(page, metrics, all_curves, params)

    page.add("<h2>The EDE space against the effect space (Figure 6)</h2>")
    pictured = config.effect_space_family
    if pictured is None:
        page.add("<p>Not drawn: <code>report.effect_space_family</code> is null.</p>")
    else:
        embedding, task = inputs.loaded[pictured], params.families[pictured].source
        space = effect_space(embedding, fresh(config), env_id=task)
        metrics["effect_space_affine_r2"] = space.r_squared
        page.add(
            f"<p>Effects s[t+{embedding.k}] − s[t] of {len(space.effects)} random "
            f"{embedding.k}-step sequences on {task} (left) and their codes E(a) under the "
            f"{pictured} family's embedding (right), coloured by effect. Best affine map "
            f"effect → code: <b>R² = {space.r_squared:.4f}</b>.</p>"
        )
        page.figure("effect-space", figures.effect_space(space), "effect space beside EDE space")

    page.add("<h2>Exploration (Figure 7)</h2>")
    drawn = config.exploration_family
    if drawn is None:
        page.add("<p>Not drawn: <code>report.exploration_family</code> is null.</p>")
    else:
        embedding, task = inputs.loaded[drawn], params.families[drawn].source
        explored = exploration(embedding, fresh(config), env_id=task)
        metrics["coverage"] = {"raw": explored.raw_coverage, "ede": explored.ede_coverage}
        page.add(
            f"<p>Positions over ten episodes on {task}: uniform random actions "
            f"every step cover <b>{100 * explored.raw_coverage:.1f}%</b> of the arena (a 20×20 "
            f"grid); uniform random EDE actions of the {drawn} family's embedding, chosen "
            f"every {embedding.k} steps, cover <b>{100 * explored.ede_coverage:.1f}%</b>.</p>"
        )
        page.figure(
            "exploration", figures.exploration(explored), "exploration with raw and EDE actions"
        )

    _videos(page, params, inputs, all_curves)

    page.add("<h2>Missing and excluded runs</h2>")
    if missing_runs:
        page.add(
            f'<p class="missing">{len(missing_runs)} of {params.runs.count} runs have no '
            "results:</p><ul>"
            + "".join(f"<li><code>{html.escape(r)}</code></li>" for r in missing_runs)
            + "</ul>"
        )
    if excluded:
        page.add(
            f'<p class="missing">{len(excluded)} finished runs are left out of the figures '
            "and tables:</p><ul>"
            + "".join(f"<li>{html.escape(r)}</li>" for r in excluded)
            + "</ul>"
        )
    if not missing_runs and not excluded:
        page.add("<p>None: every run the params name is here.</p>")
    metrics["missing_runs"] = len(missing_runs)
    metrics["excluded_runs"] = len(excluded)

    page.add("<h2>Provenance</h2>" + _provenance(params, params_text, inputs, software))
    return page, metrics, curve_files, excluded


def median_seed(ours: list[Curve], theirs: list[Curve]) -> int | None:
    """The seed both algorithms finished whose EDE-TD3 final return is the median (the lower of
    the two middle ones where their count is even); None where they share no seed."""
    shared = {c.seed for c in theirs}
    finals = sorted((float(c.returns[-1]), c.seed) for c in ours if c.seed in shared)
    return finals[(len(finals) - 1) // 2][1] if finals else None


def _videos(
    page: Page, params: Params, inputs: Inputs, curves: dict[tuple[str, str], list[Curve]]
) -> None:
    """Per task, TD3 beside EDE-TD3 of its median seed, one episode each from the same start."""
    page.add("<h2>The agents: TD3 beside EDE-TD3</h2>")
    if not params.report.videos:
        page.add("<p>Not drawn: <code>report.videos</code> is false.</p>")
        return
    page.add(
        "<p>Per task, one evaluation episode of each algorithm's final policy, the seed whose "
        "EDE-TD3 final return is the median; an orange bar marks each step where EDE-TD3 "
        "chooses a code (<code>ede-pipeline render</code>, docs/pipeline.md).</p>"
    )
    os.environ.setdefault("MUJOCO_GL", "egl")  # read as the first environment renders
    for task in params.runs.all_tasks:
        seed = median_seed(curves.get((task, "ede-td3"), []), curves.get((task, "td3"), []))
        if seed is None:
            page.add(f"<p>{html.escape(task)}: no clip, no seed finished by both.</p>")
            continue
        runs = [layout.run(task, algo, seed, inputs.runs) for algo in ("td3", "ede-td3")]
        family = params.runs.tasks[task]
        embedding = (
            (inputs.loaded[family], inputs.embedding_ids[family])
            if family in inputs.loaded
            else None
        )
        name = f"clip-{task.replace('/', '_')}"
        try:
            frames, _ = side_by_side(runs, embedding)
            data = video_bytes(frames, fps_of(task), Path(f"{name}.mp4"))
        except click.ClickException as error:  # no policy, no GL: the page says so
            page.add(f"<p>{html.escape(task)}: no clip ({html.escape(error.format_message())})</p>")
            continue
        page.add(f"<h4>{html.escape(task)}, seed {seed}</h4>")
        page.video(name, data, f"{task}: TD3 beside EDE-TD3, seed {seed}")


def _expected(params: Params, inputs: Inputs, task: str, algo: Algo, seed: int) -> dict[str, Any]:
    """What a run's ``run.json`` must say: the run the params name, with the family's embedding
    where the report was given it."""
    embedding = inputs.embedding_ids.get(params.runs.tasks[task]) if algo == "ede-td3" else ""
    expected = RunSpec(
        task, algo, seed, params.runs.budgets[task], params.td3, params.ede_td3, embedding or ""
    ).identity()
    if embedding is None:
        del expected["embedding"]  # not given to the report: nothing to check it against
    return expected


def _across_tasks(
    page: Page, metrics: dict[str, Any], curves: dict[tuple[str, str], list[Curve]], params: Params
) -> None:
    """The claim across tasks, as rliable states it: probability of improvement and IQM of
    normalised scores with stratified bootstrap intervals, and a performance profile."""
    config = params.report
    page.add("<h2>Across tasks</h2>")
    lows = {
        task: random_policy_return(task, RANDOM_EPISODES, config.seed)
        for task in params.runs.all_tasks
        if curves.get((task, "td3")) and curves.get((task, "ede-td3"))
    }
    found = across_tasks(curves, lows, config.confidence, config.bootstrap_samples, config.seed)
    if found is None:
        page.add(
            "<p>No task has finished runs of both algorithms yet, or none has one whose best "
            "evaluation is above a random policy's return.</p>"
        )
        return
    rows = []
    summary: dict[str, Any] = {
        "tasks": found.tasks,
        "task_count": len(found.tasks),
        "runs_per_task": found.runs,
    }  # DVC's metrics keep numbers only
    for score, label in SCORES.items():
        a = found.aggregates[score]
        rows.append(
            f"<tr><td>{label}</td><td>{_interval(a['probability_of_improvement'])}</td>"
            f"<td>{_interval(a['iqm_ours'])}</td><td>{_interval(a['iqm_theirs'])}</td></tr>"
        )
        summary[score] = {
            "probability_of_improvement": _as_json(a["probability_of_improvement"]),
            "iqm": {"ede-td3": _as_json(a["iqm_ours"]), "td3": _as_json(a["iqm_theirs"])},
        }
    metrics["across_tasks"] = summary
    page.add(
        f"<p>{html.escape(found.describe(config.confidence, config.bootstrap_samples))}</p>"
        "<table><tr><th>score</th><th>P(EDE-TD3 &gt; TD3)</th><th>IQM, EDE-TD3</th>"
        "<th>IQM, TD3</th></tr>" + "".join(rows) + "</table>"
    )
    page.figure(
        "performance-profile",
        figures.performance_profile(found.profile, len(found.tasks), found.runs),
        "performance profile across tasks",
    )


def _as_json(interval: Any) -> dict[str, float]:
    return {"value": interval.mean, "low": interval.low, "high": interval.high}


def _width(params: Params, task: str) -> float:
    """The bins of a task's bands and divergence: ``report.bin_steps``, else a twentieth of its
    budget."""
    return params.report.bin_steps or params.runs.budgets[task] / 20


def _fell_back(rows: list[tuple[str, Arm, list[int]]]) -> str:
    """The seeds whose returns fell and stayed below their best (:func:`ede.analysis.stats.divergence`,
    on the figure's bins): flagged, not hidden."""
    flagged = [
        f"{ALGO_LABELS[algo]} seed {seed} (best {verdict.best:.4g} "
        f"at step {verdict.best_step:,.0f}, last quarter {verdict.tail:.4g})"
        for algo, row, _ in rows
        for seed, verdict in zip(row.seeds, row.divergence, strict=True)
        if verdict is not None and verdict.diverged
    ]
    if not flagged:
        return ""
    return (
        '<p class="missing">Fell and stayed below their best (diverged, in the paper\'s '
        f"sense): {html.escape('; '.join(flagged))}.</p>"
    )


def _curve_csv(
    task: str, algos: Sequence[str], curves: dict[tuple[str, str], list[Curve]], params: Params
) -> str:
    """Mean curve per algorithm on the union of steps, for ``dvc plots``."""
    config = params.report
    series = {
        algo: curve_band(
            curves[(task, algo)], config.confidence, config.bootstrap_samples, fresh(config)
        )
        for algo in algos
        if curves[(task, algo)]
    }
    steps = sorted({float(s) for band in series.values() for s in band[0]})
    lines = [",".join(["step", *series])]
    for step in steps:
        cells = []
        for band in series.values():
            where = np.flatnonzero(band[0] == step)
            cells.append(f"{band[1][where[0]]:.6g}" if where.size else "")
        lines.append(",".join([f"{step:g}", *cells]))
    return "\n".join(lines) + "\n"


def _row(what: str, sha256: str, software: dict[str, str] | None) -> str:
    return (
        f"<tr><td>{html.escape(what)}</td><td><code>{sha256}</code></td>"
        f"<td>{html.escape(describe_software(software))}</td></tr>"
    )


def _provenance(
    params: Params, params_text: str, inputs: Inputs, runs_software: list[dict[str, Any] | None]
) -> str:
    """The SHA-256 of every input beside the versions of the software that made it, and the
    software of the runs averaged."""
    rows = [
        _row(
            "params.yaml; this report",
            hashlib.sha256(params_text.encode()).hexdigest(),
            software_versions(),
        )
    ]
    for family in params.families:
        if family in inputs.rollouts:
            attrs = inputs.rollouts[family]
            rows.append(_row(f"{family} rollouts", attrs["fingerprint"], attrs.get("software")))
        if family in inputs.embeddings:
            for name in (layout.ENCODER, layout.DECODER):
                data = json.loads((inputs.embeddings[family] / name / "meta.json").read_text())
                rows.append(
                    _row(f"{family} {name} weights", data["weights_sha256"], data.get("software"))
                )
    runs: dict[str, int] = {}  # the runs' software, described, and how many runs each
    for made_by in runs_software:
        described = describe_software(made_by)
        runs[described] = runs.get(described, 0) + 1
    rows += [
        f"<tr><td>{count} training run{'s' * (count > 1)}</td><td></td>"
        f"<td>{html.escape(software)}</td></tr>"
        for software, count in runs.items()
    ]
    params_html = html.escape(json.dumps(params.model_dump(mode="json"), indent=1))
    return (
        "<table><tr><th>input</th><th>SHA-256</th><th>software</th></tr>"
        + "".join(rows)
        + "</table>"
        f"<details><summary>the params</summary><pre>{params_html}</pre></details>"
    )


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
