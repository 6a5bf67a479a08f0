"""The statistics of learning curves: area under the curve, steps to a threshold, bootstrap."""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from typing import TYPE_CHECKING, NamedTuple

import numpy as np

if TYPE_CHECKING:
    from ede.run.runs import Curve

__all__ = [
    "Divergence",
    "Interval",
    "across_tasks",
    "align_curves",
    "bin_curve",
    "bootstrap_leads",
    "bootstrap_mean",
    "bootstrap_means",
    "divergence",
    "evaluation_noise",
    "global_numpy_seed",
    "lead_band",
    "normalised",
    "steps_to_threshold",
]


def steps_to_threshold(steps: np.ndarray, returns: np.ndarray, threshold: float) -> float:
    """The first evaluated step whose return reaches ``threshold``; ``inf`` if none does."""
    reached = np.flatnonzero(np.asarray(returns) >= threshold)
    return float(np.asarray(steps)[reached[0]]) if reached.size else float("inf")


@dataclass(frozen=True)
class Interval:
    """A mean with its bootstrap confidence interval, over ``n`` seeds."""

    mean: float
    low: float
    high: float
    n: int

    def __str__(self) -> str:
        """``mean [low, high]``; ``inf`` (a threshold never reached) reads "never"."""
        return self._show("{:.4g}")

    def steps(self) -> str:
        """The same for a number of environment steps: whole steps with thousands separators,
        ``12,000 [9,000, 15,600]``."""
        return self._show("{:,.0f}")

    def _show(self, form: str) -> str:
        if self.n == 0:
            return "missing"

        def show(value: float) -> str:
            return "never" if np.isinf(value) else form.format(value)

        return f"{show(self.mean)} [{show(self.low)}, {show(self.high)}]"


def bootstrap_mean(
    values: np.ndarray, confidence: float, samples: int, rng: np.random.Generator
) -> Interval:
    """Percentile bootstrap interval of the mean of ``values`` (one per seed): rliable's
    stratified bootstrap of one task (:func:`bootstrap_means`)."""
    values = np.asarray(values, dtype=float)
    return bootstrap_means(values[:, None], confidence, samples, rng)[0]


def bootstrap_means(
    table: np.ndarray, confidence: float, samples: int, rng: np.random.Generator
) -> list[Interval]:
    """The mean of each column of ``table`` (runs, points), with its percentile bootstrap interval.

    The runs are resampled within each column, independently (rliable's stratified bootstrap, the
    points as its strata), ``samples`` times; NumPy's global generator, which rliable draws from,
    is seeded from ``rng`` for the call.

    Infinite values (a seed that never reached a threshold) make every resample that draws them
    infinite, so the interval is honest about them: an end is ``inf`` as soon as the percentile
    falls among such resamples. rliable's percentiles interpolate, and ``inf - inf`` is NaN, so
    they are given a finite stand-in far above every finite mean and read back as ``inf``.
    ``-inf`` has no such meaning and is refused; NaN gives NaN.
    """
    from rliable import library as rly

    table = np.asarray(table, dtype=float)
    if np.isneginf(table).any():
        raise ValueError("a value of -inf: only +inf (never reached) has a meaning here")
    runs, points = table.shape
    if runs == 0:
        return [Interval(float("nan"), float("nan"), float("nan"), 0)] * points
    finite = table[np.isfinite(table)]
    ceiling = float(np.abs(finite).max()) if finite.size else 0.0
    stand_in = np.finfo(float).max / (2 * runs)  # n of them sum to half the largest double
    scores = np.where(np.isposinf(table), stand_in, table)
    with global_numpy_seed(int(rng.integers(2**32))):
        _, band = rly.get_interval_estimates(
            {"mean": scores},
            lambda s: s.mean(axis=0),
            reps=samples,
            confidence_interval_size=confidence,
        )
    low, high = np.where(band["mean"] > ceiling, np.inf, band["mean"])  # (points,) each
    means = table.mean(axis=0)
    return [
        Interval(float(m), float(lo), float(hi), runs)
        for m, lo, hi in zip(means, low, high, strict=True)
    ]


def bin_curve(
    steps: np.ndarray, returns: np.ndarray, width: float
) -> tuple[np.ndarray, np.ndarray]:
    """One run's evaluations averaged in bins of ``width`` steps, as the authors' figures were.

    Bins are right-closed — ``((b - 1)·width, b·width]`` — and the first one also holds step 0
    (the untrained policy), as pandas' ``cut`` makes them in the authors' ``rl_plots.ipynb``.

    Returns:
        each non-empty bin's right edge ``b·width`` and the mean return of its evaluations.
    """
    steps, returns = np.asarray(steps, dtype=float), np.asarray(returns, dtype=float)
    bins = np.maximum(np.ceil(steps / width), 1).astype(np.int64)  # (T,) bin of each evaluation
    edges, where = np.unique(bins, return_inverse=True)
    means = np.bincount(where, weights=returns) / np.bincount(where)
    return edges * float(width), means


