"""The figures of the report and the results page, drawn from numbers computed elsewhere
(:mod:`ede.analysis.results`, :mod:`ede.analysis.probes`): learning curves with their bands, training diagnostics,
the paper's Figures 6 and 7, and the performance profile across tasks.

Each function returns a matplotlib :class:`~matplotlib.figure.Figure` with an Agg canvas of its
own — files only, through matplotlib's object API: no pyplot, so no backend to choose and no
figure to close; ``figure.savefig`` writes it.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from ede.analysis.probes import EffectSpace, Exploration
from ede.analysis.results import Profile
from ede.analysis.stats import Band, align_curves
from ede.config import ALGO_LABELS, Algo

ALGO_COLOURS: dict[Algo, str] = {  # the paper's pair as the paper draws them, then SB3's agents
    "td3": "tab:blue",
    "ede-td3": "tab:red",
    "sb3-td3-ede": "tab:purple",
    "sb3-sac-ede": "tab:green",
    "sb3-sac": "tab:olive",
}
ALGO_STYLE: dict[str, tuple[str, str]] = {  # label and colour, by algorithm name
    algo: (ALGO_LABELS[algo], colour) for algo, colour in ALGO_COLOURS.items()
}


def _figure(width: float, height: float) -> Figure:
    figure = Figure(figsize=(width, height))
    FigureCanvasAgg(figure)  # attaches itself: savefig and draw render with Agg
    return figure


def _panels_width(panels: int) -> float:
    """Inches for a row of task panels: 4.2 each, and never too narrow for the two-line title
    (a family of one task, as "Your own task" makes, would cut it off)."""
    return max(4.2 * panels, 6.4)


def learning_curves(
    family: str,
    tasks: list[str],
    bands: Mapping[tuple[str, str], Band],
    seeds: Mapping[tuple[str, str], int],
    confidence: float,
    bin_steps: float | Mapping[str, float] | None = None,
    title: str | None = None,
) -> Figure:
    """One panel per task of a family: each algorithm's mean return with its bootstrap band.

    ``bands`` and ``seeds``: each (task, algorithm)'s band and its number of seeds (a pair
    missing: no finished runs). ``bin_steps``: the bands' bin width, one for all (named in the
    title) or one per task (named in its panel's). ``title`` replaces "<family> family" atop.
    """
    figure = _figure(_panels_width(len(tasks)), 3.4)
    axes = figure.subplots(1, len(tasks), squeeze=False)
    per_task = isinstance(bin_steps, Mapping)
    for ax, task in zip(axes[0], tasks, strict=True):
        width = bin_steps.get(task) if isinstance(bin_steps, Mapping) else bin_steps
        for algo, (label, colour) in ALGO_STYLE.items():
            band = bands.get((task, algo))
            if band is None:
                continue
            ax.plot(
                band.steps, band.mean, color=colour, label=f"{label} ({seeds[(task, algo)]} seeds)"
            )
            ax.fill_between(band.steps, band.low, band.high, color=colour, alpha=0.2, linewidth=0)
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


def diagnostics(
    family: str, tasks: list[str], runs: dict[tuple[str, str], list[dict[str, np.ndarray]]]
) -> Figure:
    """Per task, the mean over seeds of Q(s, μ(s)) (top) and of the critic loss (bottom, log)."""
    figure = _figure(_panels_width(len(tasks)), 4.6)
    axes = figure.subplots(2, len(tasks), squeeze=False, sharex="col")
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


def effect_space(space: EffectSpace) -> Figure:
    """Figure 6: effects of random k-step sequences (left) beside their codes (right), each
    sequence the same colour in both, by its effect."""
    effects, codes, k, r_squared = space.effects, space.codes, space.k, space.r_squared
    colours = _position_colours(effects)
    figure = _figure(8.4, 4)
    left, right = figure.subplots(1, 2)
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
    return figure


def exploration(explored: Exploration) -> Figure:
    """Figure 7: the positions of each episode of uniform random raw actions (left) and of
    uniform random EDE codes (right), over the arena."""
    half_width = explored.half_width
    figure = _figure(8.4, 4.2)
    axes = figure.subplots(1, 2)
    for ax, paths, title in (
        (
            axes[0],
            explored.raw_positions,
            f"uniform random actions ({100 * explored.raw_coverage:.1f}% covered)",
        ),
        (
            axes[1],
            explored.ede_positions,
            f"uniform random EDE actions ({100 * explored.ede_coverage:.1f}% covered)",
        ),
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
    return figure


def performance_profile(profile: Profile, tasks: int, runs: dict[str, int]) -> Figure:
    """The fraction of runs whose normalised final return exceeds each τ, per algorithm, with
    its band; ``tasks`` and ``runs`` (per algorithm, of each task) as the title says."""
    figure = _figure(5.0, 3.4)
    ax = figure.subplots()
    for algo, (label, colour) in ALGO_STYLE.items():
        if algo not in profile.fractions:  # the aggregates' pair alone
            continue
        ax.plot(profile.thresholds, profile.fractions[algo], color=colour, label=label)
        low, high = profile.bands[algo]
        ax.fill_between(profile.thresholds, low, high, color=colour, alpha=0.2, linewidth=0)
    ax.set_xlabel("normalised final return τ")
    ax.set_ylabel("fraction of runs with score > τ")
    each = (
        f"{runs['td3']} runs of each"
        if runs["td3"] == runs["ede-td3"]
        else f"{runs['ede-td3']} runs of EDE-TD3 and {runs['td3']} of TD3 each"
    )
    ax.set_title(f"performance profile: {tasks} task{'s' * (tasks != 1)}, {each}", fontsize=10)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    figure.tight_layout()
    return figure
