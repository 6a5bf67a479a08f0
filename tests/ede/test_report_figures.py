"""The figures (ede.analysis.figures) keep their titles inside the picture, whatever the family's size, and
draw what they are given; the aggregates across tasks (ede.analysis.results) on runs whose answer is known."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.text import Text

from ede.analysis import figures
from ede.analysis.results import AcrossTasks, across_tasks, comparisons, improvement_on_task
from ede.analysis.stats import Band, curve_band
from ede.config import ALGO_LABELS, ALGOS, ReportConfig
from ede.run.runs import Curve


def aggregate(*args: Any, **kwargs: Any) -> AcrossTasks:
    """:func:`ede.analysis.results.across_tasks` where the test expects aggregates."""
    found = across_tasks(*args, **kwargs)
    assert found is not None, "no aggregates across tasks"
    return found


def profile_figure(found: AcrossTasks) -> Figure:
    return figures.performance_profile(found.profile, len(found.tasks), found.runs)


STEPS = np.arange(1_000, 11_000, 1_000, dtype=float)


def cut_off(figure: Figure) -> list[str]:
    """Every title, axis label and legend entry reaching past the figure's edges (tick labels
    are left out: matplotlib keeps labels of ticks outside the view, which it does not draw)."""
    canvas = figure.canvas
    assert isinstance(canvas, FigureCanvasAgg), "the tests draw with Agg"
    canvas.draw()
    renderer = canvas.get_renderer()
    ticks = {
        id(label)
        for ax in figure.axes
        for axis in (ax.xaxis, ax.yaxis)
        for tick in axis.get_major_ticks() + axis.get_minor_ticks()
        for label in (tick.label1, tick.label2)
    }
    outside = []
    for text in figure.findobj(Text):
        if text.get_visible() and text.get_text() and id(text) not in ticks:
            box = text.get_window_extent(renderer)
            if (
                box.x0 < 0
                or box.x1 > figure.bbox.width
                or box.y0 < 0
                or box.y1 > figure.bbox.height
            ):
                outside.append(text.get_text())
    return outside


@pytest.mark.parametrize(
    "tasks",
    [["HalfCheetah-v5"], ["ede/ReacherVertical-v0", "ede/ReacherTurn-v0", "ede/ReacherPush-v0"]],
)
def test_the_learning_curves_titles_fit_one_task_or_many(tasks: list[str]) -> None:
    curves = {
        (task, algo): [
            Curve(seed, STEPS, np.linspace(-500.0, 2000.0, len(STEPS)) + seed) for seed in range(3)
        ]
        for task in tasks
        for algo in ("td3", "ede-td3")
    }
    bands = {
        key: curve_band(runs, 0.95, 200, np.random.default_rng(0), 2_500)
        for key, runs in curves.items()
    }
    seeds = {key: len(runs) for key, runs in curves.items()}
    figure = figures.learning_curves("halfcheetah", tasks, bands, seeds, 0.95, bin_steps=2_500)
    assert cut_off(figure) == []


@pytest.mark.parametrize("tasks", [["Hopper-v5"], ["Pusher-v5", "ede/Striker-v0"]])
def test_the_diagnostics_titles_fit_one_task_or_many(tasks: list[str]) -> None:
    run = {
        "step": STEPS,
        "mean_q": np.linspace(0.0, 30.0, len(STEPS)),
        "critic_loss": np.linspace(0.1, 2.0, len(STEPS)),
    }
    figure = figures.diagnostics("hopper", tasks, {(task, "td3"): [run] for task in tasks})
    assert cut_off(figure) == []


def test_across_tasks_on_hand_built_runs_whose_aggregates_are_known() -> None:
    steps = np.array([0.0, 500.0, 1000.0])

    def runs(offset: float, seeds: range) -> list[Curve]:
        return [Curve(s, steps, np.array([-10.0, -5.0, -2.0]) + offset + 0.1 * s) for s in seeds]

    lows = {"a": -20.0, "b": -30.0}
    better = {
        ("a", "td3"): runs(0, range(3)),
        ("a", "ede-td3"): runs(5, range(3)),
        ("b", "td3"): runs(-10, range(4)),
        ("b", "ede-td3"): runs(-3, range(1, 4)),
    }
    found = aggregate(better, lows, 0.95, 300, seed=0)
    # Each algorithm keeps its fewest seeds on any task, each task's lowest: 3 of each here, so
    # b's TD3 seed 3 is named as left out; EDE-TD3 keeps b's seeds 1-3, all it has there.
    assert found.tasks == ["a", "b"] and found.runs == {"ede-td3": 3, "td3": 3}
    assert found.left_out == ["b TD3 seed 3"]
    assert "Left out: b TD3 seed 3." in found.describe(0.95, 300)
    for score in ("final_return", "auc"):
        p = found.aggregates[score]["probability_of_improvement"]
        assert (p.mean, p.low, p.high) == (1.0, 1.0, 1.0)
        assert found.aggregates[score]["iqm_ours"].low > found.aggregates[score]["iqm_theirs"].high
    assert profile_figure(found).axes[0].get_xlabel().startswith("normalised final return")
    same = {key: runs(0, range(3)) for key in better}
    p = aggregate(same, lows, 0.95, 300, seed=0).aggregates["auc"]["probability_of_improvement"]
    assert p.mean == 0.5 and p.low < 0.5 < p.high
    assert across_tasks({("a", "td3"): runs(0, range(2))}, lows, 0.95, 300, 0) is None


def test_unequal_run_counts_of_the_two_algorithms_are_all_used() -> None:
    steps = np.array([0.0, 1000.0])
    # TD3's 2 seeds end at 0 and 2, EDE-TD3's 4 at 1, 3, 3, 3: of the 8 pairs EDE-TD3 wins 7.
    curves = {
        ("a", "td3"): [Curve(s, steps, np.array([0.0, 2.0 * s])) for s in range(2)],
        ("a", "ede-td3"): [Curve(s, steps, np.array([0.0, 1.0 + 2 * min(s, 1)])) for s in range(4)],
    }
    found = aggregate(curves, {"a": -1.0}, 0.95, 300, seed=0)
    assert found.runs == {"ede-td3": 4, "td3": 2} and found.left_out == []
    assert found.aggregates["final_return"]["probability_of_improvement"].mean == 7 / 8


def test_the_probability_of_improvement_on_one_task_uses_all_its_runs() -> None:
    steps = np.array([0.0, 1000.0])
    # As above: of the 8 pairs EDE-TD3 wins 7, by its final return and so by its area too.
    td3 = [Curve(s, steps, np.array([0.0, 2.0 * s])) for s in range(2)]
    ede = [Curve(s, steps, np.array([0.0, 1.0 + 2 * min(s, 1)])) for s in range(4)]
    found = improvement_on_task(ede, td3, 0.95, 300, seed=0)
    assert set(found) == {"final_return", "auc"}
    assert all(p.mean == 7 / 8 and p.n == 2 for p in found.values())
    same = improvement_on_task(ede, ede, 0.95, 300, seed=0)["final_return"]
    assert same.mean == 0.5 and same.low < 0.5 < same.high


def test_a_task_no_run_lifted_above_a_random_policy_is_left_out_by_name() -> None:
    steps = np.array([0.0, 1000.0])
    good = {
        (t, a): [Curve(s, steps, np.array([-9.0, -1.0 - s - (a == "td3")])) for s in range(3)]
        for t in ("a", "b")
        for a in ("td3", "ede-td3")
    }
    found = aggregate(good, {"a": -10.0, "b": -1.0}, 0.9, 300, seed=0)
    assert found.tasks == ["a"]
    assert found.left_out == ["b (its best evaluation, -1, is not above the random policy's -1)"]
    assert across_tasks(good, {"b": -1.0}, 0.9, 300, seed=0) is None


def test_the_performance_profile_band_has_the_reports_confidence() -> None:
    steps = np.array([0.0, 1000.0])
    rng = np.random.default_rng(5)
    curves = {
        ("a", a): [Curve(s, steps, np.array([-9.0, -5 + rng.normal()])) for s in range(6)]
        for a in ("td3", "ede-td3")
    }

    def band_area(confidence: float) -> float:  # of both algorithms' bands, by the shoelace
        found = aggregate(curves, {"a": -10.0}, confidence, 500, seed=0)
        area = 0.0
        for band in profile_figure(found).axes[0].collections:
            x, y = np.asarray(band.get_paths()[0].vertices).T
            area += 0.5 * abs(np.dot(x, np.roll(y, 1)) - np.dot(y, np.roll(x, 1)))
        return area

    assert 0 < band_area(0.5) < 0.8 * band_area(0.99)


def test_a_band_is_drawn_as_it_is_given_and_a_pair_without_one_not_at_all() -> None:
    given = Band(
        STEPS,
        np.full(len(STEPS), 7.0),
        np.full(len(STEPS), 6.0),
        np.full(len(STEPS), 8.0),
        np.full(len(STEPS), 3.0),
    )
    figure = figures.learning_curves(
        "halfcheetah",
        ["HalfCheetah-v5"],
        {("HalfCheetah-v5", "ede-td3"): given},
        {("HalfCheetah-v5", "ede-td3"): 3, ("HalfCheetah-v5", "td3"): 3},
        0.95,
    )
    drawn = {
        str(line.get_label()).split(" (")[0]: line.get_ydata() for line in figure.axes[0].lines
    }
    assert set(drawn) == {"EDE-TD3"}
    assert np.array_equal(drawn["EDE-TD3"], given.mean)
    (fill,) = figure.axes[0].collections
    _, y = np.asarray(fill.get_paths()[0].vertices).T
    assert y.min() == 6.0 and y.max() == 8.0  # the band between the given low and high


def test_every_algorithm_is_drawn_in_a_colour_of_its_own() -> None:
    curves: dict[tuple[str, str], list[Curve]] = {
        ("Hopper-v5", algo): [
            Curve(s, STEPS, np.linspace(0.0, 100.0 * i, len(STEPS)) + s) for s in range(2)
        ]
        for i, algo in enumerate(ALGOS)
    }
    bands = {
        key: curve_band(runs, 0.95, 100, np.random.default_rng(0)) for key, runs in curves.items()
    }
    figure = figures.learning_curves(
        "hopper", ["Hopper-v5"], bands, {key: 2 for key in curves}, 0.95
    )
    lines = figure.axes[0].lines
    assert [str(line.get_label()) for line in lines] == [
        f"{ALGO_LABELS[a]} (2 seeds)" for a in ALGOS
    ]
    assert len({line.get_color() for line in lines}) == len(ALGOS)
    assert cut_off(figure) == []


def test_ede_td3_against_every_other_algorithm_then_the_ede_space_against_raw_actions() -> None:
    steps = np.linspace(0.0, 10_000.0, 21)

    def runs(gain: float, seeds: int) -> list[Curve]:
        return [Curve(s, steps, gain * steps / 10_000 + 0.01 * s) for s in range(seeds)]

    report = ReportConfig(bootstrap_samples=200)
    # EDE-TD3 above SB3's SAC, level with TD3, below SB3's TD3 in the EDE space; SB3's SAC in
    # the EDE space has no runs here, and one seed of SB3's SAC claims no lead.
    curves = {
        "sb3-sac": runs(-5.0, 1),
        "sb3-td3-ede": runs(20.0, 3),
        "ede-td3": runs(10.0, 3),
        "td3": runs(10.0, 3),
        "sb3-sac-ede": [],
    }
    found = comparisons(curves, 1_000.0, report)
    assert [(c.ours, c.against) for c in found] == [
        ("ede-td3", "td3"),
        ("ede-td3", "sb3-td3-ede"),
        ("ede-td3", "sb3-sac"),
        ("sb3-td3-ede", "td3"),  # SB3's SAC in the EDE space has no runs to set against SAC's
    ]
    level, below, above, space = found
    assert level.improvement["final_return"].mean == 0.5
    assert below.improvement["final_return"].mean == 0.0
    assert above.improvement["auc"].mean == 1.0
    bins = below.bins()  # EDE-TD3's lead's interval above 0, below 0, of all
    assert bins is not None and bins[0] == 0 and bins[1] > 0
    assert above.lead is None and above.bins() is None
    assert space.improvement["final_return"].mean == 1.0  # SB3's TD3 in the EDE space above TD3
    bins = space.bins()
    assert bins is not None and bins[0] > 0 and bins[1] == 0
    # A pair's numbers are its runs' alone, whatever else the task has: so without EDE-TD3's.
    (alone,) = comparisons({**curves, "ede-td3": []}, 1_000.0, report)
    assert (alone.ours, alone.against) == ("sb3-td3-ede", "td3")
    assert alone.improvement == space.improvement
    assert alone.lead is not None and space.lead is not None
    assert (alone.lead.final, alone.lead.area) == (space.lead.final, space.lead.area)
    assert np.array_equal(alone.lead.band.low, space.lead.band.low)
    assert comparisons({"td3": curves["td3"], "sb3-sac-ede": runs(5.0, 3)}, 1_000.0, report) == []
