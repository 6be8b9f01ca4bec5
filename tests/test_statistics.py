"""Known answers of the interval estimates: the IQM of constructed samples, the coverage of the
bootstrap interval on simulated normal samples, stratification, clipping, reproducibility, the
Student-t interval's quantiles, and the rliable protocol's performance profiles, optimality gap
and probability of improvement on scores whose answers are counted by hand."""

from __future__ import annotations

import math

import numpy as np
import pytest

from mapets_rl.statistics import (
    bootstrap_curve,
    bootstrap_interval,
    interquartile_mean,
    mean_ci95,
    optimality_gap,
    performance_profile,
    probability_of_improvement,
)


def test_interquartile_mean_drops_the_lowest_and_highest_quarter() -> None:
    assert interquartile_mean(np.arange(1.0, 9.0)) == pytest.approx(4.5)  # mean of 3, 4, 5, 6
    # the outliers are the dropped quarters: mean of 2, 3, 4, 5
    assert interquartile_mean([1000.0, 2.0, -100.0, 5.0, 3.0, 1.0, 4.0, 6.0]) == pytest.approx(3.5)
    # n = 10: floor(10 / 4) = 2 dropped on each side, as scipy.stats.trim_mean(x, 0.25)
    assert interquartile_mean(np.arange(10.0)) == pytest.approx(4.5)
    assert interquartile_mean([1.0, 2.0, 9.0]) == pytest.approx(4.0)  # < 4 scores: the mean
    rows = np.array([np.arange(1.0, 9.0), np.arange(1.0, 9.0) * 2])
    assert interquartile_mean(rows, axis=1) == pytest.approx([4.5, 9.0])
    assert interquartile_mean(rows) == pytest.approx(interquartile_mean(rows.reshape(-1)))
    with pytest.raises(ValueError, match="non-empty"):
        interquartile_mean([])


@pytest.mark.parametrize("statistic", ["mean", "iqm"])
def test_the_interval_covers_the_true_value_about_95_percent_of_the_time(statistic: str) -> None:
    """400 normal samples of 30 runs: the true centre (mean = IQM = 0 for a symmetric law) lies
    in the interval 90-98% of the time (the percentile bootstrap under-covers a little)."""
    rng = np.random.default_rng(1)
    hits = 0
    for k in range(400):
        sample = rng.normal(0.0, 1.0, size=30)
        _, low, high = bootstrap_interval(sample, statistic, resamples=1000, seed=k)
        hits += low <= 0.0 <= high
    assert 0.90 <= hits / 400 <= 0.98, hits / 400


def test_the_estimate_is_the_statistic_and_one_run_has_no_width() -> None:
    values = [0.1, 0.5, 0.6, 0.9, 4.0]
    assert bootstrap_interval(values).estimate == pytest.approx(np.mean(values))
    assert bootstrap_interval(values, "iqm").estimate == pytest.approx(np.mean([0.5, 0.6, 0.9]))
    assert tuple(bootstrap_interval([0.7])) == (0.7, 0.7, 0.7)


def test_the_stratified_bootstrap_resamples_runs_within_each_task() -> None:
    """Task 0 scores 0 on every run, task 1 scores 10: every replicate resamples 3 runs of each,
    so its mean is 5 exactly (pooling the 6 scores would let it wander from 0 to 10)."""
    scores = np.array([[0.0, 10.0], [0.0, 10.0], [0.0, 10.0]])  # [runs, tasks]
    assert tuple(bootstrap_interval(scores)) == pytest.approx((5.0, 5.0, 5.0))
    pooled = bootstrap_interval(scores.reshape(-1))
    assert pooled.low < 3.0 and pooled.high > 7.0


def test_the_interval_is_clipped_to_the_bounds() -> None:
    # a safety sample out of range (as a faulty metric would give) still yields an interval in
    # [0, 1]; a Student-t interval of [0.0, 1.0, 1.0] would reach 1.77
    assert bootstrap_interval([-0.5, -0.2, 0.4], bounds=(0.0, 1.0)).low == 0.0
    _, low, high = bootstrap_interval([0.0, 1.0, 1.0], bounds=(0.0, 1.0))
    assert 0.0 <= low < high <= 1.0
    curve = bootstrap_curve([[0.0, 2.0], [1.0, 3.0]], bounds=(0.0, 2.5))
    assert curve.high == pytest.approx([1.0, 2.5]) and curve.low == pytest.approx([0.0, 2.0])