def align_curves(curves: list[tuple[np.ndarray, np.ndarray]]) -> tuple[np.ndarray, np.ndarray]:
    """Put curves of possibly unequal length on the union of their steps.

    Returns:
        steps (T,) and returns (N, T) with NaN where a curve has no evaluation at that step.
    """
    steps = np.unique(np.concatenate([s for s, _ in curves])) if curves else np.zeros(0)
    table = np.full((len(curves), len(steps)), np.nan)
    for row, (s, r) in enumerate(curves):
        table[row, np.searchsorted(steps, s)] = r
    return steps, table


class Band(NamedTuple):
    """A mean curve over seeds with its bootstrap band, each (T,): at ``steps``, the ``mean``,
    the interval's ``low`` and ``high`` ends, and ``n``, the seeds with data there."""

    steps: np.ndarray
    mean: np.ndarray
    low: np.ndarray
    high: np.ndarray
    n: np.ndarray


def curve_band(
    curves: list[Curve],
    confidence: float,
    samples: int,
    rng: np.random.Generator,
    bin_steps: float | None = None,
) -> Band:
    """Mean over seeds with a bootstrap band at every evaluated step, or every bin.

    With ``bin_steps``, each run's evaluations are first averaged per bin (:func:`bin_curve`), so
    the points are the bins' right edges, as in the paper's figures. Runs of unequal length count
    where they have data; ``n`` says how many seeds each point has.

    """
    pairs = [(c.steps, c.returns) for c in curves]
    if bin_steps is not None:
        pairs = [bin_curve(s, r, bin_steps) for s, r in pairs]
    steps, table = align_curves(pairs)
    mean, low, high, n = (np.full(len(steps), np.nan) for _ in range(4))
    # One bootstrap per set of seeds that have data: all of them, unless runs are unequal.
    present = ~np.isnan(table)  # (N, T)
    for seeds in np.unique(present, axis=1).T:
        points = np.flatnonzero((present == seeds[:, None]).all(axis=0))
        intervals = bootstrap_means(table[np.ix_(seeds, points)], confidence, samples, rng)
        for t, interval in zip(points, intervals, strict=True):
            mean[t], low[t], high[t], n[t] = interval.mean, interval.low, interval.high, interval.n
    return Band(steps, mean, low, high, n)


def bootstrap_leads(
    ours: np.ndarray, theirs: np.ndarray, confidence: float, samples: int, rng: np.random.Generator
) -> list[Interval]:
    """The lead of ``ours`` over ``theirs`` at each point — the difference of their means over
    seeds — with its percentile bootstrap interval.

    Args:
        ours: one arm's values (runs, points).
        theirs: the other's (runs, points), at the same points, any number of runs.
        confidence: the interval's coverage.
        samples: how many resamples: each draws each arm's runs independently, with replacement.
        rng: the generator the resamples draw from.

    Returns:
        per point the lead, its interval, and the fewer of the two arms' runs as its ``n``.
    """
    ours, theirs = np.asarray(ours, dtype=float), np.asarray(theirs, dtype=float)
    drawn_ours = rng.integers(len(ours), size=(samples, len(ours)))  # (samples, runs)
    drawn_theirs = rng.integers(len(theirs), size=(samples, len(theirs)))
    resampled = ours[drawn_ours].mean(axis=1) - theirs[drawn_theirs].mean(axis=1)  # (samples, P)
    tail = 50 * (1 - confidence)
    low, high = np.percentile(resampled, [tail, 100 - tail], axis=0)  # (P,) each
    lead = ours.mean(axis=0) - theirs.mean(axis=0)
    n = min(len(ours), len(theirs))
    return [
        Interval(float(m), float(lo), float(hi), n)
        for m, lo, hi in zip(lead, low, high, strict=True)
    ]


def lead_band(
    ours: list[Curve],
    theirs: list[Curve],
    width: float,
    confidence: float,
    samples: int,
    rng: np.random.Generator,
) -> Band:
    """The lead of one arm's binned mean curve over another's, per bin, with its bootstrap band
    (:func:`bootstrap_leads`): each run binned per ``width`` steps (:func:`bin_curve`), the two
    arms' runs aligned on the union of their bins (:func:`align_curves`). A bin where a run has
    no evaluation has no lead (NaN, ``n`` 0)."""
    pairs = [bin_curve(c.steps, c.returns, width) for c in (*ours, *theirs)]
    steps, table = align_curves(pairs)  # (N, T): ours' runs, then theirs'
    mean, low, high = (np.full(len(steps), np.nan) for _ in range(3))
    n = np.zeros(len(steps))
    complete = ~np.isnan(table).any(axis=0)
    found = bootstrap_leads(
        table[: len(ours), complete], table[len(ours) :, complete], confidence, samples, rng
    )
    for t, lead in zip(np.flatnonzero(complete), found, strict=True):
        mean[t], low[t], high[t], n[t] = lead.mean, lead.low, lead.high, lead.n
    return Band(steps, mean, low, high, n)


