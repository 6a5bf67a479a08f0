"""The report's per-family figures keep their titles inside the picture, whatever the family's size."""

from __future__ import annotations

import numpy as np
import pytest
from matplotlib.figure import Figure
from matplotlib.text import Text

from ede.report import Curve, diagnostics_figure, learning_curve_figure

STEPS = np.arange(1_000, 11_000, 1_000, dtype=float)


def cut_off(figure: Figure) -> list[str]:
    """Every title, axis label and legend entry reaching past the figure's edges (tick labels
    are left out: matplotlib keeps labels of ticks outside the view, which it does not draw)."""
    figure.canvas.draw()
    renderer = figure.canvas.get_renderer()
    ticks = {id(label) for ax in figure.axes for axis in (ax.xaxis, ax.yaxis)
             for tick in axis.get_major_ticks() + axis.get_minor_ticks()
             for label in (tick.label1, tick.label2)}
    outside = []
    for text in figure.findobj(Text):
        if text.get_visible() and text.get_text() and id(text) not in ticks:
            box = text.get_window_extent(renderer)
            if box.x0 < 0 or box.x1 > figure.bbox.width or box.y0 < 0 or box.y1 > figure.bbox.height:
                outside.append(text.get_text())
    return outside


@pytest.mark.parametrize(
    "tasks", [["HalfCheetah-v5"], ["ede/ReacherVertical-v0", "ede/ReacherTurn-v0", "ede/ReacherPush-v0"]]
)
def test_the_learning_curves_titles_fit_one_task_or_many(tasks: list[str]) -> None:
    curves = {(task, algo): [Curve(seed, STEPS, np.linspace(-500.0, 2000.0, len(STEPS)) + seed)
                             for seed in range(3)]
              for task in tasks for algo in ("td3", "ede-td3")}
    figure = learning_curve_figure("halfcheetah", tasks, curves, 0.95, 200,
                                   np.random.default_rng(0), bin_steps=2_500)
    assert cut_off(figure) == []


@pytest.mark.parametrize("tasks", [["Hopper-v5"], ["Pusher-v5", "ede/Striker-v0"]])
def test_the_diagnostics_titles_fit_one_task_or_many(tasks: list[str]) -> None:
    run = {"step": STEPS, "mean_q": np.linspace(0.0, 30.0, len(STEPS)),
           "critic_loss": np.linspace(0.1, 2.0, len(STEPS))}
    figure = diagnostics_figure("hopper", tasks, {(task, "td3"): [run] for task in tasks})
    assert cut_off(figure) == []


def test_across_tasks_on_hand_built_runs_whose_aggregates_are_known() -> None:
    from ede.report import Curve, across_tasks_section

    steps = np.array([0.0, 500.0, 1000.0])

    def runs(offset: float, seeds: range) -> list[Curve]:
        return [Curve(s, steps, np.array([-10.0, -5.0, -2.0]) + offset + 0.1 * s) for s in seeds]

    lows = {"a": -20.0, "b": -30.0}
    better = {("a", "td3"): runs(0, range(3)), ("a", "ede-td3"): runs(5, range(3)),
              ("b", "td3"): runs(-10, range(4)), ("b", "ede-td3"): runs(-3, range(1, 4))}
    found = across_tasks_section(better, lows, 0.95, 300, seed=0)
    assert found.tasks == ["a", "b"] and found.runs == 3  # b shares seeds 1-3 only
    for score in ("final_return", "auc"):
        p = found.aggregates[score]["probability_of_improvement"]
        assert (p.mean, p.low, p.high) == (1.0, 1.0, 1.0)
        assert found.aggregates[score]["iqm_ours"].low > found.aggregates[score]["iqm_theirs"].high
    assert found.figure.axes[0].get_xlabel().startswith("normalised final return")
    same = {key: runs(0, range(3)) for key in better}
    p = across_tasks_section(same, lows, 0.95, 300, seed=0).aggregates["auc"]["probability_of_improvement"]
    assert p.mean == 0.5 and p.low <= 0.5 <= p.high
    assert across_tasks_section({("a", "td3"): runs(0, range(2))}, lows, 0.95, 300, 0) is None
