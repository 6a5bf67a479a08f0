"""The report's sections in HTML, each drawn onto the page (:class:`.page.Page`) from the numbers
(:mod:`.numbers`) and the runs read (:mod:`.inputs`), in the page's order."""

from __future__ import annotations

import hashlib
import html
import json
from typing import Any

from ede.analysis import figures
from ede.analysis.probes import EffectSpace, Exploration
from ede.analysis.results import SCORES, AcrossTasks, Comparison
from ede.config import ALGO_LABELS, Params, ReportConfig
from ede.io.provenance import describe_software, software_versions
from ede_pipeline import layout
from ede_pipeline.report.inputs import Inputs, Runs
from ede_pipeline.report.numbers import Clip, Family, Pictured, Row, clip_name, width
from ede_pipeline.report.page import Page, interval, steps


def intro(page: Page, params: Params) -> None:
    config = params.report
    page.add("<h1>Effect-Dependent Embeddings: EDE-TD3 against TD3</h1>")
    page.add(
        f"<p>{params.runs.count} runs expected: {len(params.runs.all_tasks)} tasks × "
        f"{len(params.runs.algos)} algorithms × {len(params.runs.seeds)} seeds. Intervals are "
        f"{100 * config.confidence:.0f}% percentile bootstrap intervals of the mean over seeds "
        f"({config.bootstrap_samples} resamples).</p>"
    )


def learning_curves(page: Page, params: Params, families: list[Family]) -> None:
    """Per family, its learning curves' figure, its diagnostics' where its runs kept them, and
    per task its table, EDE-TD3 against each other algorithm and each other algorithm in the EDE
    space against its raw counterpart (where the params name algorithms beyond the paper's pair)
    and the seeds that fell back."""
    config = params.report
    page.add("<h2>Learning curves</h2>")
    for family in families:
        source = params.families[family.name].source
        page.add(f"<h3>{family.name} family (embedding learned on {source})</h3>")
        page.figure(
            f"curves-{family.name}",
            figures.learning_curves(
                family.name,
                family.tasks,
                family.bands,
                family.counts,
                config.confidence,
                config.bin_steps or {task: width(params, task) for task in family.tasks},
            ),
            f"learning curves of the {family.name} family",
        )
        if family.diagnostics:
            page.figure(
                f"diagnostics-{family.name}",
                figures.diagnostics(family.name, family.tasks, family.diagnostics),
                f"training diagnostics of the {family.name} family",
            )
        for task in family.tasks:
            thresholds = config.thresholds.get(task, [])
            note = f" (thresholds {', '.join(f'{t:g}' for t in thresholds)})" if thresholds else ""
            page.add(f"<h4>{task}{note}</h4>" + _table(family.rows[task], thresholds))
            if family.compared.get(task):
                page.add(_against(family.compared[task]))
            page.add(_fell_back(family.rows[task]))


def _table(rows: list[Row], thresholds: list[float]) -> str:
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
        reached = "".join(f"<td>{steps(row.to_thresholds[t])}</td>" for t in thresholds)
        body.append(
            f"<tr><td>{ALGO_LABELS[algo]}</td><td>{interval(row.final)}</td>"
            f"<td>{interval(row.area)}</td>{reached}<td>{len(row.seeds)}{missing}</td></tr>"
        )
    return f"<table>{head}{''.join(body)}</table>"


def _against(compared: list[Comparison]) -> str:
    """Each algorithm set against others on a task (EDE-TD3 against each other algorithm with
    runs there, then each other algorithm in the EDE space against its raw counterpart), a table
    each: the probability that a run of it beats one of the other's on each score, with its
    interval, and the bins where the interval of its lead over the other lies above 0, below 0,
    of all (— where either has one seed)."""
    tables = []
    for ours in dict.fromkeys(each.ours for each in compared):
        label = html.escape(ALGO_LABELS[ours])
        head = (
            f"<tr><th>{label} against</th>"
            + "".join(f"<th>P({label} &gt; it), {score}</th>" for score in SCORES.values())
            + f"<th>bins with {label} − it above 0, below 0 (of all)</th></tr>"
        )
        body = []
        for each in (c for c in compared if c.ours == ours):
            bins = "—" if (found := each.bins()) is None else "{}, {} (of {})".format(*found)
            body.append(
                f"<tr><td>{html.escape(ALGO_LABELS[each.against])}</td>"
                + "".join(f"<td>{interval(each.improvement[s])}</td>" for s in SCORES)
                + f"<td>{bins}</td></tr>"
            )
        tables.append(f"<table>{head}{''.join(body)}</table>")
    return "".join(tables)


