"""Interval estimates over independent runs (seeds): the mean with a percentile-bootstrap 95%
interval, and the interquartile mean (IQM) with a stratified-bootstrap 95% interval.

The protocol is that of Agarwal et al. (2021), "Deep Reinforcement Learning at the Edge of the
Statistical Precipice" (NeurIPS), written here on numpy (their ``rliable`` package is
archived):

- *scores* are ``[runs]`` (one task) or ``[runs, tasks]`` (the same runs' score on each task);
- the *IQM* is the mean of the middle 50% of all scores: the ``floor(n / 4)`` lowest and highest
  of the ``n`` scores are dropped (``scipy.stats.trim_mean(scores, 0.25)``, rliable's
  definition), so it is robust to an outlying run and, unlike the median, uses half the runs;
  with fewer than 4 scores nothing is dropped and it is the mean;
- the *stratified bootstrap* resamples the runs with replacement independently within each
  task, recomputes the statistic over every resampled score, and takes the 2.5th and 97.5th
  percentiles of the ``resamples`` replicates as the 95% interval (the percentile bootstrap;
  with one task it is the ordinary bootstrap over runs).

The generator is seeded (:data:`BOOTSTRAP_SEED`): the same scores give the same interval every
time. Intervals are clipped to ``bounds``, the values the metric can take
(:func:`mapets_rl.metrics.metric_range`: safety in ``[0, 1]``, speeds and counts ``>= 0``).

With few runs read the intervals with care: a bootstrap interval never reaches beyond the
sample's smallest and largest value, so with 3 seeds it is narrower than the uncertainty (it
holds the mean of 3 normal draws about 75% of the time, not 95%).

The Student-t interval of the mean (:func:`mean_ci95`) stays for the examples and benchmarks
that report it.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from typing import NamedTuple

import numpy as np
from numpy.typing import ArrayLike

BOOTSTRAP_RESAMPLES = 5000
"""Bootstrap replicates per interval: the interval's ends move by about 1% of its width between
generator seeds."""
BOOTSTRAP_SEED = 0
"""Seed of the bootstrap's generator (reproducible intervals)."""
CONFIDENCE = 0.95
"""Coverage of the intervals."""
_MAX_RESAMPLED = 4_000_000
"""Resampled scores held at once (32 MB): a long curve is bootstrapped a block of points at a
time."""


class IntervalEstimate(NamedTuple):
    """A point estimate and its confidence interval ``[low, high]``; scalars for one interval,
    ``[points]`` arrays for a curve."""

    estimate: float | np.ndarray
    low: float | np.ndarray
    high: float | np.ndarray


def interquartile_mean(scores: ArrayLike, axis: int | None = None) -> float | np.ndarray:
    """The interquartile mean: sorted along ``axis`` (``None``: all scores), the ``floor(n / 4)``
    lowest and highest of the ``n`` scores dropped, the mean of the rest.

    Args:
        scores: any shape.
        axis: the axis to reduce; ``None`` reduces all of them.

    Returns:
        A float for ``axis=None``, else ``scores`` without ``axis``.
    """
    x = np.asarray(scores, dtype=np.float64)
    if axis is None:
        x, axis = x.reshape(-1), 0
    n = x.shape[axis]
    if n == 0:
        raise ValueError("scores must be non-empty")
    cut = n // 4
    kept = np.sort(x, axis=axis).take(np.arange(cut, n - cut), axis=axis) if cut else x
    out = kept.mean(axis=axis)
    return float(out) if out.ndim == 0 else out


STATISTICS: dict[str, Callable[[np.ndarray, int], np.ndarray]] = {
    "mean": lambda x, axis: np.mean(x, axis=axis),
    "iqm": lambda x, axis: np.asarray(interquartile_mean(x, axis=axis)),
}
"""Name -> ``statistic(scores, axis)`` reducing ``axis``: ``"mean"`` and ``"iqm"``."""


def _check_options(
    statistic: str, bounds: tuple[float, float], confidence: float, resamples: int
) -> None:
    if statistic not in STATISTICS:
        raise ValueError(f"statistic must be one of {sorted(STATISTICS)}, got {statistic!r}")
    low, high = bounds
    if math.isnan(low) or math.isnan(high) or low > high:
        raise ValueError(f"bounds must be (low, high) with low <= high, got {bounds!r}")
    if not 0.0 < confidence < 1.0:
        raise ValueError(f"confidence must be in (0, 1), got {confidence!r}")
    if isinstance(resamples, bool) or not isinstance(resamples, int) or resamples < 1:
        raise ValueError(f"resamples must be an integer >= 1, got {resamples!r}")


def _scores(scores: ArrayLike, shapes: dict[int, str]) -> np.ndarray:
    """``scores`` as a float array of one of the ``ndim -> shape name`` of ``shapes``."""
    x = np.asarray(scores, dtype=np.float64)
    if x.ndim not in shapes or x.size == 0:
        raise ValueError(
            f"scores must be a non-empty {' or '.join(shapes.values())} array, got shape {x.shape}"
        )
    if not np.isfinite(x).all():
        raise ValueError("scores must be finite")
    return x


