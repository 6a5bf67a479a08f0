"""Report maths against hand-computed cases."""

from __future__ import annotations

import math

import numpy as np
import pytest

from ede.analysis.stats import (
    Interval,
    across_tasks,
    align_curves,
    bin_curve,
    bootstrap_mean,
    bootstrap_means,
    divergence,
    normalised,
    separation,
    steps_to_threshold,
)
from ede.run.runs import area_under_curve


def test_area_under_curve_is_the_trapezoidal_mean_return() -> None:
    # Trapezoids: (0 + 10) / 2 * 100 + (10 + 10) / 2 * 100 = 1500 over 200 steps.
    assert area_under_curve(np.array([0, 100, 200]), np.array([0.0, 10.0, 10.0])) == 7.5
    # Uneven spacing: (2 + 4) / 2 * 1 + (4 + 0) / 2 * 3 = 9 over 4 steps.
    assert area_under_curve(np.array([0, 1, 4]), np.array([2.0, 4.0, 0.0])) == 2.25
    assert area_under_curve(np.array([50]), np.array([-3.0])) == -3.0
    assert math.isnan(area_under_curve(np.array([]), np.array([])))
    with pytest.raises(ValueError):
        area_under_curve(np.array([0, 1]), np.array([1.0]))


def test_steps_to_threshold_is_the_first_step_reaching_it() -> None:
    steps = np.array([0, 500, 1000, 1500])
    assert steps_to_threshold(steps, np.array([-9.0, -5.0, -2.0, -3.0]), -5.0) == 500
    assert steps_to_threshold(steps, np.array([-9.0, -5.0, -2.0, -3.0]), -2.5) == 1000
    assert steps_to_threshold(steps, np.array([-9.0, -8.0, -7.0, -6.0]), 0.0) == math.inf


def test_bootstrap_interval_of_identical_values_is_a_point() -> None:
    interval = bootstrap_mean(np.array([2.0, 2.0, 2.0]), 0.95, 500, np.random.default_rng(0))
    assert (interval.mean, interval.low, interval.high, interval.n) == (2.0, 2.0, 2.0, 3)


def test_bootstrap_interval_of_two_values_by_hand() -> None:
    # Resampling [0, 10] twice: means 0 (p = 1/4), 5 (p = 1/2), 10 (p = 1/4).
    # The 2.5% and 97.5% quantiles of that distribution are 0 and 10; at 40% confidence
    # (30% and 70% quantiles) both ends are 5.
    rng = np.random.default_rng(1)
    wide = bootstrap_mean(np.array([0.0, 10.0]), 0.95, 20_000, rng)
    assert (wide.mean, wide.low, wide.high) == (5.0, 0.0, 10.0)
    narrow = bootstrap_mean(np.array([0.0, 10.0]), 0.40, 20_000, rng)
    assert (narrow.low, narrow.high) == (5.0, 5.0)


def test_bootstrap_interval_covers_the_mean_and_shrinks_with_more_seeds() -> None:
    rng = np.random.default_rng(2)
    few = bootstrap_mean(rng.normal(0, 1, 4), 0.95, 4000, rng)
    many = bootstrap_mean(rng.normal(0, 1, 400), 0.95, 4000, rng)
    assert few.low <= few.mean <= few.high and many.low <= many.mean <= many.high
    assert (many.high - many.low) < (few.high - few.low)
    assert -0.3 < many.mean < 0.3


def test_a_seed_that_never_reaches_the_threshold_shows_in_the_interval() -> None:
    steps = np.array([0, 100, 200])
    reached = [
        steps_to_threshold(steps, np.array(r), 1.0)
        for r in ([0.0, 1.0, 2.0], [0.0, 0.5, 1.5], [0.0, 0.0, 0.0])
    ]
    assert reached == [100.0, 200.0, math.inf]
    interval = bootstrap_mean(np.array(reached), 0.95, 2000, np.random.default_rng(3))
    assert interval.mean == math.inf and interval.high == math.inf
    assert interval.low == 100.0  # the resample of the fastest seed three times
    assert str(interval) == interval.steps() == "never [100, never]"
    assert str(bootstrap_mean(np.array([]), 0.95, 10, np.random.default_rng(0))) == "missing"


