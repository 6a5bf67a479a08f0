"""The measured results of docs/results.md, redrawn from the per-run files committed beside it.

    python benchmarks/results.py [--runs docs/results/runs] [--figures docs/results] [--bins 20]
                                 [--ablations docs/results/ablations]

``--runs`` holds one folder per finished run, ``<task>/<algorithm>/seed<N>/`` with its
``eval.csv``, ``run.json`` and ``metrics.json`` (as ``ede-pipeline train`` writes them), and per
task a ``source.json`` naming the commit and command that made its runs and, optionally, the
returns whose first crossing to report (``"thresholds": [500, 1000]``). The tasks are those of the
committed ``params.yaml``'s families, then every other task with a folder there, each its own
family (as ``benchmarks/experiment.py`` runs a task ``params.yaml`` does not train on). For each
family with runs, this draws its figure (``<figures>/<family>.png``: each task's mean return over
seeds with its bootstrap band, evaluations averaged in ``--bins`` bins of a run's budget, as the
report draws them) and prints, per task, in Markdown:

- the budget a run, as a fraction of the paper's (``runs.budgets``; none beyond the paper), the
  seeds, the commit;
- final return, area under the curve and the steps to reach each threshold per algorithm, with
  bootstrap intervals over seeds;
- the bins where the two algorithms' intervals are disjoint, and which lies above;
- per seed, whether it diverged (:func:`ede.stats.divergence`: its last quarter of bins all below
  its best earlier bin by more than half of what it had gained by then);

and, per family, over the paper's tasks (where there are tasks beyond them) and over every task
with runs of both algorithms, the report's aggregates across tasks (rliable: the probability that
EDE-TD3 beats TD3 and each one's interquartile mean of normalised scores, over final returns and
areas, with stratified bootstrap intervals), drawing the performance profile of all of them to
``<figures>/performance-profile.png``. A task with fewer runs of an algorithm than the others (an
experiment still running) waits, named, rather than cutting every task's seeds to its count.

``--ablations`` holds the fidelity ablations' runs the same way, one folder per variant
(``<variant>/<task>/<algorithm>/seed<N>/``, ``source.json`` per task, and where kept the variant's
embedding metrics in ``<task>/embedding/``): each is printed against the default's runs of the
same task, algorithm and seeds in ``--runs``, with the bins where their intervals are disjoint.

The confidence, the bootstrap's resamples and its seed are the report's (``report`` in
``params.yaml``), and each task's bootstrap starts afresh from that seed, so a task's numbers are
the same on every machine and whatever other tasks are beside it.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np

from ede.config import ParamsError, load_params
from ede.report import (
    ALGO_STYLE,
    RANDOM_EPISODES,
    SCORES,
    AcrossTasks,
    Curve,
    RunRejected,
    across_tasks_section,
    curve_band,
    learning_curve_figure,
    random_policy_return,
    read_run,
    summarise_task,
)
from ede.stats import divergence, separation
from ede_pipeline import layout

REPO = Path(__file__).resolve().parents[1]


class Refused(Exception):
    """Input this cannot use: one line naming the file and what is expected (exit code 2, before
    anything is written)."""


def task_folder(task: str) -> str:
    """``ede/ReacherTurn-v0`` is kept in ``ReacherTurn-v0``."""
    return task.split("/")[-1]


def read_task(folder: Path, task: str) -> tuple[dict[str, list[Curve]], int]:
    """Each algorithm's finished curves of one task, and the budget its runs share."""
    curves: dict[str, list[Curve]] = {}
    budgets = set()
    for algo in ALGO_STYLE:
        for run in sorted((folder / algo).glob("seed*"), key=lambda p: int(p.name[4:])):
            try:
                record = read_run(run, {"task": task, "algo": algo, "seed": int(run.name[4:])})
            except RunRejected as error:
                raise Refused(str(error)) from None
            if record is not None:
                curves.setdefault(algo, []).append(record.curve)
                budgets.add(int(record.curve.steps[-1]))  # checked: the run's budget
    if len(budgets) > 1:
        raise Refused(f"{folder}: runs of different budgets {sorted(budgets)}; keep one per task")
    return curves, budgets.pop() if budgets else 0


def seed_list(curves: list[Curve]) -> str:
    seeds = [c.seed for c in curves]
    if seeds == list(range(seeds[0], seeds[-1] + 1)) and len(seeds) > 2:
        return f"{seeds[0]}–{seeds[-1]}"
    return ", ".join(map(str, seeds))


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
    return ", ".join(short(g[0]) if len(g) == 1 else f"{short(g[0])}–{short(g[-1])}" for g in groups)


