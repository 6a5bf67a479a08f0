"""The results page's sections in Markdown: per task its tables, across tasks the aggregates, per
fidelity ablation the variant against the default (the statistics: :mod:`ede.analysis.results`)."""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from ede.analysis.probes import ZERO_EPISODES
from ede.analysis.results import (
    OURS,
    PAIRS,
    RANDOM_EPISODES,
    SCORES,
    AcrossTasks,
    Arm,
    Comparison,
    Lead,
    arm,
    comparisons,
    lead,
)
from ede.analysis.stats import Band
from ede.config import ALGO_LABELS, PAPER_ALGOS, Params
from ede.run.runs import Curve
from ede_pipeline.published import TaskRuns, seed_list


class Section(NamedTuple):
    """A section of the results: its heading (what a page's block names it by; None for a line
    no block takes, as where a figure went) and its Markdown, the heading's line first."""

    heading: str | None
    text: str

    @property
    def body(self) -> str:
        """The Markdown under the heading: what a page's block holds."""
        return self.text.split("\n", 2)[2] if self.heading else self.text


class Glance(NamedTuple):
    """One task's row of a table at a glance: one algorithm against another there (a pair of
    :data:`ede.analysis.results.PAIRS`)."""

    task: str
    algos: tuple[str, ...]  # the task's algorithms with runs
    ours: str  # the algorithm set against the other (EDE-TD3, in the paper's table)
    against: str  # the other algorithm (TD3, in the paper's table)
    budget: str
    seeds: str  # the seeds of the two
    final: dict[str, str]  # per algorithm label, the final return's interval
    improvement: dict[str, str]  # P(ours > against) per score (ede.analysis.results.SCORES)
    bins: tuple[int, int, int] | None  # bins where ours' lead is above 0, below 0, of all
    diverged: str  # the other's seeds that declined and that diverged, of its seeds


def short(step: float) -> str:
    """A step in thousands: ``12.5K``."""
    return f"{step / 1000:g}K"


def spans(steps: np.ndarray, width: float) -> str:
    """Bin ends as ranges of consecutive bins: ``12.5K–50K, 100K``."""
    groups: list[list[float]] = []
    for step in steps:
        if groups and step - groups[-1][-1] <= width:
            groups[-1].append(step)
        else:
            groups.append([step])
    return ", ".join(
        short(g[0]) if len(g) == 1 else f"{short(g[0])}–{short(g[-1])}" for g in groups
    )


def summary_table(
    first: str,
    second: str,
    arms: dict[str, tuple[list[Curve], str]],
    thresholds: list[float],
    width: float,
    params: Params,
) -> tuple[list[str], dict[str, Arm]]:
    """A table of one row per arm (its name: its runs and its second column): final return, area
    under the curve and the steps to reach each threshold, with bootstrap intervals over the
    runs; and each arm's statistics (:func:`ede.analysis.results.arm`, its band binned per ``width``)."""
    lines = [
        f"| {first} | {second} | final return | area under the curve |"
        + "".join(f" steps to reach {t:g} |" for t in thresholds),
        "|---|---|---|---|" + "---|" * len(thresholds),
    ]
    stats = {}
    for name, (runs, column) in arms.items():
        found = stats[name] = arm(runs, thresholds, width, params.report)
        lines.append(
            f"| {name} | {column} | {found.final} | {found.area} |"
            + "".join(f" {found.to_thresholds[t].steps()} |" for t in thresholds)
        )
    return lines, stats


def lead_lines(
    found: Lead | None, names: tuple[str, str], width: float, confidence: float
) -> list[str]:
    """The lines of one arm's lead over another (:func:`ede.analysis.results.lead`; the arms as
    ``names`` calls them): the bins (right ends) where its interval lies above 0 and below 0, and
    the lead on the final return and the area; none where an arm has a single seed."""
    if found is None:
        return []
    band, difference = found.band, f"{names[0]} − {names[1]}"

    def where(side: np.ndarray, word: str) -> str:
        count = int(side.sum())
        if not count:
            return f"{word} 0 in none"
        return f"{word} 0 in {count} of {len(side)} bins ({spans(band.steps[side], width)})"

    return [
        f"{difference} per bin, with its {confidence:.0%} bootstrap interval over seeds: "
        f"{where(band.low > 0, 'above')}, {where(band.high < 0, 'below')}.",
        "",
        f"{difference} overall: {found.final} on the final return, {found.area} on the area "
        "under the curve.",
        "",
    ]


