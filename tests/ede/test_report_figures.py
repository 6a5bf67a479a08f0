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
