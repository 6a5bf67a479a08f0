"""The results page's sections in Markdown: per task its tables, across tasks the aggregates, per
fidelity ablation the variant against the default (the statistics: :mod:`ede.analysis.results`)."""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from ede.analysis.probes import ZERO_EPISODES
from ede.analysis.results import (
    OURS,
    RANDOM_EPISODES,
    SCORES,
    AcrossTasks,
    Arm,
    Comparison,
    arm,
    comparisons,
    disjoint,
)
from ede.analysis.stats import Band
from ede.config import ALGO_LABELS, ALGOS, PAPER_ALGOS, Params
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
    """One task's row of a table at a glance: EDE-TD3 against one other algorithm there."""

    task: str
    against: str  # the other algorithm (TD3, in the paper's table)
    budget: str
    seeds: str  # the seeds of the two
    final: dict[str, str]  # per algorithm label, the final return's interval
    improvement: dict[str, str]  # P(EDE-TD3 > the other) per score (ede.analysis.results.SCORES)
    bins: tuple[int, int, int] | None  # EDE-TD3's interval above the other's, below, of all bins
    diverged: str  # the other's seeds that diverged, of its seeds


def spans(steps: np.ndarray, width: float) -> str:
    """Bin ends as ranges of consecutive bins: ``12.5K–50K, 100K``."""

    def short(step: float) -> str:
        return f"{step / 1000:g}K"

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