def summary_table(first: str, second: str, arms: dict[str, tuple[list[Curve], str]], task: str,
                  algos: dict[str, str], thresholds: list[float], width: float, params,
                  rng: np.random.Generator) -> tuple[list[str], dict[str, tuple]]:
    """A table of one row per arm (its name: its runs and second column), with final return, area
    under the curve and the steps to reach each threshold, with bootstrap intervals over the
    runs; and each arm's binned band. ``algos`` names each arm's algorithm."""
    report = params.report
    lines = [f"| {first} | {second} | final return | area under the curve |"
             + "".join(f" steps to reach {t:g} |" for t in thresholds),
             "|---|---|---|---|" + "---|" * len(thresholds)]
    bands = {}
    for name, (runs, column) in arms.items():
        row = summarise_task(task, algos[name], runs, [], None, report.confidence,
                             report.bootstrap_samples, rng)
        bands[name] = curve_band(runs, report.confidence, report.bootstrap_samples, rng, width)
        reached = [summarise_task(task, algos[name], runs, [], t, report.confidence,
                                  report.bootstrap_samples, rng).to_threshold for t in thresholds]
        lines.append(f"| {name} | {column} | {row.final} | {row.auc} |"
                     + "".join(f" {r.steps()} |" for r in reached))
    return lines, bands


def disjoint_bins(ours: tuple, theirs: tuple, width: float, names: tuple[str, str],
                  confidence: float) -> str:
    """The bins (right ends) where two bands' intervals are disjoint, and which lies above."""
    (steps, _, low_a, high_a, _), (_, _, low_b, high_b, _) = ours, theirs
    sign = separation(low_a, high_a, low_b, high_b)
    return (f"Bins (right ends) where the {confidence:.0%} intervals are disjoint: {names[0]} "
            f"above {names[1]} at {spans(steps[sign > 0], width) or 'none'}; below at "
            f"{spans(steps[sign < 0], width) or 'none'}.")


def task_section(task: str, family: str, source: str, curves: dict[str, list[Curve]], budget: int,
                 paper_budget: int | None, made: dict, bins: int, params, embedding: str | None) -> str:
    """One task's tables: per algorithm final return, area under the curve and the steps to
    reach each of ``made``'s ``thresholds``; the disjoint bins; per seed, whether it diverged.
    ``paper_budget`` is None for a task beyond the paper; ``embedding``, the held-out figures of
    the embedding EDE-TD3 used (:func:`embedding_figures`). The bootstrap starts afresh from the
    report's seed for each task, so a task's numbers depend on its runs alone."""
    report = params.report
    rng = np.random.default_rng(report.seed)
    width = budget / bins
    thresholds = [float(t) for t in made.get("thresholds", [])]
    if paper_budget is None:
        origin = f"{family} family, its own (beyond the paper). {budget:,} steps a run"
    else:
        role = "the family's source task" if task == source else "transferred"
        origin = (f"{family} family, embedding learned on {source} ({role}). {budget:,} steps a "
                  f"run, {budget / paper_budget:.1%} of the paper's {paper_budget:,}")
    labels = {ALGO_STYLE[algo][0]: algo for algo in curves}
    table, bands = summary_table("algorithm", "seeds", {ALGO_STYLE[a][0]: (runs, seed_list(runs))
                                                       for a, runs in curves.items()},
                                 task, labels, thresholds, width, params, rng)
    lines = [f"### {task}", "",
             f"{origin}; commit {made['commit'][:7]}; curves binned per {width:,.0f} steps."
             + (f" Its embedding, held out: {embedding}." if embedding else ""), "", *table, ""]
    if len(bands) == 2:
        lines += [disjoint_bins(bands["EDE-TD3"], bands["TD3"], width, ("EDE-TD3", "TD3"),
                                report.confidence), ""]
    lines += ["| algorithm | seed | first bin | best bin before the last quarter | last quarter "
              "| diverged |", "|---|---|---|---|---|---|"]
    for algo, runs in curves.items():
        for curve in runs:
            d = divergence(curve.steps, curve.returns, width)
            lines.append(f"| {ALGO_STYLE[algo][0]} | {curve.seed} | {d.first:.1f} | {d.best:.1f} at "
                         f"{d.best_step / 1000:g}K | {d.tail:.1f} | {'**yes**' if d.diverged else 'no'} |")
    return "\n".join(lines) + "\n"


def complete_tasks(curves: dict[tuple[str, str], list[Curve]], both: set[str]) -> tuple[list[str], str]:
    """The tasks with as many runs of each algorithm as the most any task has — so no task's
    seeds are cut to fit one still running — and a line naming those that wait."""
    tasks = list(dict.fromkeys(t for t, _ in curves if t in both))
    counts = {t: min(len(curves[(t, a)]) for a in ALGO_STYLE) for t in tasks}
    most = max(counts.values(), default=0)
    waiting = [f"{t} ({counts[t]} of {most})" for t in tasks if counts[t] < most]
    note = (f"\nNot yet in these aggregates, with fewer runs of an algorithm than the others: "
            f"{', '.join(waiting)}.\n") if waiting else ""
    return [t for t in tasks if counts[t] == most], note


