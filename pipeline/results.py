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

import json
import math
import re
from collections import Counter
from dataclasses import dataclass
from pathlib import Path

import click
import gymnasium
import numpy as np
from matplotlib.figure import Figure

from ede.atomic import writing_files
from ede.config import ALGO_LABELS, ALGOS, Params
from ede.figures import learning_curves, performance_profile
from ede.probes import RANDOM_EPISODES, ZERO_EPISODES, random_policy_return, zero_action_return
from ede.provenance import INSTRUCTION_SETS
from ede.results import SCORES, AcrossTasks, Arm, across_tasks, arm, disjoint, improvement_on_task
from ede.runs import Curve, Run, RunRejected, read_run, recorded_task, unshared_params
from ede.stats import Band
from ede_pipeline import layout
from ede_pipeline.common import BadInput, check_outputs, params_option

FIGURE_KIND = "results figure"  # what a figure's mark says drew it (ede.atomic.writing_files)


@dataclass(frozen=True)
class Part:
    """One entry of a task folder's ``source.json``: what made some of its runs."""

    commits: list[str]  # one, or several where its runs were made at several commits
    experiment: str | None  # the experiment file (``ede-pipeline experiment export`` names it)
    command: str | None  # the command line, in files written before experiment files
    thresholds: list[float]  # the returns whose first crossing to report
    seeds: list[int]  # the seeds it plans; none named: the runs there are all there are

    def made_at(self) -> str:
        """``commit 0123456``; ``experiment `experiments/NAME.yaml`, commits 0123456, 89abcde``."""
        commits = f"commit{'s' * (len(self.commits) > 1)} {', '.join(c[:7] for c in self.commits)}"
        return commits if self.experiment is None else f"experiment `{self.experiment}`, {commits}"

    def maker(self) -> str:
        """``experiment `experiments/NAME.yaml``` or ``command `…```."""
        return (
            f"experiment `{self.experiment}`"
            if self.experiment is not None
            else f"command `{self.command}`"
        )


@dataclass(frozen=True)
class Source:
    """A task folder's ``source.json``: what made its runs — one part, or one per set of its
    seeds where they came from several experiments — and what of them to report."""

    parts: list[Part]

    @property
    def seeds(self) -> list[int]:
        return sorted({seed for part in self.parts for seed in part.seeds})

    @property
    def thresholds(self) -> list[float]:
        return list(dict.fromkeys(t for part in self.parts for t in part.thresholds))

    def short_commits(self) -> list[str]:
        return list(dict.fromkeys(c[:7] for part in self.parts for c in part.commits))

    def made_at(self) -> str:
        """One part's :meth:`Part.made_at`; of several, each after its seeds."""
        return self._each(Part.made_at)

    def maker(self) -> str:
        return self._each(Part.maker)

    def _each(self, describe) -> str:
        if len(self.parts) == 1:
            return describe(self.parts[0])
        return "; ".join(f"{seeds_named(part.seeds)} by {describe(part)}" for part in self.parts)


@dataclass
class TaskRuns:
    """One task's finished runs as kept in its folder, read and checked."""

    task: str
    folder: Path
    curves: dict[str, list[Curve]]  # per algorithm, by seed
    budget: int  # the steps every run of the folder ran
    source: Source
    embedding: str | None  # the held-out figures of the embeddings EDE-TD3 used, where kept
    cpus: dict[str | None, int]  # runs per CPU (with its instruction sets); None: unrecorded


SEED_FOLDER = re.compile(r"seed(0|[1-9][0-9]*)")  # seed<N>, as layout.run names it


