"""The report's numbers, computed from the runs read (:mod:`.inputs`) by the results model
(:mod:`ede.analysis.results`, as the results pages compute theirs) and the probes of Figures 6 and 7: each
family's rows and bands (and EDE-TD3 against each other algorithm and each other algorithm in
the EDE space against its raw counterpart, where the params name algorithms beyond the paper's
pair), the aggregates across tasks, the curves for ``dvc plots``, the DVC
metrics, and the clips of TD3 beside EDE-TD3."""

from __future__ import annotations

import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TypeVar

import numpy as np

from ede.analysis.policy import PolicyRejected
from ede.analysis.probes import random_policy_return
from ede.analysis.results import (
    RANDOM_EPISODES,
    SCORES,
    AcrossTasks,
    Arm,
    Comparison,
    across_tasks,
    arm,
    comparisons,
    fresh,
)
from ede.analysis.stats import Band, curve_band
from ede.analysis.video import NoOffscreenGL, fps_of, side_by_side, video_bytes
from ede.config import PAPER_ALGOS, Params
from ede.run.runs import Curve
from ede_pipeline import layout
from ede_pipeline.report.inputs import Inputs, Key, Runs

Row = tuple[str, Arm, list[int]]  # an algorithm, its statistics, its missing seeds
Probed = TypeVar("Probed")  # what a probe of an embedding finds (Figures 6 and 7)


@dataclass(frozen=True)
class Family:
    """A family's numbers: per task a row per algorithm and the algorithms set against each other
    (:func:`ede.analysis.results.comparisons`), and what its figures draw."""

    name: str
    tasks: list[str]
    rows: dict[str, list[Row]]  # per task
    compared: dict[str, list[Comparison]]  # per task; none where the params name only the pair
    bands: dict[Key, Band]
    counts: dict[Key, int]  # the runs averaged
    diagnostics: dict[Key, list[dict[str, np.ndarray]]]


@dataclass(frozen=True)
class Clip:
    """A task's clip of TD3 beside EDE-TD3: its MP4, or why there is none."""

    task: str
    seed: int | None  # None: no seed finished by both
    mp4: bytes | None = None
    why: str = ""  # where there is a seed but no MP4: the policy or the machine's refusal


@dataclass(frozen=True)
class Pictured:
    """A family's embedding pictured on its source task (Figures 6 and 7)."""

    family: str
    task: str
    k: int  # the embedding's sequence length


def width(params: Params, task: str) -> float:
    """The bins of a task's bands and leads: ``report.bin_steps``, else a twentieth of its
    budget."""
    return params.report.bin_steps or params.runs.budgets[task] / 20


def families(params: Params, runs: Runs) -> list[Family]:
    """Each family's statistics, per task and algorithm (:func:`ede.analysis.results.arm`), and
    where the params name algorithms beyond the paper's pair, per task EDE-TD3 against each other
    with runs there and each other algorithm in the EDE space against its raw counterpart
    (:func:`ede.analysis.results.comparisons`; the pair's report is the paper's, its claim the
    aggregates across tasks)."""
    config = params.report
    beyond = not set(params.runs.algos) <= set(PAPER_ALGOS)
    made = []
    for family, tasks in params.runs.by_family().items():
        rows: dict[str, list[Row]] = {}
        compared: dict[str, list[Comparison]] = {}
        bands: dict[Key, Band] = {}
        for task in tasks:
            for algo in params.runs.algos:
                found = runs.curves[(task, algo)]
                row = arm(found, config.thresholds.get(task, []), width(params, task), config)
                rows.setdefault(task, []).append((algo, row, runs.missing[(task, algo)]))
                if row.band is not None:
                    bands[(task, algo)] = row.band
            if beyond:
                curves: dict[str, list[Curve]] = {
                    algo: runs.curves[(task, algo)] for algo in params.runs.algos
                }
                compared[task] = comparisons(curves, width(params, task), config)
        keys: list[Key] = [(task, algo) for task in tasks for algo in params.runs.algos]
        counts = {key: len(runs.curves[key]) for key in keys}
        diagnostics = {key: runs.diagnostics[key] for key in keys if key in runs.diagnostics}
        made.append(Family(family, tasks, rows, compared, bands, counts, diagnostics))
    return made


