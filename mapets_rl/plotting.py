"""The one way the project draws a learning curve: the mean (or IQM) over runs with its
bootstrap 95% band clipped to the values the metric can take; below
:data:`~mapets_rl.statistics.MIN_RUNS_FOR_INTERVAL` runs (two) no band, the runs' values as
points instead (the percentile interval of two runs is only their range).

``mapets-rl compare``, the example scripts and the ablations all draw through
:func:`draw_curve` (from each run's values) or :func:`draw_band` (from an interval computed
before, e.g. ``compare``'s ``curves.json``), so no plotted band leaves its metric's range
(:func:`mapets_rl.metrics.metric_range`: safety in ``[0, 1]``, speeds and counts ``>= 0``).
matplotlib is imported by the caller's ``Axes`` only: importing this module does not import it.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import ArrayLike

from mapets_rl.metrics import metric_range
from mapets_rl.statistics import MIN_RUNS_FOR_INTERVAL, bootstrap_curve

if TYPE_CHECKING:
    from matplotlib.axes import Axes
    from matplotlib.collections import PathCollection
    from matplotlib.lines import Line2D

BAND_ALPHA = 0.2
"""Opacity of the interval band."""


def _bounds(metric: str | None, bounds: tuple[float, float] | None) -> tuple[float, float]:
    if bounds is not None:
        return bounds
    return metric_range(metric) if metric is not None else (-math.inf, math.inf)


def draw_band(
    ax: Axes,
    x: Sequence[float],
    estimate: ArrayLike,
    low: ArrayLike | None = None,
    high: ArrayLike | None = None,
    *,
    metric: str | None = None,
    bounds: tuple[float, float] | None = None,
    **line_kwargs: Any,
) -> Line2D:
    """Draw ``estimate`` against ``x`` and, given ``low`` and ``high``, the band between them.

    Args:
        ax: the matplotlib axes.
        x: ``[points]``.
        estimate: ``[points]``, the curve.
        low, high: ``[points]``, the interval; ``None`` (one run): no band.
        metric: the metric drawn (``"safety"``, ``"train/safety"``); its range
            (:func:`~mapets_rl.metrics.metric_range`) clips the band.
        bounds: ``(low, high)`` to clip the band to instead of the metric's range (a metric in
            other units, e.g. a speed in mph: ``(0, inf)``).
        line_kwargs: passed to ``ax.plot`` (``label``, ``color``, ``marker``, ...).

    Returns:
        The curve's line (its colour is the band's).
    """
    if (low is None) != (high is None):
        raise ValueError("low and high must be given together (or neither, for no band)")
    (line,) = ax.plot(x, np.asarray(estimate, dtype=float), **line_kwargs)
    if low is not None:
        lo, hi = _bounds(metric, bounds)
        ax.fill_between(
            x,
            np.clip(np.asarray(low, dtype=float), lo, hi),
            np.clip(np.asarray(high, dtype=float), lo, hi),
            alpha=BAND_ALPHA,
            color=line.get_color(),
            linewidth=0,
        )
    return line


def draw_points(
    ax: Axes, x: Sequence[float], runs: ArrayLike, **scatter_kwargs: Any
) -> PathCollection:
    """Draw each run's value at every ``x`` as a point (the runs of a curve too few for a band).

    Args:
        ax: the matplotlib axes.
        x: ``[points]``.
        runs: ``[runs, points]``, each run's value at every ``x``.
        scatter_kwargs: passed to ``ax.scatter`` (``color``, ``marker``, ...).

    Returns:
        The points.
    """
    values = np.asarray(runs, dtype=float)
    if values.ndim != 2 or values.shape[1] != len(x):
        raise ValueError(f"runs must be [runs, {len(x)} points], got shape {values.shape}")
    xs = np.broadcast_to(np.asarray(x, dtype=float), values.shape)
    return ax.scatter(xs.ravel(), values.ravel(), **{"s": 10, "alpha": 0.6, **scatter_kwargs})


def clip_y_axis(
    ax: Axes, metric: str | None = None, bounds: tuple[float, float] | None = None
) -> None:
    """Keep ``ax``'s y axis inside the metric's range (or ``bounds``): call it once every curve
    is drawn (it fixes the limits), so that a count or a speed has no axis below zero."""
    lo, hi = _bounds(metric, bounds)
    bottom, top = ax.get_ylim()
    ax.set_ylim(max(bottom, lo), min(top, hi))


def draw_curve(
    ax: Axes,
    x: Sequence[float],
    runs: ArrayLike,
    *,
    metric: str | None = None,
    statistic: str = "mean",
    bounds: tuple[float, float] | None = None,
    **line_kwargs: Any,
) -> Line2D:
    """Draw the ``statistic`` over runs at every ``x`` with its bootstrap 95% band
    (:func:`mapets_rl.statistics.bootstrap_curve`), clipped to the metric's range.

    Args:
        ax: the matplotlib axes.
        x: ``[points]``.
        runs: ``[runs, points]``, each run's (seed's) value at every ``x``; one run draws its
            values and no band, two runs their ``statistic`` and each run's values as points
            (:func:`draw_points`), no band.
        metric, bounds, line_kwargs: as :func:`draw_band`.
        statistic: ``"mean"`` or ``"iqm"`` (interquartile mean, stratified bootstrap).

    Returns:
        The curve's line.
    """
    values = np.asarray(runs, dtype=float)
    if values.ndim != 2 or values.shape[1] != len(x):
        raise ValueError(f"runs must be [runs, {len(x)} points], got shape {values.shape}")
    estimate, low, high = bootstrap_curve(values, statistic, bounds=_bounds(metric, bounds))
    if values.shape[0] >= MIN_RUNS_FOR_INTERVAL:
        return draw_band(ax, x, estimate, low, high, metric=metric, bounds=bounds, **line_kwargs)
    line = draw_band(ax, x, estimate, metric=metric, bounds=bounds, **line_kwargs)
    if values.shape[0] > 1:
        draw_points(ax, x, values, color=line.get_color())
    return line
