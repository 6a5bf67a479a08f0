"""The published runs on disk, read and checked for ``ede-pipeline results``: each task's folder
(its runs, per algorithm by seed, and its ``source.json``, one part per experiment that made
runs there), the CPUs that made them, its embeddings' held-out figures, and the fidelity
ablations beside the default's runs (the layout: :mod:`ede_pipeline.results`' docstring).
Every problem is one line (:class:`ede_pipeline.common.BadInput`)."""

from __future__ import annotations

import json
import math
import re
from collections import Counter
from dataclasses import dataclass
from pathlib import Path

from ede.config import ALGOS
from ede.io.provenance import INSTRUCTION_SETS
from ede.run.runs import Curve, Run, RunRejected, read_run, recorded_task, same_files
from ede.run.spec import unshared_params
from ede_pipeline import layout
from ede_pipeline.common import BadInput


def seed_list(seeds: list[int]) -> str:
    """``0–3`` for three or more consecutive seeds, else ``4, 6``."""
    if seeds == list(range(seeds[0], seeds[-1] + 1)) and len(seeds) > 2:
        return f"{seeds[0]}–{seeds[-1]}"
    return ", ".join(map(str, seeds))


def seeds_named(seeds: list[int]) -> str:
    """``seed 4``, ``seeds 0–3``."""
    return f"seed{'s' * (len(seeds) > 1)} {seed_list(seeds)}"


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
    runs: list[tuple[Path, Run]]  # each run's folder and what was read of it


SEED_FOLDER = re.compile(r"seed(0|[1-9][0-9]*)")  # seed<N>, as layout.run names it


def published_runs(root: Path, task: str) -> list[tuple[Path, Run]]:
    """A task's finished runs under ``root`` (:func:`ede_pipeline.layout.run`), per algorithm by
    seed, each checked as a published run (:func:`ede.run.runs.read_run`: the task, algorithm and
    seed of its folder, its files those its ``run.json`` records). Every folder holding runs is an
    algorithm's (:data:`ede.config.ALGOS`), so that no run is passed over unread (``sb3-td3``
    for ``sb3-td3-ede``); every folder of an algorithm's is a run, named ``seed<N>`` as ``layout.run`` names it, so that no seed is read
    twice (``seed00`` beside ``seed0``); each run's ``run.json`` names its folder's seed, a seed
    its task's ``source.json`` names; and no two runs are one (:func:`ede.run.runs.same_files`: a
    copy of a run is refused whatever its folder and its ``run.json`` say)."""
    found = []
    for run in sorted(layout.task_runs(task, root).glob("*/seed*")):
        if run.parent.name not in ALGOS:
            raise BadInput(
                f"{run.parent}: runs of no algorithm known here; expected a folder per "
                f"algorithm, named one of {', '.join(ALGOS)}"
            )
    for algo in ALGOS:  # every algorithm a task has runs of, in ALGOS' order: TD3's first
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
                record = read_run(run, {"task": task, "algo": algo, "seed": seed}, published=True)
            except RunRejected as error:
                raise BadInput(str(error)) from None
            if record is not None:
                found.append((run, record))
    if (copy := same_files(found)) is not None:
        raise BadInput(copy)
    if found:
        folder = layout.task_runs(task, root)
        named = read_source(folder).seeds
        for run, record in found:
            if record.curve.seed not in named:
                raise BadInput(
                    f"{run}: a run of seed {record.curve.seed}, which {folder / 'source.json'} "
                    f"does not name (it names {seed_list(named) if named else 'none'}); a "
                    "task's runs are the seeds its experiments made, as each export names them"
                )
    return found


def read_folder(root: Path, task: str) -> TaskRuns | None:
    """A task's finished runs under ``root`` (:func:`published_runs`), made with the same params
    (:func:`ede.run.spec.unshared_params`), with its ``source.json`` and embedding figures; None
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
        found,
    )


def cpu(path: Path, made: dict) -> str | None:
    """The CPU that made a run, with the instruction sets of it that change results (its
    ``run.json``'s ``machine``, :func:`ede.io.provenance.machine`); None where unrecorded (runs made
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
            "'instruction_sets', as ede.io.provenance.machine records them"
        )
    return f"{model} ({', '.join(sets) or 'none of ' + ', '.join(INSTRUCTION_SETS)})"


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
    such a task: its embedding learned on its own random data). No run is another task's too
    (:func:`ede.run.runs.same_files`)."""
    kept = task_folders(runs) if runs.is_dir() else []
    tasks = {
        **{t: f for t, f in params.runs.tasks.items() if t in kept},
        **{t: layout.own_family(t, params.families) for t in kept if t not in params.runs.tasks},
    }
    families: dict[str, list[TaskRuns]] = {}
    for task, family in tasks.items():
        if found := read_folder(runs, task):
            families.setdefault(family, []).append(found)
    every = [run for found in families.values() for task_runs in found for run in task_runs.runs]
    if (copy := same_files(every)) is not None:  # one task's run copied as another's
        raise BadInput(copy)
    return families


def read_ablations(ablations: Path, runs: Path) -> list[tuple[str, TaskRuns, TaskRuns]]:
    """Each variant under ``ablations`` (``<variant>/<task>/<algorithm>/seed<N>/``, a ``source.json``
    per task) with the default's runs of the same task under ``runs``, which must hold every seed
    of every algorithm the variant ran: (variant, its runs, the default's of those seeds); no run
    of a variant is the default's or another variant's (:func:`ede.run.runs.same_files`)."""
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
    every = [run for _, ours, theirs in found for run in (*theirs.runs, *ours.runs)]
    if (copy := same_files(every)) is not None:  # a variant's run that is the default's
        raise BadInput(copy)
    return found