def _percentile_interval(
    scores: np.ndarray,
    statistic: str,
    bounds: tuple[float, float],
    confidence: float,
    resamples: int,
    seed: int,
) -> IntervalEstimate:
    """The stratified bootstrap of ``scores [runs, tasks, points]``: runs resampled within each
    task (the same resampled runs at every point), the statistic over runs and tasks, the
    percentile interval clipped to ``bounds``; each field ``[points]``."""
    runs, tasks, points = scores.shape
    reduce = STATISTICS[statistic]
    estimate = reduce(scores.reshape(runs * tasks, points), 0)
    rng = np.random.default_rng(seed)
    picks = rng.integers(0, runs, size=(resamples, runs, tasks))  # [R, runs, tasks]
    tail = (1.0 - confidence) / 2.0
    ends = np.empty((2, points))
    block = max(1, _MAX_RESAMPLED // (resamples * runs * tasks))
    for start in range(0, points, block):  # a block of points at a time bounds the memory
        part = scores[:, :, start : start + block]
        resampled = part[picks, np.arange(tasks)]  # [R, runs, tasks, block]
        replicates = reduce(resampled.reshape(resamples, runs * tasks, -1), 1)  # [R, block]
        ends[:, start : start + block] = np.quantile(replicates, [tail, 1.0 - tail], axis=0)
    return IntervalEstimate(estimate, np.clip(ends[0], *bounds), np.clip(ends[1], *bounds))


def bootstrap_interval(
    scores: ArrayLike,
    statistic: str = "mean",
    *,
    bounds: tuple[float, float] = (-math.inf, math.inf),
    confidence: float = CONFIDENCE,
    resamples: int = BOOTSTRAP_RESAMPLES,
    seed: int = BOOTSTRAP_SEED,
) -> IntervalEstimate:
    """``statistic`` of ``scores`` and its stratified percentile-bootstrap interval.

    Args:
        scores: ``[runs]`` (one task) or ``[runs, tasks]``, finite.
        statistic: ``"mean"`` or ``"iqm"`` (:func:`interquartile_mean`), over all scores.
        bounds: ``(low, high)``, the values the metric can take; the interval is clipped to it.
        confidence: the interval's coverage, in ``(0, 1)``.
        resamples: bootstrap replicates, >= 1.
        seed: the generator's seed.

    Returns:
        Floats ``(estimate, low, high)``; one run gives ``low == high == estimate``.
    """
    _check_options(statistic, bounds, confidence, resamples)
    x = _scores(scores, {1: "[runs]", 2: "[runs, tasks]"})
    x = x.reshape(x.shape[0], -1, 1)  # [runs, tasks, 1 point]
    estimate, low, high = _percentile_interval(x, statistic, bounds, confidence, resamples, seed)
    return IntervalEstimate(float(estimate[0]), float(low[0]), float(high[0]))


def bootstrap_curve(
    scores: ArrayLike,
    statistic: str = "mean",
    *,
    bounds: tuple[float, float] = (-math.inf, math.inf),
    confidence: float = CONFIDENCE,
    resamples: int = BOOTSTRAP_RESAMPLES,
    seed: int = BOOTSTRAP_SEED,
) -> IntervalEstimate:
    """:func:`bootstrap_interval` at every point of a curve (one task per point).

    Args:
        scores: ``[runs, points]``, each run's value at each point (x) of the curve, finite.
        statistic, bounds, confidence, resamples, seed: as :func:`bootstrap_interval`.

    Returns:
        ``(estimate, low, high)``, each ``[points]``; the interval at every point is the one
        :func:`bootstrap_interval` gives for that point's column.
    """
    _check_options(statistic, bounds, confidence, resamples)
    x = _scores(scores, {2: "[runs, points]"})
    return _percentile_interval(x[:, None, :], statistic, bounds, confidence, resamples, seed)


def student_t_quantile(p: float, df: int) -> float:
    """Quantile of Student's t with ``df`` degrees of freedom (numerical, ~1e-6 accurate).

    The CDF is the integral of the density, 0.5 + int_0^x f (Simpson's rule on 4001 points);
    the quantile is found by bisection.
    """
    if not 0.5 <= p < 1:
        raise ValueError(f"p must be in [0.5, 1), got {p}")
    if df < 1:
        raise ValueError(f"df must be >= 1, got {df}")
    log_c = math.lgamma((df + 1) / 2) - math.lgamma(df / 2) - 0.5 * math.log(df * math.pi)

    def cdf(x: float) -> float:
        grid = np.linspace(0.0, x, 4001)
        f = np.exp(log_c - (df + 1) / 2 * np.log1p(grid**2 / df))
        h = x / 4000
        return 0.5 + h / 3 * (f[0] + f[-1] + 4 * f[1:-1:2].sum() + 2 * f[2:-1:2].sum())

    lo, hi = 0.0, 1.0
    while cdf(hi) < p:
        hi *= 2
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if cdf(mid) < p else (lo, mid)
    return 0.5 * (lo + hi)


def mean_ci95(values: Sequence[float]) -> tuple[float, float]:
    """Mean and half-width of the 95% Student-t confidence interval (0 for one value)."""
    x = np.asarray(values, dtype=float)
    if x.size == 0:
        raise ValueError("values must be non-empty")
    if x.size == 1:
        return float(x[0]), 0.0
    half = student_t_quantile(0.975, x.size - 1) * x.std(ddof=1) / math.sqrt(x.size)
    return float(x.mean()), float(half)