def across_section(title: str, found: AcrossTasks, params) -> str:
    """The aggregates across tasks as a Markdown table, after what they are over."""
    report = params.report
    lines = [f"### Across tasks: {title}", "", found.describe(report.confidence,
                                                             report.bootstrap_samples), "",
             "| score | P(EDE-TD3 > TD3) | IQM, EDE-TD3 | IQM, TD3 |", "|---|---|---|---|"]
    for score, label in SCORES.items():
        a = found.aggregates[score]
        lines.append(f"| {label} | {a['probability_of_improvement']} | {a['iqm_ours']} | "
                     f"{a['iqm_theirs']} |")
    return "\n".join(lines) + "\n"


def embedding_figures(folder: Path) -> str | None:
    """The held-out figures of the embedding a task's EDE-TD3 runs used, where its metrics are kept
    beside them (``<task>/embedding/{encoder,decoder}_metrics.json``, as ``pretrain`` writes them)."""
    encoder, decoder = (folder / "embedding" / f"{part}_metrics.json" for part in ("encoder", "decoder"))
    if not encoder.is_file():
        return None
    e = json.loads(encoder.read_text())
    parts = [f"prediction ratio {e['prediction_ratio']:.3f}", f"KL {e['kl']:.1f} nats"]
    if decoder.is_file():
        d = json.loads(decoder.read_text())
        parts += [f"inverse error {d['inverse_error']:.2g}",
                  f"{d['at_bounds']:.1%} of decoded actions at a bound"]
    return ", ".join(parts)


def read_ablations(ablations: Path, runs: Path) -> list[tuple]:
    """Each variant under ``ablations`` (``<variant>/<task>/<algorithm>/seed<N>/``, a ``source.json``
    per task) with the default's runs of the same task, algorithm and seeds under ``runs``: the
    arguments of :func:`ablation_section` but ``bins`` and ``params``, one tuple per algorithm."""
    found = []
    for variant in sorted(p for p in ablations.glob("*") if p.is_dir()):
        for folder in sorted(p for p in variant.glob("*") if (p / "source.json").is_file()):
            if (task := run_task(folder)) is None:
                continue
            ours, budget = read_task(folder, task)
            default = runs / folder.name
            theirs, default_budget = read_task(default, task) if default.is_dir() else ({}, 0)
            if default_budget != budget:
                raise Refused(f"{folder}: runs of {budget} steps against the default's "
                              f"{default_budget} in {default}; compare like with like")
            made = read_source(folder)
            for algo, variant_runs in ours.items():
                seeds = {c.seed for c in variant_runs}
                reference = [c for c in theirs.get(algo, []) if c.seed in seeds]
                if {c.seed for c in reference} != seeds:
                    raise Refused(f"{folder / algo}: the default's runs of seeds {sorted(seeds)} "
                                  f"are not all in {default / algo}; compare like with like")
                arms = {name: (curves, f"{source['commit'][:7]}; {embedding_figures(where) or '—'}")
                        for name, curves, where, source in (
                            ("default", reference, default, read_source(default)),
                            (variant.name, variant_runs, folder, made))}
                found.append((variant.name, task, algo, arms, budget, made))
    return found


def ablation_section(variant: str, task: str, algo: str, arms: dict[str, tuple[list[Curve], str]],
                     budget: int, made: dict, bins: int, params) -> str:
    """The default and one variant (``arms``: each one's runs, and its commit and embedding
    figures): final return, area and steps to each threshold with bootstrap intervals, and the
    bins where the two's intervals are disjoint."""
    rng = np.random.default_rng(params.report.seed)
    width = budget / bins
    thresholds = [float(t) for t in made.get("thresholds", [])]
    table, bands = summary_table("runs", "commit; embedding (held out)", arms, task,
                                 dict.fromkeys(arms, algo), thresholds, width, params, rng)
    lines = [f"### {variant}: {task}, {ALGO_STYLE[algo][0]}", "",
             f"{budget:,} steps a run, seeds {seed_list(arms[variant][0])} of each; the variant's "
             f"command `{made.get('command', '')}`; curves binned per {width:,.0f} steps.", "",
             *table, "",
             disjoint_bins(bands[variant], bands["default"], width, (variant, "the default"),
                           params.report.confidence)]
    return "\n".join(lines) + "\n"


def read_source(folder: Path) -> dict:
    """A task folder's ``source.json``: the commit and command that made its runs."""
    try:
        made = json.loads((folder / "source.json").read_text())
    except (OSError, ValueError):
        made = None
    if not isinstance(made, dict) or not isinstance(made.get("commit"), str):
        raise Refused(f"{folder / 'source.json'}: expected JSON naming the 'commit' that made "
                         "the runs beside it")
    return made