def test_steps_read_as_whole_steps_where_significant_digits_would_round_them() -> None:
    interval = Interval(mean=12_345.4, low=9_000.0, high=15_600.6, n=4)
    assert str(interval) == "1.235e+04 [9000, 1.56e+04]"
    assert interval.steps() == "12,345 [9,000, 15,601]"
    assert Interval(math.nan, math.nan, math.nan, 0).steps() == "missing"


def test_curves_of_unequal_length_align_on_the_union_of_steps() -> None:
    steps, table = align_curves(
        [
            (np.array([0, 10, 20]), np.array([1.0, 2.0, 3.0])),
            (np.array([0, 10]), np.array([4.0, 5.0])),
        ]
    )
    np.testing.assert_array_equal(steps, [0, 10, 20])
    np.testing.assert_array_equal(table, [[1.0, 2.0, 3.0], [4.0, 5.0, np.nan]])


def test_bins_are_right_closed_with_step_zero_in_the_first_as_the_authors_notebook() -> None:
    # Evaluations every 1,000 steps in 2,500-step bins: {0, 1000, 2000}, {3000, 4000, 5000},
    # {6000, 7000}, ... as pandas' cut((-50, 2500], (2500, 5000], ...) groups them.
    steps = np.arange(0, 10_001, 1000)
    returns = steps / 1000.0  # 0, 1, ..., 10
    edges, means = bin_curve(steps, returns, 2500)
    assert edges.tolist() == [2500, 5000, 7500, 10000]
    assert means.tolist() == [1.0, 4.0, 6.5, 9.0]  # (0+1+2)/3, (3+4+5)/3, (6+7)/2, (8+9+10)/3


def test_a_bin_without_evaluations_is_left_out_and_uneven_steps_bin_by_value() -> None:
    edges, means = bin_curve(np.array([0, 600, 3100]), np.array([-4.0, -2.0, 5.0]), 1000)
    assert edges.tolist() == [1000, 4000] and means.tolist() == [-3.0, 5.0]


def test_binned_band_is_the_mean_over_seeds_of_each_seeds_bin_means() -> None:
    from ede.analysis.stats import curve_band
    from ede.run.runs import Curve

    steps = np.array([0, 1000, 2000, 3000, 4000, 5000])
    curves = [
        Curve(0, steps, np.array([0.0, 1, 2, 3, 4, 5])),
        Curve(1, steps, np.array([2.0, 2, 2, 9, 9, 9])),
    ]
    rng = np.random.default_rng(0)
    binned, mean, low, high, n = curve_band(curves, 0.95, 200, rng, bin_steps=2500)
    assert binned.tolist() == [2500, 5000] and n.tolist() == [2, 2]
    assert mean.tolist() == [(1.0 + 2.0) / 2, (4.0 + 9.0) / 2]
    assert low[1] == 4.0 and high[1] == 9.0  # two seeds: the band spans their bin means
    raw = curve_band(curves, 0.95, 200, rng)
    assert raw[0].tolist() == steps.tolist()


def test_a_band_over_runs_of_unequal_length_uses_the_seeds_each_point_has() -> None:
    from ede.analysis.stats import curve_band
    from ede.run.runs import Curve

    steps = np.array([0, 1000, 2000])
    curves = [
        Curve(0, steps, np.array([0.0, 4.0, 8.0])),
        Curve(1, steps[:2], np.array([2.0, 6.0])),
        Curve(2, steps[:2], np.array([4.0, 8.0])),
    ]
    _, mean, low, high, n = curve_band(curves, 0.95, 500, np.random.default_rng(0))
    assert n.tolist() == [3, 3, 1] and mean.tolist() == [2.0, 6.0, 8.0]
    assert (low[2], high[2]) == (8.0, 8.0)  # one seed left: no spread to resample
    assert low[0] == 0.0 and high[0] == 4.0  # 1/27 of the resamples draw one seed thrice


def test_each_column_has_its_own_interval_from_its_own_resamples() -> None:
    table = np.array([[1.0, 5.0, 0.0], [1.0, 5.0, 10.0], [1.0, 5.0, math.inf]])
    same, other, never = bootstrap_means(table, 0.95, 1000, np.random.default_rng(4))
    assert (same.low, same.high, other.low, other.high) == (1.0, 1.0, 5.0, 5.0)
    assert never.mean == math.inf and never.high == math.inf and never.low == 0.0