def published_runs(root: Path, task: str) -> list[tuple[Path, Run]]:
    """A task's finished runs under ``root`` (:func:`ede_pipeline.layout.run`), per algorithm by
    seed, each checked (:func:`ede.runs.read_run`: the task, algorithm and seed of its folder,
    its files those its ``run.json`` records). Every folder of an algorithm's is a run, named
    ``seed<N>`` as ``layout.run`` names it, so that no seed is read twice (``seed00`` beside
    ``seed0``); each run's ``run.json`` names its folder's seed."""
    found = []
    for algo in ALGOS:
        seeds = []
        for path in sorted(layout.run(task, algo, 0, root).parent.glob("*")):
            if not path.is_dir():
                continue
            if not SEED_FOLDER.fullmatch(path.name):
                raise BadInput(
                    f"{path}: not a run's folder name; expected seed<N>, N a whole number "
                    ">= 0 without leading zeros (seed0, seed12)"
                )
            seeds.append(int(path.name.removeprefix("seed")))
        for seed in sorted(seeds):
            run = layout.run(task, algo, seed, root)
            try:
                record = read_run(run, {"task": task, "algo": algo, "seed": seed})
            except RunRejected as error:
                raise BadInput(str(error)) from None
            if record is not None:
                found.append((run, record))
    return found


def read_folder(root: Path, task: str) -> TaskRuns | None:
    """A task's finished runs under ``root`` (:func:`published_runs`), made with the same params
    (:func:`ede.runs.unshared_params`), with its ``source.json`` and embedding figures; None
    where no run is finished."""
    folder = layout.task_runs(task, root)
    curves: dict[str, list[Curve]] = {}
    budgets: set[int] = set()
    cpus: Counter[str | None] = Counter()
    embeddings: dict[str, list[int]] = {}  # EDE-TD3's seeds by the embedding each used
    found = published_runs(root, task)
    if (difference := unshared_params([(run, record.made) for run, record in found])) is not None:
        raise BadInput(difference)
    for run, record in found:
        algo, seed = record.made["algo"], record.curve.seed
        curves.setdefault(algo, []).append(record.curve)
        budgets.add(int(record.curve.steps[-1]))  # checked: the run's budget
        cpus[cpu(run / "run.json", record.made)] += 1
        if algo == "ede-td3":
            embeddings.setdefault(str(record.made.get("embedding", "")), []).append(seed)
    if len(budgets) > 1:
        raise BadInput(f"{folder}: runs of different budgets {sorted(budgets)}; keep one per task")
    if not curves:
        return None
    return TaskRuns(
        task,
        folder,
        curves,
        budgets.pop(),
        read_source(folder),
        embedding_figures(root, task, embeddings),
        dict(cpus),
    )


def cpu(path: Path, made: dict) -> str | None:
    """The CPU that made a run, with the instruction sets of it that change results (its
    ``run.json``'s ``machine``, :func:`ede.provenance.machine`); None where unrecorded (runs made
    before run.json named its machine)."""
    machine = made.get("machine")
    if machine is None:
        return None
    model, sets = (
        (machine.get("cpu"), machine.get("instruction_sets"))
        if isinstance(machine, dict)
        else (None, None)
    )
    if (
        not isinstance(model, str)
        or not isinstance(sets, list)
        or not all(isinstance(s, str) for s in sets)
    ):
        raise BadInput(
            f"{path}: 'machine' is {machine!r}; expected its 'cpu' and "
            "'instruction_sets', as ede.provenance.machine records them"
        )
    return f"{model} ({', '.join(sets) or 'none of ' + ', '.join(INSTRUCTION_SETS)})"


def cpu_line(cpus: dict[str | None, int]) -> str:
    """``Runs made on: Intel(R) Xeon(R) Processor (avx2, avx512f): 8; CPU unrecorded: 8.``"""
    named = [f"{name}: {count}" for name, count in cpus.items() if name is not None]
    unrecorded = [f"CPU unrecorded: {cpus[None]}"] if None in cpus else []
    return f"Runs made on: {'; '.join(named + unrecorded)}."


