"""Interval estimates over independent runs (seeds): the mean with a percentile-bootstrap 95%
interval, the interquartile mean (IQM) with a stratified-bootstrap 95% interval, performance
profiles, the optimality gap and the probability of improvement, on :mod:`scipy.stats`.

The protocol is that of Agarwal et al. (2021), "Deep Reinforcement Learning at the Edge of the
Statistical Precipice" (NeurIPS). Their ``rliable`` package pins ``arch == 5.3.0`` and
pulls in seaborn (with pandas) and absl-py for a few statistics, which stand here on
:func:`scipy.stats.bootstrap` (resampling, percentile intervals),
:func:`scipy.stats.mannwhitneyu` and :data:`scipy.stats.t`:

- *scores* are ``[runs]`` (one task) or ``[runs, tasks]`` (the same runs' score on each task);
- the *IQM* is the mean of the middle 50% of all scores: the ``floor(n / 4)`` lowest and highest
  of the ``n`` scores are dropped (``scipy.stats.trim_mean(scores, 0.25)``, rliable's
  definition), so it is robust to an outlying run and, unlike the median, uses half the runs;
  with fewer than 4 scores nothing is dropped and it is the mean;
- the *stratified bootstrap* resamples the runs with replacement independently within each
  task (each task one sample of :func:`scipy.stats.bootstrap`), recomputes the statistic over
  every resampled score, and takes the 2.5th and 97.5th percentiles of the ``resamples``
  replicates as the 95% interval (the percentile bootstrap; with one task it is the ordinary
  bootstrap over runs);
- the *performance profile* (:func:`performance_profile`) is the fraction of all scores above
  each threshold ``tau``, with the stratified bootstrap's band;
- the *optimality gap* (:func:`optimality_gap`) is the mean over all scores of how far each
  falls short of a threshold ``gamma``, ``max(gamma - score, 0)``, with the stratified
  bootstrap's interval;
- the *probability of improvement* (:func:`probability_of_improvement`) P(X > Y) is, per task,
  the Mann-Whitney U statistic of X's runs over Y's divided by the number of pairs (ties count
  one half), averaged over tasks; its interval resamples X's and Y's runs independently.

The generator is seeded (:data:`BOOTSTRAP_SEED`): the same scores give the same interval every
time (and, with one task, the same interval as this module's numpy bootstrap before it moved
onto scipy: the same runs are resampled). Intervals are clipped to ``bounds``, the values the
metric can take (:func:`mapets_rl.metrics.metric_range`: safety in ``[0, 1]``, speeds and
counts ``>= 0``).

With few runs read the intervals with care: a bootstrap interval never reaches beyond the
sample's smallest and largest value, so with 3 seeds it is narrower than the uncertainty (it
holds the mean of 3 normal draws about 75% of the time, not 95%); with 2 it is their range
(``compare`` draws none below :data:`MIN_RUNS_FOR_INTERVAL` runs).

The Student-t interval of the mean (:func:`mean_ci95`) stays for the examples and benchmarks
that report it.
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Callable, Sequence
from typing import NamedTuple

import numpy as np
from numpy.typing import ArrayLike
from scipy import stats

BOOTSTRAP_RESAMPLES = 5000
"""Bootstrap replicates per interval: the interval's ends move by about 1% of its width between
generator seeds."""
BOOTSTRAP_SEED = 0
"""Seed of the bootstrap's generator (reproducible intervals)."""
CONFIDENCE = 0.95
"""Coverage of the intervals."""
MIN_RUNS_FOR_INTERVAL = 3
"""Fewest runs whose bootstrap interval is shown as one: with 2 runs the percentile interval is
their range, so ``compare`` and :mod:`mapets_rl.plotting` show the runs' values instead."""
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