def task_section(
    found: TaskRuns,
    family: str,
    source: str,
    paper_budget: int | None,
    bins: int,
    refs: tuple[float, float, float],
    params,
) -> tuple[Section, dict[str, Band], list[Glance]]:
    """One task's tables: per algorithm final return, area under the curve and the steps to
    reach each of its ``thresholds``; EDE-TD3 against each other algorithm, then each other
    algorithm in the EDE space against its raw counterpart (the one's lead, per bin and overall,
    and the probability of improvement; :func:`ede.analysis.results.comparisons`); per seed,
    whether it declined or diverged. And each algorithm's band, for the family's figure, and its
    rows at a glance, one per pair set against each other. ``paper_budget`` is None beyond the
    paper."""
    width = found.budget / bins
    arms = {
        ALGO_LABELS[a]: (runs, seed_list([c.seed for c in runs]))
        for a, runs in found.curves.items()
    }
    table, stats = summary_table("algorithm", "seeds", arms, found.source.thresholds, width, params)
    by_algo = {a: stats[ALGO_LABELS[a]] for a in found.curves}
    lines = [
        f"### {found.task}",
        "",
        f"{_origin(found, family, source, paper_budget)}; {found.source.made_at()}; curves "
        f"binned per {width:,.0f} steps."
        + (f" Its embedding, held out: {found.embedding}." if found.embedding else "")
        + f" References: uniform random actions {refs[0]:.4g} ({RANDOM_EPISODES} episodes), "
        f"zero actions {refs[1]:.4g} ± {refs[2]:.2g} ({ZERO_EPISODES} episodes, ± standard error).",
        "",
        cpu_line(found.cpus),
        "",
        *table,
        "",
    ]
    glance = []
    for compared in comparisons(found.curves, width, params.report):
        lines += _set_against(compared, width, params.report.confidence)
        glance.append(_glance(found, compared, stats, paper_budget))
    lines += _divergence(by_algo)
    bands = {algo: found.band for algo, found in by_algo.items() if found.band is not None}
    return Section(found.task, "\n".join(lines) + "\n"), bands, glance


def _origin(found: TaskRuns, family: str, source: str, paper_budget: int | None) -> str:
    """Where a task's runs come from: its family, where its embedding was learned, and its
    budget against the paper's (``paper_budget``; None beyond the paper)."""
    budget = found.budget
    if paper_budget is None:
        return f"{family} family, its own (beyond the paper). {budget:,} steps a run"
    role = "the family's source task" if found.task == source else "transferred"
    return (
        f"{family} family, embedding learned on {source} ({role}). {budget:,} steps a "
        f"run, {budget / paper_budget:.1%} of the paper's {paper_budget:,}"
    )


def _set_against(compared: Comparison, width: float, confidence: float) -> list[str]:
    """The lines setting one algorithm against another on a task: its lead, per bin and overall,
    and the probability of improvement over their seeds."""
    ours, theirs = ALGO_LABELS[compared.ours], ALGO_LABELS[compared.against]
    return [
        *lead_lines(compared.lead, (ours, theirs), width, confidence),
        f"P({ours} > {theirs}) over this task's seeds (rliable, as the aggregates across tasks): "
        + " and ".join(f"{compared.improvement[s]} on the {label}" for s, label in SCORES.items())
        + ".",
        "",
    ]


def _glance(
    found: TaskRuns, compared: Comparison, stats: dict[str, Arm], paper_budget: int | None
) -> Glance:
    """A task's row at a glance in the table of ``compared``'s pair."""
    pair = (compared.ours, compared.against)
    labels = (ALGO_LABELS[compared.ours], ALGO_LABELS[compared.against])
    diverged = [d for d in stats[labels[1]].divergence if d is not None]
    budget = found.budget
    return Glance(
        found.task,
        tuple(found.curves),
        compared.ours,
        compared.against,
        f"{budget:,}"
        + (f" ({budget / paper_budget:.1%} of the paper's)" if paper_budget else " (its own)"),
        seed_list(sorted({c.seed for a in pair for c in found.curves[a]})),
        {label: str(stats[label].final) for label in labels},
        {score: str(interval) for score, interval in compared.improvement.items()},
        compared.bins(),
        f"{sum(d.declined for d in diverged)}, {sum(d.diverged for d in diverged)} "
        f"(of {len(diverged)})",
    )