def test_intervals_are_reproducible_and_a_curve_is_its_points() -> None:
    rng = np.random.default_rng(3)
    runs = rng.normal(size=(4, 6))  # [runs, points]
    assert bootstrap_interval(runs[:, 2]) == bootstrap_interval(runs[:, 2])
    many = rng.normal(size=20)  # (4 runs have few distinct resamples: seeds agree)
    assert bootstrap_interval(many, seed=1) != bootstrap_interval(many)
    curve = bootstrap_curve(runs, "iqm")
    for point in range(6):
        assert tuple(bootstrap_interval(runs[:, point], "iqm")) == pytest.approx(
            (curve.estimate[point], curve.low[point], curve.high[point])
        )


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"statistic": "median"}, "statistic must be one of"),
        ({"bounds": (1.0, 0.0)}, "bounds must be"),
        ({"bounds": (math.nan, 1.0)}, "bounds must be"),
        ({"confidence": 1.0}, r"confidence must be in \(0, 1\)"),
        ({"resamples": 0}, "resamples must be an integer >= 1"),
        ({"scores": [1.0, math.nan]}, "scores must be finite"),
        ({"scores": []}, r"non-empty \[runs\] or \[runs, tasks\]"),
        ({"scores": np.zeros((2, 2, 2))}, "got shape"),
    ],
)
def test_bad_input_names_the_parameter(kwargs: dict, message: str) -> None:
    kwargs = {"scores": [0.1, 0.2], **kwargs}
    with pytest.raises(ValueError, match=message):
        bootstrap_interval(**kwargs)
    with pytest.raises(ValueError, match=r"\[runs, points\]"):
        bootstrap_curve([0.1, 0.2])


@pytest.mark.parametrize(("n", "quantile"), [(2, 12.7062), (3, 4.3027), (5, 2.7764), (31, 2.0423)])
def test_mean_ci95_is_the_student_t_interval(n: int, quantile: float) -> None:
    """Half-width t(0.975, n - 1) s / sqrt(n), the quantiles of a t table; one value: none."""
    values = np.arange(float(n))
    mean, half = mean_ci95(values)
    assert mean == pytest.approx(values.mean())
    assert half == pytest.approx(quantile * values.std(ddof=1) / math.sqrt(n), rel=1e-4)
    assert mean_ci95([5.0]) == (5.0, 0.0)
    with pytest.raises(ValueError, match="non-empty"):
        mean_ci95([])


def test_the_bootstrap_keeps_its_published_numbers() -> None:
    """The intervals the hand-written numpy bootstrap gave (commit 22b249f: numpy's generator
    seeded 0, 5000 replicates, linear percentiles), to the last digits: the bootstrap on scipy
    resamples the same runs, so the results pages' intervals stand."""
    values = [0.1, 0.5, 0.6, 0.9, 4.0]
    assert tuple(bootstrap_interval(values)) == pytest.approx((1.22, 0.34, 2.62), abs=1e-12)
    assert tuple(bootstrap_interval(values, "iqm")) == pytest.approx(
        (2 / 3, 0.2333333333333333, 2.966666666666667), abs=1e-12
    )
    curve = bootstrap_curve([[0.0, 0.9, 1.0], [1.0, 1.0, 1.0], [1.0, 0.2, 1.0]], bounds=(0, 1))
    assert np.array(curve).ravel() == pytest.approx(
        [2 / 3, 0.7, 1.0, 0.0, 0.2, 1.0, 1.0, 1.0, 1.0], abs=1e-12
    )


def test_the_performance_profile_counts_the_runs_above_each_threshold() -> None:
    """Task 0 has runs 0.1, 0.5, 0.9, task 1 runs 0.2, 0.2, 0.2: above 0.3 are 2 of 6 scores,
    above 0.15 are 5 of 6 (rliable's fraction over runs and tasks); the band holds it, within
    [0, 1]; the strict '>' leaves a score equal to tau out."""
    scores = np.array([[0.1, 0.2], [0.5, 0.2], [0.9, 0.2]])  # [runs, tasks]
    profile = performance_profile(scores, [0.0, 0.15, 0.2, 0.3, 0.95])
    assert profile.estimate == pytest.approx([1.0, 5 / 6, 2 / 6, 2 / 6, 0.0])
    assert np.all(profile.low <= profile.estimate) and np.all(profile.estimate <= profile.high)
    assert np.all(profile.low >= 0.0) and np.all(profile.high <= 1.0)
    # task 1 is the same in every replicate: the fraction above 0.15 is at least 3/6
    assert profile.low[1] >= 0.5 and profile.low[0] == profile.high[0] == 1.0
    one = performance_profile([0.4], [0.3, 0.5])
    assert [list(part) for part in one] == [[1.0, 0.0], [1.0, 0.0], [1.0, 0.0]]
    with pytest.raises(ValueError, match="taus must be"):
        performance_profile([0.4, 0.5], [])
    with pytest.raises(ValueError, match="scores must be finite"):
        performance_profile([0.4, math.nan], [0.3])


