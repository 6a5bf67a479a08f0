"""``ede-pipeline results``: the measured results of docs/results.md, redrawn from the per-run
files committed beside it.

    ede-pipeline results [--runs docs/results/runs] [--figures docs/results] [--bins 20]
                         [--ablations docs/results/ablations] [--params params.yaml]

``--runs`` holds one folder per finished run, ``<task>/<algorithm>/seed<N>/`` with its
``eval.csv``, ``run.json`` and ``metrics.json`` (as ``ede-pipeline train`` writes them), laid out as
the pipeline's runs (:func:`ede_pipeline.layout.run`: the task by its full id, so
``ede/ReacherTurn-v0``'s runs are in ``ede/ReacherTurn-v0/``), and in each task's folder a
``source.json`` naming what made its runs (one JSON object, or a list of them, one per experiment,
where its seeds came from several): the commit (``"commit"``, a string, or a list where its
runs were made at several) and the experiment file (``"experiment": "experiments/NAME.yaml"``,
as ``ede-pipeline experiment export`` writes it) or, in files written before experiments were
files, the command (``"command"``); and, optionally, the returns whose first crossing to report
(``"thresholds": [500, 1000]``) and the seeds it runs (``"seeds": [0, 1, 2, 3]``). A task's folder is any folder there holding
a ``source.json`` and runs; its path must be the task its runs name. The tasks are those of the
committed ``params.yaml``'s families, then every other task with a folder there, each its own
family named after it (as an experiment file runs a task ``params.yaml`` does not
train on; never one of ``params.yaml``'s families, whose name it then takes whole). For each
family with runs, this draws its figure (``<figures>/<family>.png``: each task's mean return over
seeds with its bootstrap band, evaluations averaged in ``--bins`` bins of a run's budget, as the
report draws them) and prints, per task, in Markdown:

- the budget a run, as a fraction of the paper's (``runs.budgets``; none beyond the paper), the
  seeds, the experiment file where ``source.json`` names one and the commits (7 characters), per
  part where there are several, and the held-out figures of each embedding the EDE-TD3 runs used
  (``<task>/embedding/<checksum>/``, :func:`ede_pipeline.layout.published_embedding`);
- the CPUs that made its runs (each one's model and instruction sets, as its ``run.json``'s
  ``machine`` records them, and how many runs it made; "CPU unrecorded" for runs made before);
- two reference returns: uniform random actions' (the normalised scores' 0, as the report's) and
  zero actions' over ``ZERO_EPISODES`` episodes with its standard error (doing nothing: on a task
  that penalises actions, a policy must beat it to have learned what the task rewards);
- final return, area under the curve and the steps to reach each threshold per algorithm, with
  bootstrap intervals over seeds;
- the bins where the two algorithms' intervals are disjoint, and which lies above (with two
  seeds or more of each);
- rliable's probability that an EDE-TD3 run beats a TD3 run there, over all the task's seeds,
  on the final return and on the area;
- each algorithm's mean over seeds of a seed's last quarter of bins, with its bootstrap interval
  (the asymptote, as far as the budget shows it);
- per seed, whether it diverged (:func:`ede.stats.divergence`: its last quarter of bins all below
  its best earlier bin by more than half of what it had gained by then);

and, per family, over the paper's tasks (where they span two families and there are tasks beyond
them), over the transfer tasks (the families' targets, where there are two or more: the
transfer claim's own aggregate) and over every task with runs of both algorithms, the report's
aggregates across tasks (rliable: the probability that
EDE-TD3 beats TD3 and each one's interquartile mean of normalised scores, over final returns and
areas, with stratified bootstrap intervals), drawing the performance profile of all of them to
``<figures>/performance-profile.png``. A task with a seed of its ``source.json`` not yet
finished by an algorithm (an experiment still running) waits, named, rather than cutting every
task's seeds to its count; tasks run with more seeds than others (ReacherVertical's 8) give the
aggregates each task's lowest seeds, as many as the fewest, and the rest are named.

``--ablations`` holds the fidelity ablations' runs the same way, one folder per variant
(``<variant>/<task>/<algorithm>/seed<N>/``, ``source.json`` per task, and where kept the variant's
embedding metrics in ``<task>/embedding/<checksum>/``): each is printed, with its experiment file or command,
against the default's runs of the same task, algorithm and seeds in ``--runs``, with the bins where their intervals are disjoint; a
variant run with both algorithms is drawn as a family is, to ``<figures>/ablation-<variant>.png``.

The confidence, the bootstrap's resamples and its seed are the report's (``report`` in
``params.yaml``), and every statistic's bootstrap (an interval, a band of the figure) starts afresh
from that seed, so a number depends on its own runs alone: the same on every machine, whatever
other tasks, algorithms or thresholds are beside it. Bad input (a run, ``source.json``, an
embedding's metrics, a task's folder not at its task's path, an ablation without its default) is
one line and exit code 2 (:class:`ede_pipeline.common.BadInput`), before anything is written. A
run is bad where its folder is not named ``seed<N>`` (a copy ``seed00`` beside ``seed0`` would
count seed 0 twice), its ``run.json`` names another task, algorithm or seed than its folder, a
file of it is not the one its ``run.json`` records the SHA-256 of (runs that record none are
read as they are), or it was made with other params than its task's other runs (those of both
algorithms, and of EDE-TD3's between its runs; :func:`ede.runs.unshared_params`).
"""