@dataclass(frozen=True)
class Divergence:
    """Whether one run's late level fell below its earlier best, on its evaluations themselves.

    ``first`` is the untrained policy's return (the evaluation at step 0); ``best`` the highest
    mean of as many consecutive evaluations as the last quarter has, all before it, over the steps
    ``best_span``; ``last`` the last quarter's mean; ``noise`` how far ``best - last`` reaches on a
    plateau by the run's own noise alone, at the report's confidence (:func:`divergence`).
    """

    first: float
    best: float
    best_span: tuple[float, float]
    last: float
    noise: float
    declined: bool
    diverged: bool

    @property
    def decline(self) -> float:
        """How far the last quarter lies below the best window before it."""
        return self.best - self.last


def evaluation_noise(returns: np.ndarray) -> float:
    """The standard deviation σ of one evaluation about the run's level, from its successive
    differences: ``sqrt(mean(diff(returns)²) / 2)``; a slow trend between evaluations adds little."""
    return float(np.sqrt(np.mean(np.diff(np.asarray(returns, dtype=float)) ** 2) / 2))


def lag_one_correlation(returns: np.ndarray) -> float:
    """The correlation of successive evaluations about their straight-line trend, in [0, 0.95]: a
    policy that changes a little between evaluations keeps some of its luck (TD3's on Pusher:
    0.5 to 0.8); the trend removed, a steady rise or fall does not count as luck kept."""
    y = np.asarray(returns, dtype=float)
    t = np.arange(len(y), dtype=float)
    x = y - np.polyval(np.polyfit(t, y, 1), t) if len(y) > 2 else y - y.mean()
    scale = float(np.dot(x, x))
    return float(np.clip(np.dot(x[:-1], x[1:]) / scale, 0.0, 0.95)) if scale > 0 else 0.0


def window_means(values: np.ndarray, n: int) -> np.ndarray:
    """The means of every ``n`` consecutive values along the last axis: ``(..., T)`` to
    ``(..., T - n + 1)``."""
    sums = np.cumsum(np.asarray(values, dtype=float), axis=-1)
    zero = np.zeros((*sums.shape[:-1], 1))
    return (sums[..., n - 1 :] - np.concatenate([zero, sums[..., :-n]], axis=-1)) / n


def plateau_decline(
    before: int, n: int, sigma: float, rho: float, confidence: float, seed: int, draws: int = 1000
) -> float:
    """How far a run on a plateau falls by its noise alone, by the rule of :func:`divergence`: the
    ``confidence`` quantile of B − L over ``draws`` runs of ``before + n`` evaluations whose
    noise is stationary with standard deviation ``sigma`` and lag-one correlation ``rho`` (an
    AR(1) process). Simulated, since the best of many overlapping windows is not one mean."""
    rng = np.random.default_rng(seed)
    shocks = rng.standard_normal((draws, before + n)) * sigma * np.sqrt(1 - rho**2)
    noise = np.empty_like(shocks)
    noise[:, 0] = rng.standard_normal(draws) * sigma
    for t in range(1, before + n):
        noise[:, t] = rho * noise[:, t - 1] + shocks[:, t]
    falls = window_means(noise[:, :before], n).max(axis=1) - noise[:, before:].mean(axis=1)
    return float(np.quantile(falls, confidence))