def test_the_probability_of_improvement_counts_pairs_and_half_ties() -> None:
    """X = (1, 2, 3), Y = (2, 2, 0): of the 9 pairs X wins 1 > 0, 2 > 0, 3 > 2, 3 > 2, 3 > 0
    and ties 2 = 2 twice: (5 + 2 / 2) / 9 = 2/3; P(Y > X) = 1 - 2/3. Over two tasks, the mean of
    the tasks' probabilities."""
    x, y = [1.0, 2.0, 3.0], [2.0, 2.0, 0.0]
    poi = probability_of_improvement(x, y)
    assert poi.estimate == pytest.approx(6 / 9)
    assert probability_of_improvement(y, x).estimate == pytest.approx(3 / 9)
    assert 0.0 <= poi.low <= poi.estimate <= poi.high <= 1.0 and poi.low < poi.high
    assert tuple(probability_of_improvement([1.0] * 3, [1.0] * 3)) == (0.5, 0.5, 0.5)
    # task 1: X = (5, 6, 7) always beats Y = (1, 2, 3): P = 1; the mean with task 0's 2/3
    two = probability_of_improvement(np.array([x, [5.0, 6.0, 7.0]]).T, np.array([y, [1, 2, 3]]).T)
    assert two.estimate == pytest.approx((6 / 9 + 1.0) / 2)
    assert two.low >= 0.5  # task 1 is 1 in every replicate, task 0 at least 0
    # unequal run counts: X = (1, 3) against Y = (2, 2, 2): 3 wins of 6 pairs
    assert probability_of_improvement([1.0, 3.0], [2.0, 2.0, 2.0]).estimate == pytest.approx(0.5)
    assert tuple(probability_of_improvement([4.0], [1.0, 5.0])) == (0.5, 0.5, 0.5)
    with pytest.raises(ValueError, match="same tasks"):
        probability_of_improvement(np.zeros((3, 2)), np.zeros((3, 1)))


def test_the_optimality_gap_is_the_mean_shortfall_below_the_threshold() -> None:
    """Runs x tasks ``[[0.5, 1.2], [0.8, 0.0], [1.0, 0.6]]`` below gamma = 1 fall short by
    0.5, 0, 0.2, 1, 0, 0.4: the gap is 2.1 / 6 = 0.35, rliable's ``gamma - mean(min(scores,
    gamma))``; a score above gamma does not make up for another's shortfall; the interval is
    the stratified bootstrap of the shortfalls."""
    scores = np.array([[0.5, 1.2], [0.8, 0.0], [1.0, 0.6]])
    gap, low, high = optimality_gap(scores, 1.0)
    assert gap == pytest.approx(0.35)
    assert gap == pytest.approx(1.0 - np.minimum(scores, 1.0).mean())
    shortfalls = np.maximum(1.0 - scores, 0.0)
    assert (low, high) == pytest.approx(tuple(bootstrap_interval(shortfalls)[1:]))
    assert 0.0 <= low < gap < high
    assert tuple(optimality_gap([2.0, 0.0], 1.0)) == pytest.approx((0.5, 0.0, 1.0))
    assert tuple(optimality_gap([0.25], 1.0)) == (0.75, 0.75, 0.75)  # one run: no width
    assert tuple(optimality_gap([3.0, 4.0, 5.0], 2.0)) == (0.0, 0.0, 0.0)  # all above gamma
    # stratified: task 0 falls short by 0.3 on every run, task 1 by 0.7: every replicate 0.5
    even = np.array([[0.7, 0.3]] * 4)
    assert tuple(optimality_gap(even, 1.0)) == pytest.approx((0.5, 0.5, 0.5))
    for bad in (math.nan, math.inf, "1", True):
        with pytest.raises(ValueError, match="threshold must be a finite number"):
            optimality_gap(scores, bad)