def read_source(folder: Path) -> Source:
    """A task folder's ``source.json``: one object, or a list of them where its seeds came from
    several experiments, each naming the commit (or commits) and the experiment file (or, in files
    written before experiment files, the command) that made its runs, the returns whose first
    crossing to report, and the seeds it plans (no seed in two parts)."""
    path = folder / "source.json"
    try:
        made = json.loads(path.read_text())
    except (OSError, ValueError):
        raise BadInput(
            f"{path}: expected JSON naming the 'commit' that made the runs beside it "
            "(a string, or a list of them)"
        ) from None
    parts = [read_part(path, part) for part in (made if isinstance(made, list) else [made])]
    if not parts:
        raise BadInput(f"{path}: an empty list; expected what made the runs beside it")
    seeds = [seed for part in parts for seed in part.seeds]
    if len(seeds) != len(set(seeds)):
        twice = sorted({s for s in seeds if seeds.count(s) > 1})
        raise BadInput(
            f"{path}: seeds {twice} are named by two of its parts; expected each seed made by one"
        )
    return Source(parts)


def read_part(path: Path, made: object) -> Part:
    """One part of ``source.json`` (:func:`read_source`)."""
    commits = made.get("commit") if isinstance(made, dict) else None
    commits = [commits] if isinstance(commits, str) else commits
    if (
        not isinstance(made, dict)
        or not isinstance(commits, list)
        or not commits
        or not all(isinstance(c, str) for c in commits)
    ):
        raise BadInput(
            f"{path}: expected JSON naming the 'commit' that made the runs beside it "
            "(a string, or a list of them)"
        )
    experiment, command = made.get("experiment"), made.get("command")
    if not isinstance(experiment if "experiment" in made else command, str):
        raise BadInput(
            f"{path}: expected the 'experiment' file (or the 'command') that made the "
            "runs beside it, as a string"
        )
    thresholds = made.get("thresholds", [])
    if not isinstance(thresholds, list) or not all(
        isinstance(t, (int, float)) and not isinstance(t, bool) and math.isfinite(t)
        for t in thresholds
    ):
        raise BadInput(f"{path}: 'thresholds' is {thresholds!r}; expected a list of returns")
    seeds = made.get("seeds", [])
    if not isinstance(seeds, list) or not all(
        isinstance(s, int) and not isinstance(s, bool) and s >= 0 for s in seeds
    ):
        raise BadInput(
            f"{path}: 'seeds' is {seeds!r}; expected a list of seeds (whole numbers >= 0)"
        )
    return Part(commits, experiment, command, thresholds, seeds)


def embedding_figures(root: Path, task: str, embeddings: dict[str, list[int]]) -> str | None:
    """The held-out figures of the embeddings a task's EDE-TD3 runs used (``embeddings``: their
    seeds by the decoder's checksum each run.json names), where their metrics are kept beside
    them (:func:`ede_pipeline.layout.published_embedding`: ``{encoder,decoder}_metrics.json``, as
    ``pretrain`` writes them); of several, each after its seeds."""
    figures = {}
    for checksum, seeds in embeddings.items():
        kept = layout.published_embedding(task, checksum, root)
        encoder, decoder = (kept / f"{part}_metrics.json" for part in ("encoder", "decoder"))
        if not encoder.is_file():
            continue
        try:
            e = json.loads(encoder.read_text())
            parts = [f"prediction ratio {e['prediction_ratio']:.3f}", f"KL {e['kl']:.1f} nats"]
            if decoder.is_file():
                d = json.loads(decoder.read_text())
                parts += [
                    f"inverse error {d['inverse_error']:.2g}",
                    f"{d['at_bounds']:.1%} of decoded actions at a bound",
                ]
        except (OSError, ValueError, KeyError, TypeError):
            raise BadInput(
                f"{kept}: expected pretrain's metrics, prediction_ratio and kl of the "
                "encoder, inverse_error and at_bounds of the decoder"
            ) from None
        figures[seeds_named(sorted(seeds))] = ", ".join(parts)
    if len(figures) > 1:
        return "; ".join(f"{seeds}: {text}" for seeds, text in figures.items())
    return next(iter(figures.values()), None)


def run_task(folder: Path) -> str | None:
    """The task a folder's runs trained on, as their ``run.json`` names it; None with no runs."""
    for made in sorted(folder.glob("*/seed*/run.json")):
        try:
            return recorded_task(made.parent)
        except RunRejected as error:
            raise BadInput(str(error)) from None
    return None