def test_separation_marks_disjoint_intervals_by_which_side_is_above() -> None:
    low_a, high_a = np.array([0.0, 2.0, 0.0, 0.0, np.nan]), np.array([1.0, 3.0, 1.0, 2.0, 1.0])
    low_b, high_b = np.array([1.5, 0.0, -2.0, 1.0, 0.0]), np.array([2.0, 1.9, -0.5, 3.0, 1.0])
    np.testing.assert_array_equal(separation(low_a, high_a, low_b, high_b), [-1, 1, 1, 0, 0])


STEPS = np.arange(0, 100_001, 1_000.0)


def test_a_run_that_falls_and_stays_below_its_best_diverges() -> None:
    rises_then_falls = np.where(STEPS <= 50_000, -100 + STEPS / 1_000, -50 - (STEPS - 50_000) / 500)
    verdict = divergence(STEPS, rises_then_falls, 10_000)
    assert verdict.diverged
    assert verdict.best_step == 50_000 and verdict.first < verdict.best
    assert verdict.tail < verdict.best - 0.5 * (verdict.best - verdict.first)


def test_learning_plateaus_dips_that_recover_and_flat_runs_do_not_diverge() -> None:
    rising = -100 + STEPS / 1_000
    plateau = np.minimum(rising, -60)
    dip = plateau.copy()
    dip[(STEPS > 80_000) & (STEPS < 90_000)] = -100  # a dip inside the tail, then back
    flat = np.full_like(STEPS, -100.0)
    for curve in (rising, plateau, dip, flat):
        assert not divergence(STEPS, curve, 10_000).diverged
    # A fall by less than half of what was gained is not a divergence either.
    assert not divergence(STEPS, np.where(STEPS <= 50_000, rising, -50 - 0.4 * 50), 10_000).diverged


def test_a_curve_too_short_for_a_tail_is_refused() -> None:
    with pytest.raises(ValueError, match="too few"):
        divergence(STEPS[:3], STEPS[:3], 10_000)


def test_one_method_better_on_every_run_has_probability_one_of_improvement() -> None:
    rng = np.random.default_rng(0)
    theirs = rng.normal(size=(5, 3))
    found = across_tasks(theirs + 10, theirs, 0.95, 500, seed=0)
    p = found["probability_of_improvement"]
    assert (p.mean, p.low, p.high) == (1.0, 1.0, 1.0)
    assert found["iqm_ours"].low > found["iqm_theirs"].high


def test_identical_methods_have_probability_one_half_with_an_interval_around_it() -> None:
    scores = np.random.default_rng(1).normal(size=(8, 4))
    found = across_tasks(scores, scores.copy(), 0.95, 1000, seed=0)
    p = found["probability_of_improvement"]
    assert p.mean == 0.5 and p.low < 0.5 < p.high
    assert found["iqm_ours"].mean == found["iqm_theirs"].mean  # resampled apart: intervals differ


def test_across_tasks_is_determined_by_its_seed_and_refuses_mismatched_tables() -> None:
    rng = np.random.default_rng(2)
    ours, theirs = rng.normal(size=(4, 2)), rng.normal(size=(4, 2))
    np.random.seed(3)
    before = np.random.get_state(legacy=False)["state"]["key"].copy()
    assert across_tasks(ours, theirs, 0.95, 300, 7) == across_tasks(ours, theirs, 0.95, 300, 7)
    after = np.random.get_state(legacy=False)["state"]["key"]
    np.testing.assert_array_equal(after, before)  # the global generator kept
    with pytest.raises(ValueError, match="over the same tasks"):
        across_tasks(ours, theirs[:, :1], 0.95, 300, 7)


def test_normalised_scores_run_from_low_to_high_per_task() -> None:
    scores = np.array([[-10.0, 5.0], [0.0, 15.0]])
    np.testing.assert_allclose(
        normalised(scores, np.array([-10.0, 5.0]), np.array([0.0, 15.0])), [[0.0, 0.0], [1.0, 1.0]]
    )
    with pytest.raises(ValueError, match=r"tasks \[1\]: high not above low"):
        normalised(scores, np.array([-10.0, 5.0]), np.array([0.0, 5.0]))


def test_minus_infinity_has_no_meaning_in_a_bootstrap_of_means() -> None:
    with pytest.raises(ValueError, match="-inf"):
        bootstrap_mean(np.array([1.0, -math.inf]), 0.95, 100, np.random.default_rng(0))