def divergence(
    steps: np.ndarray,
    returns: np.ndarray,
    confidence: float,
    seed: int,
    drop_fraction: float = 0.5,
) -> Divergence:
    """Did the run decline, or diverge, by its own evaluations (no bins)?

    The last quarter holds the ``n`` evaluations after ¾ of the last evaluated step; ``last`` is
    their mean L. ``best`` B is the highest mean of ``n`` consecutive evaluations all before the
    last quarter (a window as long as it, so like is set against like); ``first`` F the step-0
    evaluation. The run declined where ``B - L`` is more than a run on a plateau reaches by its
    noise alone in ``confidence`` of the cases (:func:`plateau_decline`, with its last quarter's
    lag-one correlation ρ, :func:`lag_one_correlation`, and the σ its successive differences give,
    :func:`evaluation_noise`, over sqrt(1 − ρ); drawn from ``seed``). It diverged where it declined and lost
    more than ``drop_fraction`` of what it had gained, ``B - L > drop_fraction·(B - F)``; a run
    whose gain is within that noise never learned and cannot diverge. A dip that recovers
    within the last quarter lowers L by part of it.

    Raises:
        ValueError: fewer than ``2n + 1`` evaluations, where a window as long as the last quarter
            cannot lie before it without the untrained policy's.
    """
    steps, returns = np.asarray(steps, dtype=float), np.asarray(returns, dtype=float)
    late = steps > 0.75 * steps[-1]
    n = int(late.sum())
    before = returns[~late]
    if n == 0 or len(before) < n + 1:
        raise ValueError(
            f"{len(steps)} evaluations, {n} in the last quarter: too few to set it against a "
            "window as long before it"
        )
    windows = window_means(before, n)  # (len(before) - n + 1,)
    start = int(np.argmax(windows))
    best, last, first = float(windows[start]), float(returns[late].mean()), float(returns[0])
    # Successive differences see σ·sqrt(2(1 − ρ)) of correlated noise: σ itself is larger.
    rho = lag_one_correlation(returns[late])
    sigma = evaluation_noise(returns) / np.sqrt(1 - rho)
    noise = plateau_decline(len(before), n, sigma, rho, confidence, seed)
    declined = bool(best - last > noise)
    gained = best - first
    return Divergence(
        first,
        best,
        (float(steps[start]), float(steps[start + n - 1])),
        last,
        noise,
        declined,
        declined and bool(gained > noise and best - last > drop_fraction * gained),
    )


# Across tasks: rliable's aggregates (Agarwal et al., 2021) --------------------------------------


def normalised(scores: np.ndarray, low: np.ndarray, high: np.ndarray) -> np.ndarray:
    """Scores (runs, tasks) mapped per task so that ``low`` is 0 and ``high`` is 1; a task whose
    ``high`` is not above its ``low`` has no scale and is refused."""
    low, high = np.asarray(low, dtype=float), np.asarray(high, dtype=float)
    if np.any(~(high > low)):
        raise ValueError(f"tasks {np.flatnonzero(~(high > low)).tolist()}: high not above low")
    return (np.asarray(scores, dtype=float) - low) / (high - low)


@contextmanager
def global_numpy_seed(seed: int) -> Iterator[None]:
    """NumPy's global generator seeded for the block, then put back as it was: rliable's
    stratified bootstrap draws its runs from it, whatever its ``random_state`` says."""
    saved = np.random.get_state()
    np.random.seed(seed)
    try:
        yield
    finally:
        np.random.set_state(saved)


def across_tasks(
    ours: np.ndarray, theirs: np.ndarray, confidence: float, samples: int, seed: int
) -> dict[str, Interval]:
    """rliable's aggregates of two methods' scores, each (runs, tasks) with runs stratified by
    task (the two may have different numbers of runs): the probability that a run of ``ours``
    beats one of ``theirs`` on a task, averaged over tasks, and each method's interquartile mean,
    all with stratified bootstrap intervals.

    Returns:
        ``probability_of_improvement``, ``iqm_ours``, ``iqm_theirs``; each interval's ``n`` is the
        runs per task behind it (the pair's: the fewer of the two).
    """
    from rliable import library as rly
    from rliable import metrics

    ours, theirs = np.asarray(ours, dtype=float), np.asarray(theirs, dtype=float)
    if (
        ours.ndim != 2
        or theirs.ndim != 2
        or ours.shape[1] != theirs.shape[1]
        or min(*ours.shape, *theirs.shape) == 0
    ):
        raise ValueError(
            f"scores of shapes {ours.shape} and {theirs.shape}: expected (runs, tasks) "
            "each, over the same tasks, at least one of each"
        )
    kwargs = {"reps": samples, "confidence_interval_size": confidence}
    with global_numpy_seed(seed):
        point, band = rly.get_interval_estimates(
            {"pair": (ours, theirs)}, metrics.probability_of_improvement, **kwargs
        )
        low, high = np.ravel(band["pair"])
        found = {
            "probability_of_improvement": Interval(
                float(point["pair"]), float(low), float(high), min(len(ours), len(theirs))
            )
        }
        point, band = rly.get_interval_estimates(
            {"ours": ours, "theirs": theirs},
            lambda s: np.array([metrics.aggregate_iqm(s)]),
            **kwargs,
        )
    for name, scores in (("ours", ours), ("theirs", theirs)):
        found[f"iqm_{name}"] = Interval(
            float(point[name][0]), float(band[name][0, 0]), float(band[name][1, 0]), len(scores)
        )
    return found
