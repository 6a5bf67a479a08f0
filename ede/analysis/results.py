"""The statistics of a set of runs: the one model that the report (``ede-pipeline report``) and
the results page (``ede-pipeline results``) render, each in its own way.

Per arm — an algorithm's runs on a task, or an ablation's variant's — the final return, the area
under the curve and the steps to each threshold, the binned band, and per seed whether it
declined or diverged and its last quarter (:func:`arm`); per task, EDE-TD3 set against each other
algorithm with runs there, and each other algorithm in the EDE space against the same learner on
raw actions (:func:`comparisons`): the probability that a run of the one beats one of the other's
(:func:`improvement_on_task`) and the one's lead, per bin and on the final return and the area,
each with its own interval (:func:`lead`); across tasks, rliable's aggregates of EDE-TD3 against
TD3 and the performance profile (:func:`across_tasks`).

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
    bootstrap_leads,
    bootstrap_mean,
    curve_band,
    divergence,
    global_numpy_seed,
    lead_band,
    normalised,
    steps_to_threshold,
)
from ede.analysis.stats import across_tasks as rliable_across_tasks
from ede.config import ALGO_LABELS, ALGOS, RAW_COUNTERPART, ReportConfig
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
    divergence: list[Divergence | None]  # per seed; None: too few evaluations to tell
    last_quarter: Interval | None  # the mean over seeds of each one's last quarter


def arm(
    curves: list[Curve], thresholds: Sequence[float], width: float, report: ReportConfig
) -> Arm:
    """An arm's statistics from its runs' curves, its band binned per ``width`` steps."""
    final = np.array([c.returns[-1] for c in curves])
    area = np.array([area_under_curve(c.steps, c.returns) for c in curves])
    rng = fresh(report)  # the final return's, then the area's: one generator, two draws
    final_interval = bootstrap_mean(final, report.confidence, report.bootstrap_samples, rng)
    area_interval = bootstrap_mean(area, report.confidence, report.bootstrap_samples, rng)
    late = [_divergence(c, report) for c in curves]
    tails = [d.last for d in late if d is not None]
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


def _divergence(curve: Curve, report: ReportConfig) -> Divergence | None:
    try:
        return divergence(curve.steps, curve.returns, report.confidence, report.seed)
    except ValueError:  # too few evaluations to have a last quarter and a window before it
        return None


@dataclass(frozen=True)
class Lead:
    """One arm's lead over another: the difference of their means over seeds, per bin of their
    binned curves and on the final return and the area, each with its bootstrap interval."""

    band: Band  # per bin: the lead, its interval's ends, the fewer of the two arms' seeds
    final: Interval
    area: Interval

    def bins(self) -> tuple[int, int, int]:
        """The bins where the lead's interval lies above 0, below 0, and of all."""
        return int((self.band.low > 0).sum()), int((self.band.high < 0).sum()), len(self.band.steps)


def lead(ours: list[Curve], theirs: list[Curve], width: float, report: ReportConfig) -> Lead | None:
    """The lead of ``ours`` over ``theirs`` (:func:`ede.analysis.stats.bootstrap_leads`), per bin
    of ``width`` steps and on each score, each from a generator of its own (:func:`fresh`); None
    where an arm has a single seed, whose interval would be the other's alone."""
    if min(len(ours), len(theirs)) < 2:
        return None
    confidence, samples = report.confidence, report.bootstrap_samples

    def overall(score: Callable[[Curve], float]) -> Interval:
        ours_scores, theirs_scores = (np.array([[score(c)] for c in cs]) for cs in (ours, theirs))
        return bootstrap_leads(ours_scores, theirs_scores, confidence, samples, fresh(report))[0]

    return Lead(
        lead_band(ours, theirs, width, confidence, samples, fresh(report)),
        overall(SCORE_OF["final_return"]),
        overall(SCORE_OF["auc"]),
    )


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
PAIRS: tuple[tuple[str, str], ...] = (
    *((OURS, algo) for algo in ALGOS if algo != OURS),
    *((algo, RAW_COUNTERPART[algo]) for algo in ALGOS if algo in RAW_COUNTERPART and algo != OURS),
)
"""The algorithms set against each other on a task, each pair's first against its second:
EDE-TD3 against every other algorithm, TD3 first (:data:`ede.config.ALGOS`' order), then every
other algorithm in the EDE space against the same learner on raw actions
(:data:`ede.config.RAW_COUNTERPART`): does the space help it as it helps TD3."""


@dataclass(frozen=True)
class Comparison:
    """One algorithm set against another on a task (a pair of :data:`PAIRS`): the probability
    that a run of the first beats one of the second's (per score, ``SCORES``), and the first's
    lead over the second (:func:`lead`)."""

    ours: str  # the algorithm set against the other
    against: str  # the other algorithm
    improvement: dict[str, Interval]  # P(ours > against), per score
    lead: Lead | None  # None where an arm has a single seed

    def bins(self) -> tuple[int, int, int] | None:
        """The bins where the lead's interval lies above 0, below 0, and of all; None where an
        arm has a single seed."""
        return None if self.lead is None else self.lead.bins()


def comparisons(
    curves: Mapping[str, list[Curve]], width: float, report: ReportConfig
) -> list[Comparison]:
    """Each pair of :data:`PAIRS` with runs of both on a task (``curves``, by algorithm; their
    bins ``width`` steps), in that order: EDE-TD3 against each other algorithm, TD3 first, then
    each other algorithm in the EDE space against its raw counterpart."""
    return [
        Comparison(
            ours,
            against,
            improvement_on_task(
                curves[ours],
                curves[against],
                report.confidence,
                report.bootstrap_samples,
                report.seed,
            ),
            lead(curves[ours], curves[against], width, report),
        )
        for ours, against in PAIRS
        if curves.get(ours) and curves.get(against)
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