def _divergence(by_algo: dict[str, Arm]) -> list[str]:
    """Whether each algorithm's runs declined or diverged (:func:`ede.analysis.stats.divergence`):
    the last quarter's mean over seeds, and per seed its untrained policy's return, its best window
    before the last quarter, its last quarter, the decline and how far noise alone reaches."""
    lines = [
        "The last quarter's mean over seeds (each seed's in the table below; the asymptote, as "
        "far as this budget shows it): "
        + ", ".join(
            f"{ALGO_LABELS[algo]} {arm_stats.last_quarter or 'too few evaluations to tell'}"
            for algo, arm_stats in by_algo.items()
        )
        + ".",
        "",
        "| algorithm | seed | untrained (step 0) | best quarter before the last (its span) "
        "| last quarter | decline (best − last) | noise alone reaches (on a plateau, at the confidence) | declined | diverged |",
        "|---|---|---|---|---|---|---|---|---|",
    ]

    def verdict(yes: bool) -> str:
        return "**yes**" if yes else "no"

    for algo, arm_stats in by_algo.items():
        for seed, d in zip(arm_stats.seeds, arm_stats.divergence, strict=True):
            lines.append(
                f"| {ALGO_LABELS[algo]} | {seed} | too few evaluations to tell | | | | | | |"
                if d is None
                else f"| {ALGO_LABELS[algo]} | {seed} | {d.first:.1f} | {d.best:.1f} "
                f"({short(d.best_span[0])}–{short(d.best_span[1])}) | {d.last:.1f} | {d.decline:.1f} | "
                f"{d.noise:.1f} | {verdict(d.declined)} | {verdict(d.diverged)} |"
            )
    return lines


def complete_tasks(
    curves: dict[tuple[str, str], list[Curve]], both: set[str], planned: dict[str, list[int]]
) -> tuple[list[str], str]:
    """The tasks whose runs are all finished — of each algorithm, every seed its ``source.json``
    plans (``"seeds"``; where it names none, the runs there are all there are) — and a line
    naming those that wait, so that no task's seeds are cut to fit one still running."""
    tasks = list(dict.fromkeys(t for t, _ in curves if t in both))
    finished = {
        t: min(len({c.seed for c in curves[(t, a)]} & set(planned.get(t, ()))) for a in PAPER_ALGOS)
        for t in tasks
    }
    waiting = [t for t in tasks if finished[t] < len(planned.get(t, ()))]
    named = ", ".join(f"{t} ({finished[t]} of its {len(planned[t])} seeds)" for t in waiting)
    note = (
        (f"\nNot yet in these aggregates, with runs of an algorithm still to finish: {named}.\n")
        if waiting
        else ""
    )
    return [t for t in tasks if t not in waiting], note


def across_section(title: str, found: AcrossTasks, params, waiting: str) -> Section:
    """The aggregates across tasks as a Markdown table, after what they are over, and the line
    naming the tasks that wait (:func:`complete_tasks`)."""
    report = params.report
    lines = [
        f"### Across tasks: {title}",
        "",
        found.describe(report.confidence, report.bootstrap_samples),
        "",
        "| score | P(EDE-TD3 > TD3) | IQM, EDE-TD3 | IQM, TD3 |",
        "|---|---|---|---|",
    ]
    for score, label in SCORES.items():
        a = found.aggregates[score]
        lines.append(
            f"| {label} | {a['probability_of_improvement']} | {a['iqm_ours']} | {a['iqm_theirs']} |"
        )
    return Section(f"Across tasks: {title}", "\n".join(lines) + "\n" + waiting)