def task_metrics(families: list[Family]) -> dict[str, Any]:
    """Per task and algorithm, the mean final return and area over its seeds, and how many."""
    return {
        task: {
            algo: {
                "final_return": None if row.final.n == 0 else row.final.mean,
                "auc": None if row.area.n == 0 else row.area.mean,
                "seeds": row.final.n,
            }
            for algo, row, _ in family.rows[task]
        }
        for family in families
        for task in family.tasks
    }


def curve_csv(
    task: str, algos: Sequence[str], curves: dict[Key, list[Curve]], params: Params
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


def across(params: Params, curves: dict[Key, list[Curve]]) -> AcrossTasks | None:
    """The claim across tasks, as rliable states it (:func:`ede.analysis.results.across_tasks`), each
    task's scores normalised from a random policy's return; None where no task has both
    algorithms' runs."""
    config = params.report
    lows = {
        task: random_policy_return(task, RANDOM_EPISODES, config.seed)
        for task in params.runs.all_tasks
        if curves.get((task, "td3")) and curves.get((task, "ede-td3"))
    }
    return across_tasks(curves, lows, config.confidence, config.bootstrap_samples, config.seed)


def across_metrics(found: AcrossTasks) -> dict[str, Any]:
    """The aggregates across tasks as DVC's metrics keep them (numbers only)."""
    summary: dict[str, Any] = {
        "tasks": found.tasks,
        "task_count": len(found.tasks),
        "runs_per_task": found.runs,
    }
    for score in SCORES:
        a = found.aggregates[score]
        summary[score] = {
            "probability_of_improvement": _as_json(a["probability_of_improvement"]),
            "iqm": {"ede-td3": _as_json(a["iqm_ours"]), "td3": _as_json(a["iqm_theirs"])},
        }
    return summary


def _as_json(interval: Any) -> dict[str, float]:
    return {"value": interval.mean, "low": interval.low, "high": interval.high}


def pictured(
    params: Params,
    inputs: Inputs,
    family: str | None,
    probe: Callable[..., Probed],  # (embedding, rng, env_id=task)
) -> tuple[Pictured, Probed] | None:
    """What ``probe`` finds of ``family``'s embedding on its source task, from a generator fresh
    from ``report.seed`` (Figure 6's :func:`ede.analysis.probes.effect_space`, Figure 7's
    :func:`ede.analysis.probes.exploration`); None where the family is null (the figure not drawn)."""
    if family is None:
        return None
    embedding, task = inputs.loaded[family], params.families[family].source
    return Pictured(family, task, embedding.k), probe(embedding, fresh(params.report), env_id=task)


def median_seed(ours: list[Curve], theirs: list[Curve]) -> int | None:
    """The seed both algorithms finished whose EDE-TD3 final return is the median (the lower of
    the two middle ones where their count is even); None where they share no seed."""
    shared = {c.seed for c in theirs}
    finals = sorted((float(c.returns[-1]), c.seed) for c in ours if c.seed in shared)
    return finals[(len(finals) - 1) // 2][1] if finals else None


def clips(params: Params, inputs: Inputs, curves: dict[Key, list[Curve]]) -> list[Clip]:
    """Per task, TD3 beside EDE-TD3 of its median seed, one episode each from the same start,
    as MP4 (:func:`ede.analysis.video.side_by_side`); a policy that cannot be played, or a machine
    without offscreen GL, is a clip's reason to be missing."""
    os.environ.setdefault("MUJOCO_GL", "egl")  # read as the first environment renders
    made = []
    for task in params.runs.all_tasks:
        seed = median_seed(curves.get((task, "ede-td3"), []), curves.get((task, "td3"), []))
        if seed is None:
            made.append(Clip(task, None))
            continue
        runs = [layout.run(task, algo, seed, inputs.runs) for algo in ("td3", "ede-td3")]
        family = params.runs.tasks[task]
        embedding = (
            (inputs.loaded[family], inputs.embedding_ids[family])
            if family in inputs.loaded
            else None
        )
        try:
            frames, _ = side_by_side(runs, embedding)
            data = video_bytes(frames, fps_of(task), Path(f"{clip_name(task)}.mp4"))
        except (PolicyRejected, NoOffscreenGL) as error:  # no policy, no GL: the page says so
            made.append(Clip(task, seed, why=str(error)))
            continue
        made.append(Clip(task, seed, data))
    return made


def clip_name(task: str) -> str:
    """A task's clip's name on the page (and its file's, with ``.mp4``)."""
    return f"clip-{task.replace('/', '_')}"