def disjoint_bins(
    stats: dict[str, Arm],
    names: tuple[str, str],
    width: float,
    confidence: float,
    wording: tuple[str, str] | None = None,
) -> list[str]:
    """A line naming the bins (right ends) where two arms' intervals are disjoint, and which lies
    above (the arms as ``wording`` calls them); none where an arm has a single seed, whose
    interval is a point."""
    ours = stats[names[0]]
    sign = disjoint(ours, stats[names[1]])
    if sign is None or ours.band is None:
        return []
    above, below = wording or names
    return [
        f"Bins (right ends) where the {confidence:.0%} intervals are disjoint: {above} above "
        f"{below} at {spans(ours.band.steps[sign > 0], width) or 'none'}; below at "
        f"{spans(ours.band.steps[sign < 0], width) or 'none'}.",
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
    reach each of its ``thresholds``; EDE-TD3 against each other algorithm (the disjoint bins, the
    probability of improvement); per seed, whether it diverged. And each algorithm's band, for
    the family's figure, and its rows at a glance, one per algorithm EDE-TD3 is set against.
    ``paper_budget`` is None beyond the paper."""
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
    for compared in comparisons(found.curves, by_algo, params.report):
        lines += _ede_against(compared, stats, width, params.report.confidence)
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


def _ede_against(
    compared: Comparison, stats: dict[str, Arm], width: float, confidence: float
) -> list[str]:
    """The lines setting EDE-TD3 against one other algorithm on a task: the bins where their
    intervals are disjoint, and the probability of improvement over its seeds."""
    ours, theirs = ALGO_LABELS[OURS], ALGO_LABELS[compared.against]
    return [
        *disjoint_bins(stats, (ours, theirs), width, confidence),
        f"P({ours} > {theirs}) over this task's seeds (rliable, as the aggregates across tasks): "
        + " and ".join(f"{compared.improvement[s]} on the {label}" for s, label in SCORES.items())
        + ".",
        "",
    ]


def _glance(
    found: TaskRuns, compared: Comparison, stats: dict[str, Arm], paper_budget: int | None
) -> Glance:
    """A task's row at a glance in the table of EDE-TD3 against ``compared``'s algorithm."""
    labels = (ALGO_LABELS[OURS], ALGO_LABELS[compared.against])
    diverged = [d for d in stats[labels[1]].divergence if d is not None]
    budget = found.budget
    return Glance(
        found.task,
        compared.against,
        f"{budget:,}"
        + (f" ({budget / paper_budget:.1%} of the paper's)" if paper_budget else " (its own)"),
        seed_list(sorted({c.seed for a in (OURS, compared.against) for c in found.curves[a]})),
        {label: str(stats[label].final) for label in labels},
        {score: str(interval) for score, interval in compared.improvement.items()},
        compared.bins(),
        f"{sum(d.diverged for d in diverged)} of {len(diverged)}",
    )


def _divergence(by_algo: dict[str, Arm]) -> list[str]:
    """Whether each algorithm's runs diverged: the last quarter's mean over seeds, and per seed
    its first bin, its best before the last quarter and its last quarter."""
    lines = [
        "The last quarter's mean over seeds (each seed's in the table below; the asymptote, as "
        "far as this budget shows it): "
        + ", ".join(
            f"{ALGO_LABELS[algo]} {arm_stats.last_quarter or 'too few bins to tell'}"
            for algo, arm_stats in by_algo.items()
        )
        + ".",
        "",
        "| algorithm | seed | first bin | best bin before the last quarter | last quarter "
        "| diverged |",
        "|---|---|---|---|---|---|",
    ]
    for algo, arm_stats in by_algo.items():
        for seed, d in zip(arm_stats.seeds, arm_stats.divergence, strict=True):
            lines.append(
                f"| {ALGO_LABELS[algo]} | {seed} | too few bins to tell | | | |"
                if d is None
                else f"| {ALGO_LABELS[algo]} | {seed} | {d.first:.1f} | {d.best:.1f} at "
                f"{d.best_step / 1000:g}K | {d.tail:.1f} | {'**yes**' if d.diverged else 'no'} |"
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
    """Every task with runs of EDE-TD3 and another algorithm, a table per other algorithm (TD3's
    first, the paper's), one row a task: its budget and seeds, the two algorithms' final returns,
    P(EDE-TD3 > the other) on each score, the bins where their intervals are disjoint and the
    other's seeds that diverged (each as its task's section has it); and under a table, the
    tasks of the others without runs of its algorithm."""
    heading = "The tasks at a glance"
    lines = [
        f"### {heading}",
        "",
        f"Means over seeds with {confidence:.0%} bootstrap intervals. A bin counts where one "
        "algorithm's interval lies wholly above the other's, at the report's bootstrap seed "
        "(with two seeds or more of each; — with fewer).",
    ]
    tasks = list(dict.fromkeys(row.task for row in rows))
    for against in (a for a in ALGOS if any(row.against == a for row in rows)):
        table = [row for row in rows if row.against == against]
        lines += ["", *_glance_table(table, against)]
        if without := [t for t in tasks if t not in {row.task for row in table}]:
            lines += ["", f"No runs of {ALGO_LABELS[against]} on {', '.join(without)}."]
    return Section(heading, "\n".join(lines) + "\n")


def _glance_table(rows: list[Glance], against: str) -> list[str]:
    """The table at a glance of EDE-TD3 against one other algorithm (:func:`at_a_glance`)."""
    theirs, ede = ALGO_LABELS[against], ALGO_LABELS[OURS]
    lines = [
        f"| task | steps a run | seeds | final return, {theirs} | final return, {ede} | "
        + "".join(f"P({ede} > {theirs}), {label} | " for label in SCORES.values())
        + f"bins with {ede} above, below (of all) | {theirs} seeds diverged |",
        "|---|---|---|---|---|---|---|---|" + "---|" * (len(SCORES) - 1),
    ]
    for row in rows:
        bins = "—" if row.bins is None else "{}, {} (of {})".format(*row.bins)
        lines.append(
            f"| {row.task} | {row.budget} | {row.seeds} | {row.final[theirs]} | {row.final[ede]} | "
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
    variant's thresholds with bootstrap intervals, and the bins where their intervals are
    disjoint. And the variant's band per algorithm, for its figure."""
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
            *disjoint_bins(
                stats,
                (variant, "default"),
                width,
                params.report.confidence,
                (variant, "the default"),
            ),
        ]
        sections.append(Section(heading, "\n".join(lines).rstrip("\n") + "\n"))
        if (band := stats[variant].band) is not None:
            variant_bands[algo] = band
    return sections, variant_bands