from __future__ import annotations

from pathlib import Path

import click
import gymnasium
import numpy as np
from matplotlib.figure import Figure

from ede.atomic import writing_files
from ede.config import ALGO_LABELS, ALGOS, Params
from ede.figures import learning_curves, performance_profile
from ede.probes import RANDOM_EPISODES, ZERO_EPISODES, random_policy_return, zero_action_return
from ede.results import SCORES, AcrossTasks, Arm, across_tasks, arm, disjoint, improvement_on_task
from ede.runs import Curve
from ede.stats import Band
from ede_pipeline import layout
from ede_pipeline.common import BadInput, check_outputs, params_option
from ede_pipeline.published import TaskRuns, read_ablations, read_runs, seed_list

FIGURE_KIND = "results figure"  # what a figure's mark says drew it (ede.atomic.writing_files)


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
    runs; and each arm's statistics (:func:`ede.results.arm`, its band binned per ``width``)."""
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
) -> tuple[str, dict[str, Band]]:
    """One task's tables: per algorithm final return, area under the curve and the steps to
    reach each of its ``thresholds``; the disjoint bins; per seed, whether it diverged. And each
    algorithm's band, for the family's figure. ``paper_budget`` is None beyond the paper."""
    budget, width = found.budget, found.budget / bins
    if paper_budget is None:
        origin = f"{family} family, its own (beyond the paper). {budget:,} steps a run"
    else:
        role = "the family's source task" if found.task == source else "transferred"
        origin = (
            f"{family} family, embedding learned on {source} ({role}). {budget:,} steps a "
            f"run, {budget / paper_budget:.1%} of the paper's {paper_budget:,}"
        )
    arms = {
        ALGO_LABELS[a]: (runs, seed_list([c.seed for c in runs]))
        for a, runs in found.curves.items()
    }
    table, stats = summary_table("algorithm", "seeds", arms, found.source.thresholds, width, params)
    by_algo = {a: stats[ALGO_LABELS[a]] for a in found.curves}
    lines = [
        f"### {found.task}",
        "",
        f"{origin}; {found.source.made_at()}; curves binned per {width:,.0f} steps."
        + (f" Its embedding, held out: {found.embedding}." if found.embedding else "")
        + f" References: uniform random actions {refs[0]:.4g} ({RANDOM_EPISODES} episodes), "
        f"zero actions {refs[1]:.4g} ± {refs[2]:.2g} ({ZERO_EPISODES} episodes, ± standard error).",
        "",
        cpu_line(found.cpus),
        "",
        *table,
        "",
    ]
    if len(arms) == 2:
        labels = (ALGO_LABELS["ede-td3"], ALGO_LABELS["td3"])
        lines += disjoint_bins(stats, labels, width, params.report.confidence)
        report = params.report
        improvement = improvement_on_task(
            found.curves["ede-td3"],
            found.curves["td3"],
            report.confidence,
            report.bootstrap_samples,
            report.seed,
        )
        lines += [
            "P(EDE-TD3 > TD3) over this task's seeds (rliable, as the aggregates across tasks): "
            + " and ".join(f"{improvement[s]} on the {label}" for s, label in SCORES.items())
            + ".",
            "",
        ]
    lines += [
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
    return "\n".join(lines) + "\n", {
        algo: arm_stats.band for algo, arm_stats in by_algo.items() if arm_stats.band is not None
    }


def complete_tasks(
    curves: dict[tuple[str, str], list[Curve]], both: set[str], planned: dict[str, list[int]]
) -> tuple[list[str], str]:
    """The tasks whose runs are all finished — of each algorithm, every seed its ``source.json``
    plans (``"seeds"``; where it names none, the runs there are all there are) — and a line
    naming those that wait, so that no task's seeds are cut to fit one still running."""
    tasks = list(dict.fromkeys(t for t, _ in curves if t in both))
    finished = {
        t: min(len({c.seed for c in curves[(t, a)]} & set(planned.get(t, ()))) for a in ALGOS)
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


def across_section(title: str, found: AcrossTasks, params) -> str:
    """The aggregates across tasks as a Markdown table, after what they are over."""
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
    return "\n".join(lines) + "\n"


def cpu_line(cpus: dict[str | None, int]) -> str:
    """``Runs made on: Intel(R) Xeon(R) Processor (avx2, avx512f): 8; CPU unrecorded: 8.``"""
    named = [f"{name}: {count}" for name, count in cpus.items() if name is not None]
    unrecorded = [f"CPU unrecorded: {cpus[None]}"] if None in cpus else []
    return f"Runs made on: {'; '.join(named + unrecorded)}."


def ablation_sections(
    variant: str, ours: TaskRuns, theirs: TaskRuns, bins: int, params: Params
) -> tuple[str, dict[str, Band]]:
    """Per algorithm, the default and the variant: final return, area and steps to each of the
    variant's thresholds with bootstrap intervals, and the bins where their intervals are
    disjoint. And the variant's band per algorithm, for its figure."""
    width = ours.budget / bins
    sections: list[str] = []
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
        lines = [
            f"### {variant}: {ours.task}, {ALGO_LABELS[algo]}",
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
        sections.append("\n".join(lines).rstrip("\n") + "\n")
        if (band := stats[variant].band) is not None:
            variant_bands[algo] = band
    return "\n".join(sections), variant_bands


def references(tasks: list[str], params) -> dict[str, tuple[float, float, float]]:
    """Each task's reference returns: uniform random actions' (the low end of its normalised
    scores) and zero actions' with its standard error (ZERO_EPISODES episodes)."""
    found = {}
    for task in tasks:
        try:
            found[task] = (
                random_policy_return(task, RANDOM_EPISODES, params.report.seed),
                *zero_action_return(task, ZERO_EPISODES, params.report.seed),
            )
        except (gymnasium.error.Error, ValueError) as error:
            raise BadInput(
                f"{task}: cannot be made to measure its reference returns: {error}"
            ) from None
    return found


@click.command()
@click.option(
    "--runs",
    type=click.Path(file_okay=False, path_type=Path),
    default=layout.RESULTS_RUNS,
    show_default=True,
    help="The published runs: a folder per task, as `ede-pipeline experiment export` writes them.",
)
@click.option(
    "--figures",
    type=click.Path(file_okay=False, path_type=Path),
    default=layout.RESULTS,
    show_default=True,
    help="Where the figures go.",
)
@click.option(
    "--bins",
    type=click.IntRange(min=1),
    default=20,
    show_default=True,
    help="Bins per run's budget.",
)
@click.option(
    "--ablations",
    type=click.Path(file_okay=False, path_type=Path),
    help="One folder per variant, each compared with the default's runs in --runs  "
    "[default: 'ablations' beside --runs]",
)
@params_option
def results(params: Params, runs: Path, figures: Path, bins: int, ablations: Path | None) -> None:
    """Print docs/results.md's tables (Markdown) and draw its figures from the published runs.

    Per task: budget, seeds, experiment and commits, the CPUs of its runs, reference returns,
    final return, area and steps to each threshold with bootstrap intervals, the bins where the
    algorithms' intervals are disjoint, the probability of improvement, and which seeds diverged;
    per family, its figure and the aggregates across tasks; per fidelity ablation, its runs against
    the default's. Every statistic is the report's (params' `report`). Bad input is one line, exit
    2, before anything is written.
    """
    ablations = ablations or runs.parent / "ablations"
    report = params.report
    families = read_runs(runs, params)
    found_ablations = read_ablations(ablations, runs) if ablations.is_dir() else []
    curves_of = {
        family: {(f.task, a): c for f in found for a, c in f.curves.items()}
        for family, found in families.items()
    }
    both = {
        task
        for curves in curves_of.values()
        for (task, _) in curves
        if all((task, a) in curves for a in ALGOS)
    }
    refs = references([f.task for found in families.values() for f in found], params)
    lows = {task: refs[task][0] for task in both}
    planned = {f.task: f.source.seeds for found in families.values() for f in found}
    drawings = [*families, "performance-profile", *(f"ablation-{v}" for v, *_ in found_ablations)]
    check_outputs(  # each figure a new file or one this command drew, before any is drawn
        (None, FIGURE_KIND),
        files=tuple((figures / f"{name}.png", FIGURE_KIND) for name in drawings),
        inputs=(runs, ablations),
    )

    def save(figure: Figure, name: str) -> None:
        figures.mkdir(parents=True, exist_ok=True)
        with writing_files([(figures / f"{name}.png", FIGURE_KIND)]):
            figure.savefig(figures / f"{name}.png", dpi=120)

    # Every input is read and checked: from here on, print and draw.
    for family, found in families.items():
        source = params.families[family].source if family in params.families else found[0].task
        bands: dict[tuple[str, str], Band] = {}
        for task_runs in found:
            text, task_bands = task_section(
                task_runs,
                family,
                source,
                params.runs.budgets.get(task_runs.task),
                bins,
                refs[task_runs.task],
                params,
            )
            click.echo(text)
            bands.update({(task_runs.task, a): band for a, band in task_bands.items()})
        figure = learning_curves(
            family,
            [f.task for f in found],
            bands,
            {key: len(runs) for key, runs in curves_of[family].items()},
            report.confidence,
            {f.task: f.budget / bins for f in found},
        )
        save(figure, family)
        click.echo(f"Figure: {figures / f'{family}.png'}\n")
    everything = {key: c for curves in curves_of.values() for key, c in curves.items()}
    sets = [(f"the {family} family", curves) for family, curves in curves_of.items()]
    paper = [family for family in curves_of if family in params.families]
    if len(curves_of) > len(paper) > 1:  # and the tasks beyond, in "every task"
        sets.append(("the paper's tasks", {k: c for f in paper for k, c in curves_of[f].items()}))
    # The transfer claim's own aggregate: the tasks an embedding learned elsewhere acts in.
    targets = {t for f in paper for t in params.families[f].targets}
    transfer = {k: c for f in paper for k, c in curves_of[f].items() if k[0] in targets}
    if len({task for task, _ in transfer}) > 1:
        sets.append(("the transfer tasks", transfer))
    for title, curves in sets + [("every task", everything)] * (len(curves_of) > 1):
        tasks, waiting = complete_tasks(curves, both, planned)
        aggregates = across_tasks(
            curves,
            {t: lows[t] for t in tasks},
            report.confidence,
            report.bootstrap_samples,
            report.seed,
        )
        if aggregates is not None:
            click.echo(across_section(title, aggregates, params) + waiting)
            if title == "every task" or len(curves_of) == 1:
                profile = aggregates.profile
                save(
                    performance_profile(profile, len(aggregates.tasks), aggregates.runs),
                    "performance-profile",
                )
    drawn: dict[str, list[tuple[TaskRuns, dict[str, Band]]]] = {}
    for variant, ours, theirs in found_ablations:
        text, variant_bands = ablation_sections(variant, ours, theirs, bins, params)
        click.echo(text)
        if set(ours.curves) == set(ALGOS):  # both algorithms: drawn as a family is
            drawn.setdefault(variant, []).append((ours, variant_bands))
    for variant, kept in drawn.items():
        figure = learning_curves(
            variant,
            [k.task for k, _ in kept],
            {(k.task, a): band for k, bands in kept for a, band in bands.items()},
            {(k.task, a): len(c) for k, _ in kept for a, c in k.curves.items()},
            report.confidence,
            {k.task: k.budget / bins for k, _ in kept},
            title=f"the {variant} variant (a fidelity ablation)",
        )
        save(figure, f"ablation-{variant}")
        click.echo(f"Figure: {figures / f'ablation-{variant}.png'}\n")
