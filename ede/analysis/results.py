"""The statistics of a set of runs: the one model that the report (``ede-pipeline report``) and
the results page (``ede-pipeline results``) render, each in its own way.

Per arm — an algorithm's runs on a task, or an ablation's variant's — the final return, the area
under the curve and the steps to each threshold, the binned band, and per seed whether it
diverged and its last quarter (:func:`arm`); per task, EDE-TD3 set against each other algorithm
with runs there (:func:`comparisons`): the probability that an EDE-TD3 run beats one of the other's
(:func:`improvement_on_task`) and the bins where their intervals are disjoint (:func:`disjoint`);
across tasks, rliable's aggregates of EDE-TD3 against TD3 and the performance profile
(:func:`across_tasks`).

Every interval is a percentile bootstrap over seeds at ``report.confidence`` with
``report.bootstrap_samples`` resamples (``params.yaml``'s ``report``). The one generator rule:
every statistic draws from a generator fresh from ``report.seed`` (:func:`fresh`), so a number
depends on its own runs alone, never on which tasks or statistics came before it; rliable's
comparisons seed NumPy's global generator with ``report.seed`` itself.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from ede.analysis.stats import (
    Band,
    Divergence,
    Interval,
    bootstrap_mean,
    curve_band,
    divergence,
    global_numpy_seed,
    normalised,
    separation,
    steps_to_threshold,
)
from ede.analysis.stats import across_tasks as rliable_across_tasks
from ede.config import ALGO_LABELS, ALGOS, ReportConfig
from ede.run.runs import Curve, area_under_curve

RANDOM_EPISODES = 10  # episodes of uniform random actions behind a task's normalised 0

# The scores compared across tasks: each one's key in ``AcrossTasks.aggregates`` and its name,
# and how each is read off a run's curve.
SCORES = {"final_return": "final return", "auc": "area under the curve"}
SCORE_OF: dict[str, Callable[[Curve], float]] = {
    "final_return": lambda c: float(c.returns[-1]),
    "auc": lambda c: area_under_curve(c.steps, c.returns),
}


def fresh(report: ReportConfig) -> np.random.Generator:
    """The generator a statistic draws from: afresh from the report's seed, every time."""
    return np.random.default_rng(report.seed)


def interval(values: np.ndarray, report: ReportConfig) -> Interval:
    """The mean of ``values`` (one per seed) with its bootstrap interval."""
    return bootstrap_mean(values, report.confidence, report.bootstrap_samples, fresh(report))


# Per arm -----------------------------------------------------------------------------------


@dataclass(frozen=True)
class Arm:
    """One arm's statistics over its seeds (all empty where it has no runs)."""

    seeds: list[int]
    final: Interval
    area: Interval
    to_thresholds: dict[float, Interval]  # per threshold, the steps to reach it
    band: Band | None  # the mean curve over seeds, binned, with its bootstrap band
    divergence: list[Divergence | None]  # per seed; None: too few bins to tell
    last_quarter: Interval | None  # the mean over seeds of each one's last quarter


def arm(
    curves: list[Curve], thresholds: Sequence[float], width: float, report: ReportConfig
) -> Arm:
    """An arm's statistics from its runs' curves, binned per ``width`` steps."""
    final = np.array([c.returns[-1] for c in curves])
    area = np.array([area_under_curve(c.steps, c.returns) for c in curves])
    rng = fresh(report)  # the final return's, then the area's: one generator, two draws
    final_interval = bootstrap_mean(final, report.confidence, report.bootstrap_samples, rng)
    area_interval = bootstrap_mean(area, report.confidence, report.bootstrap_samples, rng)
    late = [_divergence(c, width) for c in curves]
    tails = [d.tail for d in late if d is not None]
    return Arm(
        seeds=[c.seed for c in curves],
        final=final_interval,
        area=area_interval,
        to_thresholds={
            t: interval(
                np.array([steps_to_threshold(c.steps, c.returns, t) for c in curves]), report
            )
            for t in thresholds
        },
        band=(
            curve_band(curves, report.confidence, report.bootstrap_samples, fresh(report), width)
            if curves
            else None
        ),
        divergence=late,
        last_quarter=interval(np.array(tails), report)
        if curves and len(tails) == len(late)
        else None,
    )