def _stratified_bootstrap(
    scores: np.ndarray,
    reduce: Callable[[np.ndarray, int], np.ndarray],
    bounds: tuple[float, float],
    confidence: float,
    resamples: int,
    seed: int,
) -> IntervalEstimate:
    """The stratified bootstrap of ``scores [runs, tasks, points]`` on
    :func:`scipy.stats.bootstrap`: each task's runs are one sample, resampled independently of
    the other tasks' (the same resampled runs at every point), ``reduce(scores, axis)`` over the
    runs of every task together, the percentile interval clipped to ``bounds``; each field
    ``[points]``. One run has no interval (``low == high ==`` the estimate, clipped)."""
    runs, tasks, points = scores.shape
    estimate = reduce(scores.reshape(runs * tasks, points), 0)
    if runs == 1:
        clipped = np.clip(estimate, *bounds)
        return IntervalEstimate(estimate, clipped, clipped.copy())

    def statistic(*samples: np.ndarray, axis: int) -> np.ndarray:
        return reduce(np.concatenate(samples, axis=axis), axis)

    ends = np.empty((2, points))
    block = max(1, _MAX_RESAMPLED // (resamples * runs * tasks))
    for start in range(0, points, block):  # a block of points at a time bounds the memory
        part = scores[:, :, start : start + block]
        result = stats.bootstrap(
            tuple(part[:, task, :].T for task in range(tasks)),  # per task [block, runs]
            statistic,
            n_resamples=resamples,
            vectorized=True,
            axis=-1,
            confidence_level=confidence,
            method="percentile",
            rng=np.random.default_rng(seed),  # every block resamples the same runs
        )
        ends[0, start : start + block] = result.confidence_interval.low
        ends[1, start : start + block] = result.confidence_interval.high
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
    estimate, low, high = _stratified_bootstrap(
        x, STATISTICS[statistic], bounds, confidence, resamples, seed
    )
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
    return _stratified_bootstrap(
        x[:, None, :], STATISTICS[statistic], bounds, confidence, resamples, seed
    )


def performance_profile(
    scores: ArrayLike,
    taus: ArrayLike,
    *,
    confidence: float = CONFIDENCE,
    resamples: int = BOOTSTRAP_RESAMPLES,
    seed: int = BOOTSTRAP_SEED,
) -> IntervalEstimate:
    """The performance profile (score distribution) of Agarwal et al. (2021): at every
    threshold ``tau``, the fraction of all runs' scores above ``tau`` (over runs and tasks),
    with its stratified-bootstrap interval (the same resampled runs at every ``tau``).

    Args:
        scores: ``[runs]`` (one task) or ``[runs, tasks]``, finite.
        taus: ``[points]``, the thresholds, finite.
        confidence, resamples, seed: as :func:`bootstrap_interval`.

    Returns:
        ``(estimate, low, high)``, each ``[points]`` in ``[0, 1]``; one run gives no width.
    """
    _check_options("mean", (0.0, 1.0), confidence, resamples)
    x = _scores(scores, {1: "[runs]", 2: "[runs, tasks]"})
    t = np.asarray(taus, dtype=np.float64)
    if t.ndim != 1 or t.size == 0 or not np.isfinite(t).all():
        raise ValueError(f"taus must be a non-empty finite [points] array, got {taus!r}")
    above = (x.reshape(x.shape[0], -1, 1) > t).astype(np.float64)  # [runs, tasks, points]
    return _stratified_bootstrap(above, STATISTICS["mean"], (0.0, 1.0), confidence, resamples, seed)


def optimality_gap(
    scores: ArrayLike,
    threshold: float,
    *,
    confidence: float = CONFIDENCE,
    resamples: int = BOOTSTRAP_RESAMPLES,
    seed: int = BOOTSTRAP_SEED,
) -> IntervalEstimate:
    """The optimality gap of Agarwal et al. (2021): the mean over all runs' scores (runs and
    tasks) of ``max(threshold - score, 0)``, how far the scores fall short of ``threshold``
    (rliable's ``gamma``; a score above it counts as reaching it, not as making up for
    another's shortfall), with its stratified-bootstrap interval.

    Args:
        scores: ``[runs]`` (one task) or ``[runs, tasks]``, finite.
        threshold: ``gamma``, the score counted as good enough, finite.
        confidence, resamples, seed: as :func:`bootstrap_interval`.

    Returns:
        Floats ``(estimate, low, high)``, each ``>= 0``; one run gives ``low == high ==``
        the estimate.
    """
    _check_options("mean", (0.0, math.inf), confidence, resamples)
    x = _scores(scores, {1: "[runs]", 2: "[runs, tasks]"})
    real = isinstance(threshold, numbers.Real) and not isinstance(threshold, bool)
    if not (real and math.isfinite(threshold)):
        raise ValueError(f"threshold must be a finite number, got {threshold!r}")
    shortfall = np.maximum(threshold - x, 0.0).reshape(x.shape[0], -1, 1)  # [runs, tasks, 1]
    estimate, low, high = _stratified_bootstrap(
        shortfall, STATISTICS["mean"], (0.0, math.inf), confidence, resamples, seed
    )
    return IntervalEstimate(float(estimate[0]), float(low[0]), float(high[0]))


def _improvement(x: Sequence[np.ndarray], y: Sequence[np.ndarray], axis: int) -> np.ndarray:
    """P(X > Y) of the tasks' samples ``x[task]`` and ``y[task]`` along ``axis``: per task the
    Mann-Whitney U statistic of X over Y divided by the number of pairs, the mean over tasks."""
    per_task = [
        stats.mannwhitneyu(a, b, axis=axis, method="asymptotic").statistic
        / (a.shape[axis] * b.shape[axis])
        for a, b in zip(x, y, strict=True)
    ]
    return np.mean(per_task, axis=0)


def probability_of_improvement(
    scores_x: ArrayLike,
    scores_y: ArrayLike,
    *,
    confidence: float = CONFIDENCE,
    resamples: int = BOOTSTRAP_RESAMPLES,
    seed: int = BOOTSTRAP_SEED,
) -> IntervalEstimate:
    """The probability of improvement P(X > Y) of Agarwal et al. (2021) and its bootstrap
    interval.

    On each task, the probability that a run of X scores above a run of Y, ties counting one
    half: the Mann-Whitney U statistic of X over Y (:func:`scipy.stats.mannwhitneyu`) divided
    by ``runs_x * runs_y``; then the mean over tasks. The interval resamples the runs of X and
    of Y independently within each task (rliable's stratified independent bootstrap).

    Args:
        scores_x: ``[runs_x]`` or ``[runs_x, tasks]``, finite.
        scores_y: ``[runs_y]`` or ``[runs_y, tasks]``, the same tasks, finite.
        confidence, resamples, seed: as :func:`bootstrap_interval`.

    Returns:
        Floats ``(estimate, low, high)`` in ``[0, 1]``; without an interval
        (``low == high == estimate``) when either side has one run.
    """
    _check_options("mean", (0.0, 1.0), confidence, resamples)
    x = _scores(scores_x, {1: "[runs]", 2: "[runs, tasks]"})
    y = _scores(scores_y, {1: "[runs]", 2: "[runs, tasks]"})
    x, y = x.reshape(x.shape[0], -1), y.reshape(y.shape[0], -1)
    if x.shape[1] != y.shape[1]:
        raise ValueError(
            f"scores_x and scores_y must have the same tasks, got {x.shape[1]} and {y.shape[1]}"
        )
    tasks = x.shape[1]
    estimate = float(_improvement(list(x.T), list(y.T), axis=-1))
    if min(len(x), len(y)) == 1:
        return IntervalEstimate(estimate, estimate, estimate)

    def statistic(*samples: np.ndarray, axis: int) -> np.ndarray:
        return _improvement(samples[:tasks], samples[tasks:], axis)

    result = stats.bootstrap(
        (*x.T, *y.T),
        statistic,
        n_resamples=resamples,
        vectorized=True,
        confidence_level=confidence,
        method="percentile",
        rng=np.random.default_rng(seed),
    )
    low, high = result.confidence_interval
    return IntervalEstimate(estimate, float(low), float(high))


def mean_ci95(values: Sequence[float]) -> tuple[float, float]:
    """Mean and half-width of the 95% Student-t confidence interval (0 for one value): the
    t quantile from :data:`scipy.stats.t`."""
    x = np.asarray(values, dtype=float)
    if x.size == 0:
        raise ValueError("values must be non-empty")
    if x.size == 1:
        return float(x[0]), 0.0
    half = stats.t.ppf(0.975, x.size - 1) * x.std(ddof=1) / math.sqrt(x.size)
    return float(x.mean()), float(half)