def at_a_glance(rows: list[Glance], confidence: float) -> Section:
    """Every task with runs of both algorithms of a pair (:data:`ede.analysis.results.PAIRS`), a
    table per pair in that order (EDE-TD3 against TD3 first, the paper's; then EDE-TD3 against
    each other algorithm; then each other algorithm in the EDE space against its raw
    counterpart), one row a task: its budget and seeds, the two algorithms' final returns, P(the
    first > the second) on each score, the bins where the first's lead lies above and below 0 and
    the second's seeds that declined and diverged (each as its task's section has it); and under
    a table, the other tasks, by the algorithm of its pair they have no runs of."""
    heading = "The tasks at a glance"
    lines = [
        f"### {heading}",
        "",
        f"Means over seeds with {confidence:.0%} bootstrap intervals. A bin counts where the "
        "interval of EDE-TD3's lead (its mean minus the other's) lies above 0, or below, at the "
        "report's bootstrap seed (with two seeds or more of each; — with fewer).",
    ]
    algos = {row.task: row.algos for row in rows}  # each task's algorithms with runs
    shown = [p for p in PAIRS if any((row.ours, row.against) == p for row in rows)]
    space = next((p for p in shown if p[0] != OURS), None)  # the first of the EDE space's tables
    for pair in shown:
        if pair == space:
            lines += [
                "",
                "Each other algorithm in the EDE space against the same learner on raw actions: "
                "a bin counts where the interval of its lead (its mean minus the learner's) lies "
                "above 0, or below.",
            ]
        table = [row for row in rows if (row.ours, row.against) == pair]
        lines += ["", *_glance_table(table, pair)]
        drawn = {row.task for row in table}
        lacking: dict[str, list[str]] = {}  # by the algorithms of the pair without runs there
        for task in (t for t in algos if t not in drawn):
            names = " or ".join(ALGO_LABELS[a] for a in pair if a not in algos[task])
            lacking.setdefault(names, []).append(task)
        for names, tasks in lacking.items():
            lines += ["", f"No runs of {names} on {', '.join(tasks)}."]
    return Section(heading, "\n".join(lines) + "\n")


def _glance_table(rows: list[Glance], pair: tuple[str, str]) -> list[str]:
    """The table at a glance of a pair's first algorithm against its second
    (:func:`at_a_glance`)."""
    ours, theirs = (ALGO_LABELS[a] for a in pair)
    lines = [
        f"| task | steps a run | seeds | final return, {theirs} | final return, {ours} | "
        + "".join(f"P({ours} > {theirs}), {label} | " for label in SCORES.values())
        + f"bins with {ours} − {theirs} above 0, below 0 (of all) | "
        + f"{theirs} seeds declined, diverged (of all) |",
        "|---|---|---|---|---|---|---|---|" + "---|" * (len(SCORES) - 1),
    ]
    for row in rows:
        bins = "—" if row.bins is None else "{}, {} (of {})".format(*row.bins)
        lines.append(
            f"| {row.task} | {row.budget} | {row.seeds} | {row.final[theirs]} | {row.final[ours]} | "
            + "".join(f"{row.improvement[score]} | " for score in SCORES)
            + f"{bins} | {row.diverged} |"
        )
    return lines


def cpu_line(cpus: dict[str | None, int]) -> str:
    """``Runs made on: Intel(R) Xeon(R) Processor (avx2, avx512f): 8; CPU unrecorded: 8.``"""
    named = [f"{name}: {count}" for name, count in cpus.items() if name is not None]
    unrecorded = [f"CPU unrecorded: {cpus[None]}"] if None in cpus else []
    return f"Runs made on: {'; '.join(named + unrecorded)}."


def ablation_sections(
    variant: str, ours: TaskRuns, theirs: TaskRuns, bins: int, params: Params
) -> tuple[list[Section], dict[str, Band]]:
    """Per algorithm, the default and the variant: final return, area and steps to each of the
    variant's thresholds with bootstrap intervals, and the variant's lead over the default, per
    bin and overall. And the variant's band per algorithm, for its figure."""
    width = ours.budget / bins
    sections: list[Section] = []
    variant_bands: dict[str, Band] = {}
    for algo, runs in ours.curves.items():

        def column(kept: TaskRuns, algo: str = algo) -> str:  # TD3 runs use no embedding
            figures = kept.embedding if algo == "ede-td3" else None
            return f"{', '.join(kept.source.short_commits())}; {figures or '—'}"

        arms = {"default": (theirs.curves[algo], column(theirs)), variant: (runs, column(ours))}
        table, stats = summary_table(
            "runs",
            "commit; embedding (held out)",
            arms,
            ours.source.thresholds,
            width,
            params,
        )
        heading = f"{variant}: {ours.task}, {ALGO_LABELS[algo]}"
        lines = [
            f"### {heading}",
            "",
            f"{ours.budget:,} steps a run, seeds {seed_list([c.seed for c in runs])} of each; the variant's "
            f"{ours.source.maker()}; curves binned per {width:,.0f} steps.",
            "",
            *table,
            "",
            *lead_lines(
                lead(runs, theirs.curves[algo], width, params.report),
                (variant, "the default"),
                width,
                params.report.confidence,
            ),
        ]
        sections.append(Section(heading, "\n".join(lines).rstrip("\n") + "\n"))
        if (band := stats[variant].band) is not None:
            variant_bands[algo] = band
    return sections, variant_bands