def task_folders(root: Path) -> list[str]:
    """The tasks kept under ``root``, sorted: each folder holding a ``source.json`` and runs is
    one, its task its path under ``root`` (:func:`ede_pipeline.layout.task_runs`), which must be
    the task its runs name. (A folder of runs without its ``source.json`` is one too, so that
    :func:`read_source` names what is missing rather than its runs being passed over.)"""
    folders = {source.parent for source in root.rglob("source.json")}
    folders |= {
        made.parents[2]
        for made in root.rglob("seed*/run.json")
        if len(made.relative_to(root).parts) > 3
    }  # <task>/<algo>/seed<N>/run.json
    tasks = []
    for folder in sorted(folders):
        if (task := run_task(folder)) is None:
            continue
        if folder != (kept := layout.task_runs(task, root)):
            raise BadInput(f"{folder}: its runs are of {task}; keep them in {kept}/")
        tasks.append(task)
    return tasks


def read_runs(runs: Path, params) -> dict[str, list[TaskRuns]]:
    """Each family with finished runs, and its tasks': ``params.yaml``'s tasks in its order, then
    every other task kept under ``runs``, as its own family (as an experiment file runs
    such a task: its embedding learned on its own random data)."""
    kept = task_folders(runs) if runs.is_dir() else []
    tasks = {
        **{t: f for t, f in params.runs.tasks.items() if t in kept},
        **{t: layout.own_family(t, params.families) for t in kept if t not in params.runs.tasks},
    }
    families: dict[str, list[TaskRuns]] = {}
    for task, family in tasks.items():
        if found := read_folder(runs, task):
            families.setdefault(family, []).append(found)
    return families


def seed_list(seeds: list[int]) -> str:
    """``0–3`` for three or more consecutive seeds, else ``4, 6``."""
    if seeds == list(range(seeds[0], seeds[-1] + 1)) and len(seeds) > 2:
        return f"{seeds[0]}–{seeds[-1]}"
    return ", ".join(map(str, seeds))


def seeds_named(seeds: list[int]) -> str:
    """``seed 4``, ``seeds 0–3``."""
    return f"seed{'s' * (len(seeds) > 1)} {seed_list(seeds)}"


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


def read_ablations(ablations: Path, runs: Path) -> list[tuple[str, TaskRuns, TaskRuns]]:
    """Each variant under ``ablations`` (``<variant>/<task>/<algorithm>/seed<N>/``, a ``source.json``
    per task) with the default's runs of the same task under ``runs``, which must hold every seed
    of every algorithm the variant ran: (variant, its runs, the default's of those seeds)."""
    found = []
    for variant in sorted(p for p in ablations.glob("*") if p.is_dir()):
        if variant.name == "default":
            raise BadInput(
                f"{variant}: a variant named 'default' would be set against itself; rename it"
            )
        for task in task_folders(variant):
            if (ours := read_folder(variant, task)) is None:
                continue
            folder, default = layout.task_runs(task, variant), layout.task_runs(task, runs)
            theirs = read_folder(runs, task)
            if theirs is None:
                raise BadInput(
                    f"{folder}: no finished default runs of {task} in {default} to set it against"
                )
            if theirs.budget != ours.budget:
                raise BadInput(
                    f"{folder}: runs of {ours.budget} steps against the default's "
                    f"{theirs.budget} in {default}; compare like with like"
                )
            chosen = {}
            for algo, variant_runs in ours.curves.items():
                seeds = {c.seed for c in variant_runs}
                chosen[algo] = [c for c in theirs.curves.get(algo, []) if c.seed in seeds]
                if {c.seed for c in chosen[algo]} != seeds:
                    raise BadInput(
                        f"{folder / algo}: the default's runs of seeds {sorted(seeds)} "
                        f"are not all in {default / algo}; compare like with like"
                    )
            theirs.curves = chosen
            found.append((variant.name, ours, theirs))
    return found


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
