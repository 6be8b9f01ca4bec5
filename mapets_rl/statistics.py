"""Summary statistics over runs (seeds): the mean with its 95% Student-t confidence interval.

The ground floor: numpy only, nothing of the project, so every floor may use it.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np


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


def mean_std_ci95(values: Sequence[float]) -> tuple[float, float, float]:
    """Mean, sample standard deviation (ddof 1; 0 for one value) and the 95% Student-t
    half-width (0 for one value)."""
    mean, half = mean_ci95(values)
    std = float(np.std(np.asarray(values, dtype=float), ddof=1)) if len(values) > 1 else 0.0
    return mean, std, half