def run_task(folder: Path) -> str | None:
    """The task a folder's runs trained on, as their ``run.json`` names it; None with no runs."""
    for made in sorted(folder.glob("*/seed*/run.json")):
        try:
            return str(json.loads(made.read_text())["task"])
        except (ValueError, KeyError, TypeError):
            raise Refused(f"{made}: not a run record; expected JSON naming its 'task'") from None
    return None


def families_of(runs: Path, params) -> dict[str, list[str]]:
    """Each family's tasks: ``params.yaml``'s, in its order, then every task with a folder under
    ``runs`` that it does not train on, as its own family (as ``benchmarks/experiment.py`` runs
    such a task: its embedding learned on its own random data)."""
    families: dict[str, list[str]] = {}
    for task, family in params.runs.tasks.items():
        families.setdefault(family, []).append(task)
    known = {task_folder(t) for t in params.runs.tasks}
    for folder in sorted(p for p in runs.glob("*") if p.is_dir() and p.name not in known):
        if (task := run_task(folder)) is not None:
            families.setdefault(layout.own_family(task), []).append(task)
    return families


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=Path, default=REPO / "docs/results/runs")
    parser.add_argument("--figures", type=Path, default=REPO / "docs/results")
    parser.add_argument("--bins", type=int, default=20, help="bins per run's budget")
    parser.add_argument("--params", type=Path, default=REPO / "params.yaml")
    parser.add_argument("--ablations", type=Path, help="one folder per variant, each compared with "
                        "the default's runs in --runs [default: 'ablations' beside --runs]")
    args = parser.parse_args()
    args.ablations = args.ablations or args.runs.parent / "ablations"
    params = load_params(args.params)
    found_by_family: dict[str, dict[str, tuple]] = {}
    for family, tasks in families_of(args.runs, params).items():
        found = {}
        for task in tasks:
            folder = args.runs / task_folder(task)
            curves, budget = read_task(folder, task) if folder.is_dir() else ({}, 0)
            if curves:
                found[task] = (curves, budget, read_source(folder), embedding_figures(folder))
        if found:
            found_by_family[family] = found
    ablations = read_ablations(args.ablations, args.runs) if args.ablations.is_dir() else []
    # Every input is read and checked: from here on, print and draw.
    by_family: dict[str, dict[tuple[str, str], list[Curve]]] = {}
    for family, found in found_by_family.items():
        source = params.families[family].source if family in params.families else next(iter(found))
        for task, (curves, budget, made, embedding) in found.items():
            print(task_section(task, family, source, curves, budget, params.runs.budgets.get(task),
                               made, args.bins, params, embedding))
        figure = learning_curve_figure(
            family, list(found), {(t, a): c for t, (cs, *_) in found.items() for a, c in cs.items()},
            params.report.confidence, params.report.bootstrap_samples,
            np.random.default_rng(params.report.seed),
            {t: budget / args.bins for t, (_, budget, *_) in found.items()})
        args.figures.mkdir(parents=True, exist_ok=True)
        figure.savefig(args.figures / f"{family}.png", dpi=120)
        plt.close(figure)
        print(f"Figure: {args.figures / f'{family}.png'}\n")
        by_family[family] = {(t, a): c for t, (cs, *_) in found.items() for a, c in cs.items()}
    report = params.report
    both = {task for curves in by_family.values() for (task, _) in curves
            if all((task, a) in curves for a in ALGO_STYLE)}
    lows = {task: random_policy_return(task, RANDOM_EPISODES, report.seed) for task in sorted(both)}
    everything = {key: c for curves in by_family.values() for key, c in curves.items()}
    paper = {key: c for f, curves in by_family.items() if f in params.families
             for key, c in curves.items()}
    sets = [(f"the {family} family", curves) for family, curves in by_family.items()]
    if len(by_family) > len(set(by_family) & set(params.families)) > 1:
        sets.append(("the paper's tasks", paper))  # and tasks beyond it, in "every task"
    for title, curves in sets + [("every task", everything)] * (len(by_family) > 1):
        tasks, waiting = complete_tasks(curves, both)
        found = across_tasks_section(curves, {t: lows[t] for t in tasks}, report.confidence,
                                     report.bootstrap_samples, report.seed)
        if found is not None:
            print(across_section(title, found, params) + waiting)
            if title == "every task" or len(by_family) == 1:
                found.figure.savefig(args.figures / "performance-profile.png", dpi=120)
            plt.close(found.figure)
    for ablation in ablations:
        print(ablation_section(*ablation, args.bins, params))


if __name__ == "__main__":
    try:
        main()
    except (Refused, ParamsError) as error:
        print(f"error: {error}", file=sys.stderr)
        raise SystemExit(2) from None