def _fell_back(rows: list[Row]) -> str:
    """The seeds whose last quarter fell below their best by more than noise and than half their
    gain (:func:`ede.analysis.stats.divergence`): flagged, not hidden."""
    flagged = [
        f"{ALGO_LABELS[algo]} seed {seed} (best {verdict.best:.4g} over steps "
        f"{verdict.best_span[0]:,.0f}–{verdict.best_span[1]:,.0f}, last quarter {verdict.last:.4g})"
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


def across_tasks(page: Page, found: AcrossTasks | None, config: ReportConfig) -> None:
    """The claim across tasks, as rliable states it: probability of improvement and IQM of
    normalised scores with stratified bootstrap intervals, and a performance profile."""
    page.add("<h2>Across tasks</h2>")
    if found is None:
        page.add(
            "<p>No task has finished runs of both algorithms yet, or none has one whose best "
            "evaluation is above a random policy's return.</p>"
        )
        return
    rows = []
    for score, label in SCORES.items():
        a = found.aggregates[score]
        rows.append(
            f"<tr><td>{label}</td><td>{interval(a['probability_of_improvement'])}</td>"
            f"<td>{interval(a['iqm_ours'])}</td><td>{interval(a['iqm_theirs'])}</td></tr>"
        )
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


def effect_space(page: Page, drawn: tuple[Pictured, EffectSpace] | None) -> None:
    """Figure 6: the effects of random sequences beside their codes (None: not drawn)."""
    page.add("<h2>The EDE space against the effect space (Figure 6)</h2>")
    if drawn is None:
        page.add("<p>Not drawn: <code>report.effect_space_family</code> is null.</p>")
        return
    pictured, space = drawn
    k = pictured.k
    page.add(
        f"<p>Effects s[t+{k}] − s[t] of {len(space.effects)} random "
        f"{k}-step sequences on {pictured.task} (left) and their codes E(a) under the "
        f"{pictured.family} family's embedding (right), coloured by effect. Best affine map "
        f"effect → code: <b>R² = {space.r_squared:.4f}</b>.</p>"
    )
    page.figure("effect-space", figures.effect_space(space), "effect space beside EDE space")


def exploration(page: Page, drawn: tuple[Pictured, Exploration] | None) -> None:
    """Figure 7: the arena covered by random raw actions and by random codes (None: not
    drawn)."""
    page.add("<h2>Exploration (Figure 7)</h2>")
    if drawn is None:
        page.add("<p>Not drawn: <code>report.exploration_family</code> is null.</p>")
        return
    pictured, explored = drawn
    page.add(
        f"<p>Positions over ten episodes on {pictured.task}: uniform random actions "
        f"every step cover <b>{100 * explored.raw_coverage:.1f}%</b> of the arena (a 20×20 "
        f"grid); uniform random EDE actions of the {pictured.family} family's embedding, chosen "
        f"every {pictured.k} steps, cover <b>{100 * explored.ede_coverage:.1f}%</b>.</p>"
    )
    page.figure(
        "exploration", figures.exploration(explored), "exploration with raw and EDE actions"
    )


def videos(page: Page, clips: list[Clip] | None) -> None:
    """Per task, TD3 beside EDE-TD3 of its median seed (None: ``report.videos`` is false)."""
    page.add("<h2>The agents: TD3 beside EDE-TD3</h2>")
    if clips is None:
        page.add("<p>Not drawn: <code>report.videos</code> is false.</p>")
        return
    page.add(
        "<p>Per task, one evaluation episode of each algorithm's final policy, the seed whose "
        "EDE-TD3 final return is the median; an orange bar marks each step where EDE-TD3 "
        "chooses a code (<code>ede-pipeline render</code>, docs/pipeline.md).</p>"
    )
    for clip in clips:
        task = html.escape(clip.task)
        if clip.seed is None:
            page.add(f"<p>{task}: no clip, no seed finished by both.</p>")
        elif clip.mp4 is None:
            page.add(f"<p>{task}: no clip ({html.escape(clip.why)})</p>")
        else:
            page.add(f"<h4>{task}, seed {clip.seed}</h4>")
            alt = f"{clip.task}: TD3 beside EDE-TD3, seed {clip.seed}"
            page.video(clip_name(clip.task), clip.mp4, alt)


def missing(page: Page, runs: Runs, count: int) -> None:
    """The runs of the ``count`` the params name with no results, and those left out."""
    page.add("<h2>Missing and excluded runs</h2>")
    if runs.absent:
        absent = [f"<code>{html.escape(r)}</code>" for r in runs.absent]
        page.add(_listed(f"{len(runs.absent)} of {count} runs have no results", absent))
    if runs.excluded:
        excluded = [html.escape(r) for r in runs.excluded]
        page.add(
            _listed(
                f"{len(runs.excluded)} finished runs are left out of the figures and tables",
                excluded,
            )
        )
    if not runs.absent and not runs.excluded:
        page.add("<p>None: every run the params name is here.</p>")


def _listed(intro: str, items: list[str]) -> str:
    """A warning, then its items (HTML already) as a list."""
    return (
        f'<p class="missing">{intro}:</p><ul>' + "".join(f"<li>{i}</li>" for i in items) + "</ul>"
    )


def _row(what: str, sha256: str, software: dict[str, str] | None) -> str:
    return (
        f"<tr><td>{html.escape(what)}</td><td><code>{sha256}</code></td>"
        f"<td>{html.escape(describe_software(software))}</td></tr>"
    )


def provenance(
    page: Page,
    params: Params,
    params_text: str,
    inputs: Inputs,
    runs_software: list[dict[str, Any] | None],
) -> None:
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
    page.add(
        "<h2>Provenance</h2>"
        "<table><tr><th>input</th><th>SHA-256</th><th>software</th></tr>"
        + "".join(rows)
        + "</table>"
        f"<details><summary>the params</summary><pre>{params_html}</pre></details>"
    )
