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
    bootstrap_leads,
    bootstrap_mean,
    bootstrap_means,
    divergence,
    evaluation_noise,
    lead_band,
    normalised,
    steps_to_threshold,
)
from ede.run.runs import Curve, area_under_curve


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


def test_a_lead_is_the_difference_of_means_with_each_arm_resampled_on_its_own() -> None:
    ours, theirs = (
        np.array([[3.0, 1.0], [5.0, 1.0]]),
        np.array([[0.0, 1.0], [2.0, 1.0], [4.0, 1.0]]),
    )
    apart, level = bootstrap_leads(ours, theirs, 0.95, 2000, np.random.default_rng(0))
    assert (apart.mean, apart.n) == (2.0, 2) and (level.mean, level.low, level.high) == (0, 0, 0)
    # The extremes: ours' 3 drawn twice against theirs' 4 three times (-1), and 5 against 0 (5).
    assert -1 <= apart.low < 2 < apart.high <= 5
    # Each arm's resamples vary alone: an arm of one value adds nothing to the interval's width.
    alone = bootstrap_leads(ours[:, :1], np.full((3, 1), 2.0), 0.95, 2000, np.random.default_rng(0))
    drawn = bootstrap_mean(ours[:, 0], 0.95, 2000, np.random.default_rng(0))
    assert alone[0].high - alone[0].low == pytest.approx(drawn.high - drawn.low, abs=0.2)


def test_a_lead_band_is_per_bin_of_the_two_arms_binned_curves() -> None:
    steps = np.arange(0, 10_001, 1_000.0)
    ahead = [Curve(s, steps, steps / 100 + s) for s in range(3)]  # 0, 1, 2 above the line
    behind = [Curve(s, steps, np.zeros_like(steps) + s) for s in range(3)]
    band = lead_band(ahead, behind, 2_500, 0.95, 500, np.random.default_rng(0))
    np.testing.assert_array_equal(band.steps, [2_500, 5_000, 7_500, 10_000])
    # Per bin the mean of ahead's bin means less behind's: the line's mean in the bin.
    np.testing.assert_allclose(band.mean, [10, 40, 65, 90])
    assert (band.low > 0).all() and (band.n == 3).all()
    # A bin where a run has no evaluation has no lead.
    short = [Curve(0, steps[:6], steps[:6] / 100), *ahead[1:]]
    assert np.isnan(lead_band(short, behind, 2_500, 0.95, 500, np.random.default_rng(0)).mean[-1])


STEPS = np.arange(0, 250_001, 1_000.0)  # 251 evaluations; the last quarter's are the last 63
NOISE = 2.0


def noisy(curve: np.ndarray, seed: int = 0) -> np.ndarray:
    return curve + np.random.default_rng(seed).normal(0, NOISE, len(curve))


def test_the_noise_is_recovered_from_successive_differences_through_a_learning_curve() -> None:
    # Measured over 1,000 noise draws on a plateau: the estimate's mean 2.00, its spread 0.108;
    # a rise of 50 over the run adds (0.2)²/2 to its square. 0.45 is four spreads.
    rising = np.minimum(-100 + STEPS / 1_000, -50)
    for seed in range(5):
        assert evaluation_noise(noisy(rising, seed)) == pytest.approx(NOISE, abs=0.45)


def test_a_noisy_plateau_has_not_declined_and_a_fall_of_more_than_half_the_gain_diverged() -> None:
    plateau = np.minimum(-100 + STEPS / 1_000, -50)  # learns to -50 by 50K, then holds
    verdict = divergence(STEPS, noisy(plateau), 0.95, 0)
    assert not verdict.declined and not verdict.diverged and verdict.first < -95
    assert verdict.last == pytest.approx(-50, abs=1) and verdict.best == pytest.approx(-50, abs=1)
    # The fall noise reaches on a plateau is more than one comparison of two means of 63 (the
    # best of many windows is higher than one), 1.645·σ·sqrt(2/63): 1.5 times it here.
    single = 1.645 * NOISE * np.sqrt(2 / 63)
    assert 1.1 * single < verdict.noise < 2.5 * single
    falls = np.where(STEPS <= 100_000, plateau, -90)  # back to 10 above where it began
    verdict = divergence(STEPS, noisy(falls), 0.95, 0)
    assert verdict.declined and verdict.diverged
    assert verdict.best_span[1] <= 100_000 and verdict.decline == pytest.approx(40, abs=2)
    # A fall by less than half of what was gained has declined, not diverged.
    verdict = divergence(STEPS, noisy(np.where(STEPS <= 100_000, plateau, -65)), 0.95, 0)
    assert verdict.declined and not verdict.diverged


def test_a_dip_that_recovers_within_the_last_quarter_has_not_diverged() -> None:
    dip = np.minimum(-100 + STEPS / 1_000, -50)
    dip[(STEPS > 200_000) & (STEPS <= 205_000)] = -100  # five evaluations at the start's level
    verdict = divergence(STEPS, noisy(dip), 0.95, 0)
    assert not verdict.diverged and verdict.decline < 0.5 * (verdict.best - verdict.first)


def correlated(seed: int, rho: float) -> np.ndarray:
    """Stationary noise of standard deviation NOISE whose successive values correlate by rho."""
    rng = np.random.default_rng(seed)
    noise = np.empty(len(STEPS))
    noise[0] = rng.normal(0, NOISE)
    for t in range(1, len(noise)):
        noise[t] = rho * noise[t - 1] + rng.normal(0, NOISE * np.sqrt(1 - rho**2))
    return noise


@pytest.mark.parametrize(("rho", "rate"), [(0.0, 0.08), (0.7, 0.2)])
def test_plateaus_decline_by_chance_about_as_often_as_the_confidence_allows(
    rho: float, rate: float
) -> None:
    # A plateau's fall is held to what its own noise, as correlated as it is, reaches in 95% of
    # simulated plateaus. Measured on 400 draws of this curve: 3.0% declined with white noise,
    # 11% with successive evaluations correlated by 0.7 (TD3's on Pusher: 0.5 to 0.8; the
    # correlation measured on the last quarter's 63 evaluations comes out low) — against 5%
    # nominal; held to a white-noise threshold, the correlated plateaus would decline far more.
    plateau = np.minimum(-100 + STEPS / 1_000, -50)
    verdicts = [divergence(STEPS, plateau + correlated(seed, rho), 0.95, 0) for seed in range(200)]
    assert np.mean([v.declined for v in verdicts]) < rate
    assert not any(v.diverged for v in verdicts)  # a plateau gained nothing to lose half of
    if rho > 0:  # the threshold grows with the correlation
        white = [divergence(STEPS, plateau + correlated(seed, 0.0), 0.95, 0) for seed in range(20)]
        assert np.mean([v.noise for v in verdicts]) > 1.3 * np.mean([v.noise for v in white])


def test_a_run_that_never_learned_cannot_diverge() -> None:
    # Its best stretch is no higher than its untrained policy by more than noise: a fall below
    # both is a decline, not the loss of what it had gained.
    flat = np.where(STEPS <= 150_000, -100.0, -130.0)
    verdict = divergence(STEPS, noisy(flat), 0.95, 0)
    assert verdict.declined and not verdict.diverged


def test_a_run_too_short_for_a_window_before_its_last_quarter_is_refused() -> None:
    with pytest.raises(ValueError, match="too few"):
        divergence(STEPS[:2], STEPS[:2], 0.95, 0)  # one in the last quarter, one before
    assert divergence(STEPS[:3], STEPS[:3], 0.95, 0).best_span == (1000.0, 1000.0)  # 2n + 1 will do


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