def _divergence(curve: Curve, width: float) -> Divergence | None:
    try:
        return divergence(curve.steps, curve.returns, width)
    except ValueError:  # too few bins to have a tail and bins before it
        return None


def disjoint(ours: Arm, theirs: Arm) -> np.ndarray | None:
    """Per bin of ``ours``' band, +1 where its interval lies wholly above ``theirs``', -1 wholly
    below, 0 where they overlap; None where an arm has a single seed (its interval a point)."""
    if min(len(ours.seeds), len(theirs.seeds)) < 2 or ours.band is None or theirs.band is None:
        return None
    return separation(ours.band.low, ours.band.high, theirs.band.low, theirs.band.high)


def improvement_on_task(
    ours: list[Curve], theirs: list[Curve], confidence: float, samples: int, seed: int
) -> dict[str, Interval]:
    """rliable's probability that a run of ``ours`` beats a run of ``theirs`` on one task, per
    score (``SCORES``), with its bootstrap interval over all the task's runs of each (the two may
    have different numbers): the aggregates' evidence, for a task alone."""

    def column(curves: list[Curve], score: Callable[[Curve], float]) -> np.ndarray:  # (runs, 1)
        return np.array([[score(c)] for c in curves])

    return {
        name: rliable_across_tasks(
            column(ours, score), column(theirs, score), confidence, samples, seed
        )["probability_of_improvement"]
        for name, score in SCORE_OF.items()
    }


OURS = "ede-td3"  # the algorithm every other is set against, task by task


@dataclass(frozen=True)
class Comparison:
    """EDE-TD3 set against one other algorithm on a task: the arm it is compared with, the
    probability that an EDE-TD3 run beats one of the arm's (per score, ``SCORES``), and per bin
    of EDE-TD3's band whether their intervals are disjoint (:func:`disjoint`)."""

    against: str  # the other algorithm
    improvement: dict[str, Interval]  # P(EDE-TD3 > the arm), per score
    disjoint: np.ndarray | None  # +1, -1 or 0 per bin; None where an arm has a single seed

    def bins(self) -> tuple[int, int, int] | None:
        """The bins where EDE-TD3's interval lies wholly above the other's, wholly below, and of
        all; None where an arm has a single seed."""
        sign = self.disjoint
        if sign is None:
            return None
        return int((sign > 0).sum()), int((sign < 0).sum()), len(sign)


def comparisons(
    curves: Mapping[str, list[Curve]], arms: Mapping[str, Arm], report: ReportConfig
) -> list[Comparison]:
    """EDE-TD3 set against each other algorithm with runs on a task (``curves`` and their
    statistics ``arms``, by algorithm), in :data:`ede.config.ALGOS`' order, TD3 first; none
    where EDE-TD3 has no runs there."""
    if not curves.get(OURS):
        return []
    return [
        Comparison(
            algo,
            improvement_on_task(
                curves[OURS],
                curves[algo],
                report.confidence,
                report.bootstrap_samples,
                report.seed,
            ),
            disjoint(arms[OURS], arms[algo]),
        )
        for algo in ALGOS
        if algo != OURS and curves.get(algo)
    ]


# Across tasks ------------------------------------------------------------------------------


@dataclass(frozen=True)
class Profile:
    """rliable's performance profile: per algorithm, the fraction of runs whose normalised final
    return exceeds each threshold τ, and its band."""

    thresholds: np.ndarray  # (T,)
    fractions: dict[str, np.ndarray]  # per algorithm, (T,)
    bands: dict[str, np.ndarray]  # per algorithm, (2, T): low, high


