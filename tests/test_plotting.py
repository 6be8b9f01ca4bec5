"""The one plotting path: a curve and its bootstrap band, clipped to the metric's range."""

from __future__ import annotations

import math

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import pytest  # noqa: E402

from mapets_rl.plotting import clip_y_axis, draw_band, draw_curve  # noqa: E402
from mapets_rl.statistics import bootstrap_curve  # noqa: E402


def band_ys(ax) -> list[float]:
    """The y values of the vertices of every shaded band (``fill_between``) of ``ax``."""
    return [
        float(y)
        for coll in ax.collections
        for path in coll.get_paths()
        for y in path.vertices[:, 1]
    ]


def test_draw_curve_draws_the_mean_and_its_bootstrap_band_in_range() -> None:
    fig, ax = plt.subplots()
    runs = [[0.0, 0.9, 1.0], [1.0, 1.0, 1.0], [1.0, 0.2, 1.0]]  # safety of 3 seeds
    line = draw_curve(ax, [1, 2, 3], runs, metric="train/safety", label="mapets")
    estimate, low, high = bootstrap_curve(runs)
    assert list(line.get_ydata()) == pytest.approx(estimate)
    ys = band_ys(ax)
    assert min(ys) == pytest.approx(min(low)) and max(ys) == pytest.approx(max(high))
    assert 0.0 <= min(ys) and max(ys) <= 1.0
    assert line.get_label() == "mapets"
    plt.close(fig)


def test_draw_curve_draws_the_iqm_and_no_band_for_one_run() -> None:
    fig, ax = plt.subplots()
    runs = [[1.0], [2.0], [3.0], [100.0], [4.0], [5.0], [6.0], [-50.0]]
    line = draw_curve(ax, [0], runs, statistic="iqm")
    assert list(line.get_ydata()) == pytest.approx([3.5])
    line = draw_curve(ax, [0, 1], [[2.0, 3.0]], metric="safety")
    assert list(line.get_ydata()) == [2.0, 3.0] and len(ax.collections) == 1
    with pytest.raises(ValueError, match=r"runs must be \[runs, 2 points\]"):
        draw_curve(ax, [0, 1], [1.0, 2.0])
    plt.close(fig)


def test_draw_band_clips_to_the_metric_range_or_to_given_bounds() -> None:
    fig, ax = plt.subplots()
    draw_band(ax, [0, 1], [0.9, 0.95], [0.5, 0.6], [1.35, 1.2], metric="safety")
    assert max(band_ys(ax)) == 1.0
    fig2, ax2 = plt.subplots()
    draw_band(ax2, [0, 1], [5.0, 6.0], [-30.0, 1.0], [9.0, 9.0], bounds=(0.0, math.inf))
    assert min(band_ys(ax2)) == 0.0
    fig3, ax3 = plt.subplots()
    draw_band(ax3, [0, 1], [0.0, 0.0], [-8.0, -8.0], [8.0, 8.0], metric="return")  # unbounded
    assert min(band_ys(ax3)) == -8.0
    with pytest.raises(ValueError, match="low and high must be given together"):
        draw_band(ax3, [0, 1], [0.0, 0.0], [-8.0, -8.0])
    for f in (fig, fig2, fig3):
        plt.close(f)


def test_two_runs_draw_their_points_and_no_band() -> None:
    """The percentile interval of two runs is their range: no band called a 95% CI, the mean
    and each run's values as points in the line's colour."""
    fig, ax = plt.subplots()
    line = draw_curve(ax, [1, 2], [[0.2, 0.4], [0.6, 1.0]], metric="safety", label="two")
    assert list(line.get_ydata()) == pytest.approx([0.4, 0.7])
    (points,) = ax.collections  # the scatter, no fill_between
    assert sorted(map(tuple, points.get_offsets().tolist())) == [
        (1.0, 0.2),
        (1.0, 0.6),
        (2.0, 0.4),
        (2.0, 1.0),
    ]
    assert tuple(points.get_facecolor()[0][:3]) == pytest.approx(
        matplotlib.colors.to_rgb(line.get_color())
    )
    plt.close(fig)


def test_clip_y_axis_keeps_a_count_axis_above_zero() -> None:
    """Collisions all 0: matplotlib centres the flat line, reaching -0.055; clipped at 0. An
    unbounded metric keeps matplotlib's limits."""
    fig, ax = plt.subplots()
    draw_band(ax, [0, 1], [0.0, 0.0], metric="collisions")
    assert ax.get_ylim()[0] < 0.0
    clip_y_axis(ax, "collisions")
    assert ax.get_ylim()[0] == 0.0 and ax.get_ylim()[1] > 0.0
    fig2, ax2 = plt.subplots()
    draw_band(ax2, [0, 1], [0.0, 0.0], metric="return")
    before = ax2.get_ylim()
    clip_y_axis(ax2, "return")
    assert ax2.get_ylim() == before and before[0] < 0.0
    for f in (fig, fig2):
        plt.close(f)
