"""The report's content: learning curves and their statistics, and the paper's two pictures.

Everything here takes loaded data and returns numbers or matplotlib figures; reading files and
writing HTML is the pipeline's business.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field

import matplotlib

matplotlib.use("Agg")  # files only, never a display

import gymnasium
import matplotlib.pyplot as plt
import numpy as np
import torch
from matplotlib.figure import Figure

from ede.config import ALGO_LABELS, Algo
from ede.embedding import ActionEmbedding
from ede.runs import Curve
from ede.stats import (
    Interval,
    across_tasks,
    align_curves,
    area_under_curve,
    bin_curve,
    bootstrap_mean,
    bootstrap_means,
    global_numpy_seed,
    normalised,
    steps_to_threshold,
)
from ede.tasks import action_bounds, make, simulator
from ede.td3 import CodeExecutor, EmbeddingAdapter, IdentityAdapter
from ede.training import evaluate
from ede.vector import MemberEnvs

__all__ = [
    "ALGO_STYLE",
    "SCORES",
    "SCORE_OF",
    "AcrossTasks",
    "TaskRow",
    "across_tasks_section",
    "curve_band",
    "diagnostics_figure",
    "effect_space",
    "exploration",
    "improvement_on_task",
    "learning_curve_figure",
    "random_policy_return",
    "summarise_task",
    "zero_action_return",
]

ALGO_COLOURS: dict[Algo, str] = {"td3": "tab:blue", "ede-td3": "tab:red"}
ALGO_STYLE: dict[str, tuple[str, str]] = {  # label and colour, by algorithm name
    algo: (ALGO_LABELS[algo], colour) for algo, colour in ALGO_COLOURS.items()
}


@dataclass
class TaskRow:
    """One algorithm on one task: its statistics over seeds."""

    task: str
    algo: str
    final: Interval
    auc: Interval
    to_thresholds: dict[float, Interval]  # per threshold, the steps to reach it
    seeds: list[int] = field(default_factory=list)
    missing: list[int] = field(default_factory=list)


def summarise_task(
    task: str,
    algo: str,
    curves: list[Curve],
    missing: list[int],
    thresholds: Sequence[float],
    confidence: float,
    samples: int,
    rng: np.random.Generator,
) -> TaskRow:
    """Final return, area under the curve and the steps to each of ``thresholds``, with
    bootstrap intervals."""
    final = np.array([c.returns[-1] for c in curves])
    auc = np.array([area_under_curve(c.steps, c.returns) for c in curves])
    to_thresholds = {  # drawn first, as when there was one threshold at most
        t: bootstrap_mean(
            np.array([steps_to_threshold(c.steps, c.returns, t) for c in curves]),
            confidence,
            samples,
            rng,
        )
        for t in thresholds
    }
    final_interval = bootstrap_mean(final, confidence, samples, rng)
    auc_interval = bootstrap_mean(auc, confidence, samples, rng)
    return TaskRow(
        task=task,
        algo=algo,
        final=final_interval,
        auc=auc_interval,
        to_thresholds=to_thresholds,
        seeds=[c.seed for c in curves],
        missing=missing,
    )


def curve_band(
    curves: list[Curve],
    confidence: float,
    samples: int,
    rng: np.random.Generator,
    bin_steps: float | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Mean over seeds with a bootstrap band at every evaluated step, or every bin.

    With ``bin_steps``, each run's evaluations are first averaged per bin (:func:`bin_curve`), so
    the points are the bins' right edges, as in the paper's figures. Runs of unequal length count
    where they have data; ``n`` says how many seeds each point has.

    Returns:
        steps, mean, low, high, n — each (T,).
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
    return steps, mean, low, high, n


def _panels_width(panels: int) -> float:
    """Inches for a row of task panels: 4.2 each, and never too narrow for the two-line title
    (a family of one task, as "Your own task" makes, would cut it off)."""
    return max(4.2 * panels, 6.4)


def learning_curve_figure(
    family: str,
    tasks: list[str],
    curves: dict[tuple[str, str], list[Curve]],
    confidence: float,
    samples: int,
    rng: np.random.Generator | None,
    bin_steps: float | Mapping[str, float] | None = None,
    bands: Mapping[tuple[str, str], tuple] | None = None,
    title: str | None = None,
) -> Figure:
    """One panel per task of a family: each algorithm's mean return with its bootstrap band.

    With ``bin_steps`` the curves are binned as the paper's figures (:func:`curve_band`); a
    mapping gives each task its own width, named in its panel's title. ``bands`` gives each
    (task, algorithm)'s band as :func:`curve_band` returned it, drawn as it is (so a figure shows
    the intervals its tables were read from); the others are computed with ``rng``. ``title``
    replaces "<family> family" atop the figure.
    """
    figure, axes = plt.subplots(
        1, len(tasks), figsize=(_panels_width(len(tasks)), 3.4), squeeze=False
    )
    per_task = isinstance(bin_steps, Mapping)
    for ax, task in zip(axes[0], tasks, strict=True):
        width = bin_steps.get(task) if isinstance(bin_steps, Mapping) else bin_steps
        for algo, (label, colour) in ALGO_STYLE.items():
            runs = curves.get((task, algo), [])
            if not runs:
                continue
            band = (bands or {}).get((task, algo))
            if band is None:
                assert rng is not None, "a band to compute needs rng"
                band = curve_band(runs, confidence, samples, rng, width)
            steps, mean, low, high, _ = band
            ax.plot(steps, mean, color=colour, label=f"{label} ({len(runs)} seeds)")
            ax.fill_between(steps, low, high, color=colour, alpha=0.2, linewidth=0)
        ax.set_title(
            f"{task}\nbins of {width:,.0f} steps" if per_task and width else task,
            fontsize=10 if per_task else None,
        )
        ax.set_xlabel("environment steps")
        ax.grid(alpha=0.3)
        if ax.lines:
            ax.legend(fontsize=8)
        else:
            ax.text(0.5, 0.5, "no finished runs", ha="center", va="center", transform=ax.transAxes)
    axes[0][0].set_ylabel("evaluation return")
    binned = (
        "evaluations averaged per bin, "
        if per_task
        else f"evaluations averaged per {bin_steps:,} steps, "
        if bin_steps
        else ""
    )
    figure.suptitle(
        f"{title or f'{family} family'}\n{binned}mean over seeds, "
        f"{100 * confidence:.0f}% bootstrap band",
        fontsize=10,
    )
    figure.tight_layout()
    return figure


def diagnostics_figure(
    family: str, tasks: list[str], runs: dict[tuple[str, str], list[dict[str, np.ndarray]]]
) -> Figure:
    """Per task, the mean over seeds of Q(s, μ(s)) (top) and of the critic loss (bottom, log)."""
    figure, axes = plt.subplots(
        2, len(tasks), figsize=(_panels_width(len(tasks)), 4.6), squeeze=False, sharex="col"
    )
    for column, task in enumerate(tasks):
        for algo, (label, colour) in ALGO_STYLE.items():
            found = runs.get((task, algo), [])
            if not found:
                continue
            for row, name in enumerate(("mean_q", "critic_loss")):
                steps, table = align_curves([(d["step"], d[name]) for d in found])
                axes[row][column].plot(
                    steps,
                    np.nanmean(table, axis=0),
                    color=colour,
                    label=f"{label} ({len(found)} seeds)",
                )
        axes[0][column].set_title(task)
        axes[1][column].set_yscale("log")
        axes[1][column].set_xlabel("environment steps")
        for ax in axes[:, column]:
            ax.grid(alpha=0.3)
        if axes[0][column].lines:
            axes[0][column].legend(fontsize=8)
    axes[0][0].set_ylabel("mean Q(s, μ(s))")
    axes[1][0].set_ylabel("critic loss")
    figure.suptitle(
        f"{family} family: training diagnostics\nmean over seeds per evaluation interval",
        fontsize=10,
    )
    figure.tight_layout()
    return figure


def _position_colours(xy: np.ndarray) -> np.ndarray:
    """A 2-D colour map: red grows with x, green with y (each scaled to the data's range)."""
    lo, hi = xy.min(axis=0), xy.max(axis=0)
    unit = (xy - lo) / np.where(hi > lo, hi - lo, 1.0)
    return np.stack([unit[:, 0], unit[:, 1], 1.0 - 0.5 * (unit[:, 0] + unit[:, 1])], axis=1)


@dataclass
class EffectSpace:
    effects: np.ndarray  # (N, 2) s[t+k] - s[t]
    codes: np.ndarray  # (N, 2) whitened E(a)
    r_squared: float  # of the best affine map effect -> code
    figure: Figure


def effect_space(
    embedding: ActionEmbedding,
    rng: np.random.Generator,
    sequences: int = 2000,
    env_id: str = "ede/Point-v0",
) -> EffectSpace:
    """Figure 6: effects of random k-step sequences beside their codes, same colours.

    Each sequence is stepped from a fresh reset of ``env_id``; its effect is the change of the
    first two state coordinates (the position). The affine fit z ≈ A·effect + b is reported as
    its R² over both code dimensions.
    """
    env = make(env_id)
    data = simulator(env).data  # the simulator's state: the same object through every reset
    k = embedding.k
    low, high = action_bounds(env)
    actions = rng.uniform(low, high, size=(sequences, k, len(low))).astype(np.float32)
    effects = np.zeros((sequences, 2))
    for n in range(sequences):
        env.reset(seed=int(rng.integers(2**31)))
        start = data.qpos[:2].copy()
        for action in actions[n]:
            env.step(action)
        effects[n] = data.qpos[:2] - start
    env.close()
    with torch.no_grad():
        codes = embedding.encode(torch.as_tensor(actions, device=embedding.device)).cpu().numpy()
    design = np.hstack([effects, np.ones((sequences, 1))])
    coefficients, *_ = np.linalg.lstsq(design, codes[:, :2], rcond=None)
    residual = codes[:, :2] - design @ coefficients
    r_squared = 1 - residual.var(axis=0).sum() / codes[:, :2].var(axis=0).sum()

    colours = _position_colours(effects)
    figure, (left, right) = plt.subplots(1, 2, figsize=(8.4, 4))
    left.scatter(effects[:, 0], effects[:, 1], c=colours, s=6)
    left.set(title=f"effect s[t+{k}] − s[t]", xlabel="Δx", ylabel="Δy", aspect="equal")
    right.scatter(codes[:, 0], codes[:, 1], c=colours, s=6)
    right.set(
        title=f"EDE space E(a)  (affine fit R² = {r_squared:.3f})",
        xlabel="z₁",
        ylabel="z₂",
        aspect="equal",
    )
    figure.tight_layout()
    return EffectSpace(effects, codes, float(r_squared), figure)


@dataclass
class Exploration:
    raw_positions: list[np.ndarray]  # per episode, (T, 2)
    ede_positions: list[np.ndarray]
    raw_coverage: float  # fraction of the arena's grid cells visited
    ede_coverage: float
    figure: Figure


def _coverage(positions: list[np.ndarray], half_width: float, cells: int) -> float:
    xy = np.concatenate(positions)
    index = np.clip(((xy + half_width) / (2 * half_width) * cells).astype(int), 0, cells - 1)
    return len({(i, j) for i, j in index}) / cells**2


def exploration(
    embedding: ActionEmbedding,
    rng: np.random.Generator,
    episodes: int = 10,
    env_id: str = "ede/PointMass-v0",
    half_width: float = 1.0,
    cells: int = 20,
) -> Exploration:
    """Figure 7: positions over ``episodes`` episodes of uniform random raw actions, and of
    uniform random EDE codes (in [−bound, bound]^D) chosen every k steps and decoded — executed
    as training executes codes (:class:`ede.td3.CodeExecutor`; raw actions are codes with k = 1).

    Coverage is the fraction of a ``cells`` × ``cells`` grid over the arena
    ([−half_width, half_width]²) that the positions visit.
    """
    env = make(env_id)
    data = simulator(env).data  # the simulator's state: the same object through every reset
    low, high = action_bounds(env)
    seeds = rng.integers(2**31, size=episodes)
    device = embedding.device

    def uniform_action(obs: np.ndarray, _: np.ndarray) -> torch.Tensor:  # (1, O) -> (1, A)
        return torch.as_tensor(rng.uniform(low, high).astype(np.float32), device=device)[None]

    def uniform_code(obs: np.ndarray, _: np.ndarray) -> torch.Tensor:  # (1, O) -> (1, D)
        z = rng.uniform(-embedding.bound, embedding.bound, size=embedding.dim)  # (D,)
        return torch.as_tensor(z, dtype=torch.float32, device=device)[None]

    envs = MemberEnvs([lambda: env])  # the one environment, as training steps its members'
    one = np.ones(1, dtype=bool)

    def rollout(
        executor: CodeExecutor, policy: Callable[[np.ndarray, np.ndarray], torch.Tensor]
    ) -> list[np.ndarray]:  # per episode, (T, 2) positions
        return [
            np.array([data.qpos[:2].copy() for _ in executor.episodes(policy, 1, [seed], one)])
            for seed in seeds
        ]

    raw = rollout(CodeExecutor(envs, IdentityAdapter(low, high, device)), uniform_action)
    ede = rollout(CodeExecutor(envs, EmbeddingAdapter(embedding)), uniform_code)
    env.close()
    raw_cov, ede_cov = _coverage(raw, half_width, cells), _coverage(ede, half_width, cells)
    figure, axes = plt.subplots(1, 2, figsize=(8.4, 4.2))
    for ax, paths, title in (
        (axes[0], raw, f"uniform random actions ({100 * raw_cov:.1f}% covered)"),
        (axes[1], ede, f"uniform random EDE actions ({100 * ede_cov:.1f}% covered)"),
    ):
        for path in paths:
            ax.plot(path[:, 0], path[:, 1], linewidth=1)
        ax.set(
            xlim=(-half_width, half_width),
            ylim=(-half_width, half_width),
            aspect="equal",
            title=title,
        )
        ax.set_xticks([])
        ax.set_yticks([])
    figure.tight_layout()
    return Exploration(raw, ede, raw_cov, ede_cov, figure)


RANDOM_EPISODES = 10  # episodes of uniform random actions behind a task's normalised 0


def random_policy_return(task: str, episodes: int, seed: int) -> float:
    """The mean return of uniform random actions on ``task`` over ``episodes`` episodes, episode e
    from ``reset(seed=seed + e)``: the low end of a task's normalised scores."""
    rng = np.random.default_rng(seed)
    return float(
        np.mean(
            _episode_returns(task, episodes, seed, lambda space: rng.uniform(space.low, space.high))
        )
    )


def zero_action_return(task: str, episodes: int, seed: int) -> tuple[float, float]:
    """The mean return, and its standard error, of the action nearest zero on ``task`` (idle
    actuators: on a task with an action penalty, the return of doing nothing) over ``episodes``
    episodes, episode e from ``reset(seed=seed + e)``. A policy below it has learned nothing the
    task rewards beyond sparing its actions."""
    returns = _episode_returns(
        task, episodes, seed, lambda space: np.clip(0.0, space.low, space.high)
    )
    return float(np.mean(returns)), float(np.std(returns, ddof=1) / np.sqrt(episodes))


def _episode_returns(
    task: str, episodes: int, seed: int, act: Callable[[gymnasium.spaces.Box], np.ndarray]
) -> np.ndarray:
    """Each episode's return on ``task`` with ``act(action_space)`` as the policy, by the
    evaluation's own loop (:func:`ede.training.evaluate`)."""
    env = make(task)
    try:
        space = env.action_space
        assert isinstance(space, gymnasium.spaces.Box)
        adapter = IdentityAdapter(space.low, space.high, torch.device("cpu"))
        returns = evaluate(
            MemberEnvs([lambda: env]),
            lambda obs: torch.as_tensor(np.asarray(act(space), space.dtype))[None],
            adapter,
            episodes,
            [seed],
        )
        return returns[0]
    finally:
        env.close()


# The scores the aggregates are over: each one's key in ``AcrossTasks.aggregates`` and its name,
# and how each is read off a run's curve.
SCORES = {"final_return": "final return", "auc": "area under the curve"}
SCORE_OF: dict[str, Callable[[Curve], float]] = {
    "final_return": lambda c: float(c.returns[-1]),
    "auc": lambda c: area_under_curve(c.steps, c.returns),
}


def improvement_on_task(
    ours: list[Curve], theirs: list[Curve], confidence: float, samples: int, seed: int
) -> dict[str, Interval]:
    """rliable's probability that a run of ``ours`` beats a run of ``theirs`` on one task, per
    score (``SCORES``), with its bootstrap interval over all the task's runs of each (the two may
    have different numbers): the aggregates' evidence, for a task alone."""

    def column(curves: list[Curve], score: Callable[[Curve], float]) -> np.ndarray:  # (runs, 1)
        return np.array([[score(c)] for c in curves])

    return {
        name: across_tasks(column(ours, score), column(theirs, score), confidence, samples, seed)[
            "probability_of_improvement"
        ]
        for name, score in SCORE_OF.items()
    }


@dataclass
class AcrossTasks:
    """rliable's aggregates of EDE-TD3 against TD3 over every task with runs of both."""

    tasks: list[str]
    runs: dict[str, int]  # per algorithm: the runs of each task behind the aggregates
    left_out: list[str]  # tasks and seeds that are not in them, each with why
    aggregates: dict[str, dict[str, Interval]]  # per score ("final_return", "auc"): across_tasks'
    figure: Figure

    def describe(self, confidence: float, samples: int) -> str:
        """What the aggregates are over and how they were made, in one paragraph."""
        tasks = f"{len(self.tasks)} task{'s' * (len(self.tasks) != 1)}"
        runs = " and ".join(f"{n} of {ALGO_STYLE[a][0]}" for a, n in self.runs.items())
        left_out = f" Left out: {'; '.join(self.left_out)}." if self.left_out else ""
        return (
            f"{tasks} ({', '.join(self.tasks)}); per task {runs} (each task's lowest seeds, as "
            "many as every task has). Computed with rliable (Agarwal et al., 2021): stratified "
            f"bootstrap intervals ({100 * confidence:.0f}%, {samples} resamples). Scores are "
            f"normalised per task: 0 is uniform random actions' mean return ({RANDOM_EPISODES} "
            f"episodes), 1 the best evaluation any run reached there.{left_out}"
        )


def across_tasks_section(
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
                    f"{task} {ALGO_STYLE[algo][0]} seed"
                    f"{'s' * (len(ordered) > count + 1)} "
                    f"{', '.join(str(c.seed) for c in ordered[count:])}"
                )
    low, high = np.array([lows[t] for t in tasks]), np.array([highs[t] for t in tasks])

    def table(algo: str, score: Callable[[Curve], float]) -> np.ndarray:  # (runs, tasks)
        return np.array([[score(c) for c in chosen[(t, algo)]] for t in tasks]).T

    aggregates = {}
    normalised_final = {}
    for name, score in SCORE_OF.items():
        ede, td3 = (normalised(table(a, score), low, high) for a in algos)
        aggregates[name] = across_tasks(ede, td3, confidence, samples, seed)
        if name == "final_return":
            normalised_final = {"td3": td3, "ede-td3": ede}
    thresholds = np.linspace(0.0, 1.0, 41)
    with global_numpy_seed(seed):
        profiles, bands = rly.create_performance_profile(
            normalised_final, thresholds, reps=samples, confidence_interval_size=confidence
        )
    figure, ax = plt.subplots(figsize=(5.0, 3.4))
    for algo, (label, colour) in ALGO_STYLE.items():
        ax.plot(thresholds, profiles[algo], color=colour, label=label)
        ax.fill_between(
            thresholds, bands[algo][0], bands[algo][1], color=colour, alpha=0.2, linewidth=0
        )
    runs = {a: len(chosen[(tasks[0], a)]) for a in algos}
    ax.set_xlabel("normalised final return τ")
    ax.set_ylabel("fraction of runs with score > τ")
    each = (
        f"{runs['td3']} runs of each"
        if runs["td3"] == runs["ede-td3"]
        else f"{runs['ede-td3']} runs of EDE-TD3 and {runs['td3']} of TD3 each"
    )
    ax.set_title(
        f"performance profile: {len(tasks)} task{'s' * (len(tasks) != 1)}, {each}", fontsize=10
    )
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    figure.tight_layout()
    return AcrossTasks(tasks, runs, left_out, aggregates, figure)