@dataclass(frozen=True)
class AcrossTasks:
    """rliable's aggregates of EDE-TD3 against TD3 over every task with runs of both."""

    tasks: list[str]
    runs: dict[str, int]  # per algorithm: the runs of each task behind the aggregates
    left_out: list[str]  # tasks and seeds that are not in them, each with why
    aggregates: dict[str, dict[str, Interval]]  # per score ("final_return", "auc")
    profile: Profile

    def describe(self, confidence: float, samples: int) -> str:
        """What the aggregates are over and how they were made, in one paragraph."""
        tasks = f"{len(self.tasks)} task{'s' * (len(self.tasks) != 1)}"
        runs = " and ".join(f"{n} of {ALGO_LABELS[a]}" for a, n in self.runs.items())
        left_out = f" Left out: {'; '.join(self.left_out)}." if self.left_out else ""
        return (
            f"{tasks} ({', '.join(self.tasks)}); per task {runs} (each task's lowest seeds, as "
            "many as every task has). Computed with rliable (Agarwal et al., 2021): stratified "
            f"bootstrap intervals ({100 * confidence:.0f}%, {samples} resamples). Scores are "
            f"normalised per task: 0 is uniform random actions' mean return ({RANDOM_EPISODES} "
            f"episodes), 1 the best evaluation any run reached there.{left_out}"
        )


def across_tasks(
    curves: dict[tuple[str, str], list[Curve]],
    lows: dict[str, float],
    confidence: float,
    samples: int,
    seed: int,
) -> AcrossTasks | None:
    """Probability of improvement and IQM over final returns and areas under the curve, scores
    normalised per task between ``lows[task]`` (a random policy's return) and the best evaluation
    any run reached there; and the performance profile of the normalised final returns.

    rliable stratifies by task and so needs the same number of runs of an algorithm on every
    task: each algorithm keeps each task's lowest seeds, as many as its fewest on any task, and
    the seeds beyond are named in ``left_out``. So is a task whose best evaluation is not above
    the random policy's return, which has no scale to normalise by. None where no task is left.
    """
    from rliable import library as rly

    algos = ("ede-td3", "td3")
    left_out = []
    tasks = [t for t in lows if all(curves.get((t, a)) for a in algos)]
    highs = {t: max(float(c.returns.max()) for a in algos for c in curves[(t, a)]) for t in tasks}
    for task in [t for t in tasks if highs[t] <= lows[t]]:
        left_out.append(
            f"{task} (its best evaluation, {highs[task]:.4g}, is not above the random "
            f"policy's {lows[task]:.4g})"
        )
        tasks.remove(task)
    if not tasks:
        return None
    chosen = {}
    for algo in algos:
        count = min(len(curves[(t, algo)]) for t in tasks)
        for task in tasks:
            ordered = sorted(curves[(task, algo)], key=lambda c: c.seed)
            chosen[(task, algo)] = ordered[:count]
            if ordered[count:]:
                left_out.append(
                    f"{task} {ALGO_LABELS[algo]} seed{'s' * (len(ordered) > count + 1)} "
                    f"{', '.join(str(c.seed) for c in ordered[count:])}"
                )
    low, high = np.array([lows[t] for t in tasks]), np.array([highs[t] for t in tasks])

    def table(algo: str, score: Callable[[Curve], float]) -> np.ndarray:  # (runs, tasks)
        return np.array([[score(c) for c in chosen[(t, algo)]] for t in tasks]).T

    aggregates = {}
    normalised_final = {}
    for name, score in SCORE_OF.items():
        ede, td3 = (normalised(table(a, score), low, high) for a in algos)
        aggregates[name] = rliable_across_tasks(ede, td3, confidence, samples, seed)
        if name == "final_return":
            normalised_final = {"td3": td3, "ede-td3": ede}
    thresholds = np.linspace(0.0, 1.0, 41)
    with global_numpy_seed(seed):
        fractions, bands = rly.create_performance_profile(
            normalised_final, thresholds, reps=samples, confidence_interval_size=confidence
        )
    runs = {a: len(chosen[(tasks[0], a)]) for a in algos}
    return AcrossTasks(tasks, runs, left_out, aggregates, Profile(thresholds, fractions, bands))
