"""The rliable protocol's comparisons of methods over their runs' final values, what
``mapets-rl compare`` writes as ``rliable.md``, ``rliable.json`` and
``performance_profiles.png`` (Agarwal et al. 2021, "Deep RL at the Edge of the Statistical
Precipice"; :mod:`mapets_rl.statistics`):

- *performance profiles*: per metric and group, the fraction of the group's runs whose final
  value is above ``tau``, on :data:`PROFILE_POINTS` thresholds from the smallest to the largest
  final value of any group (one when every run ends on the same value), with its
  stratified-bootstrap 95% band;
- *optimality gap*: per metric with a threshold ``gamma`` and group, the mean over the group's
  runs of ``max(gamma - final value, 0)``, how far its runs fall short of ``gamma``, with its
  stratified-bootstrap 95% interval; ``gamma`` is given per metric (``compare``'s
  ``optimality_thresholds``, ``--optimality-gap METRIC=GAMMA``) or, by default, the top of the
  metric's range where it has one (:func:`~mapets_rl.metrics.metric_range`: safety 1, comfort
  3); a metric with neither has no gap;
- *probability of improvement*: per metric and ordered pair of groups ``(X, Y)``, P(X > Y),
  the probability that a run of X ends above a run of Y (ties count one half; the
  Mann-Whitney U statistic over the number of pairs), with its bootstrap 95% interval.

A comparison is over one scenario (one task in rliable's terms), so no averaging over tasks
takes place here. "Above" is the metric's value, not its merit: for a metric where lower is
better (``collisions``) P(X > Y) near 1 says X collides more, and its optimality gap below a
``gamma`` measures how far it stays under it. Intervals are given only where
each group has at least :data:`~mapets_rl.statistics.MIN_RUNS_FOR_INTERVAL` runs (the
bootstrap interval of two runs is their range); below that the estimate stands alone.
"""

from __future__ import annotations

import math
import numbers
import textwrap
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from mapets_rl.experiment.files import atomic_savefig
from mapets_rl.metrics import metric_label, metric_range
from mapets_rl.plotting import draw_band
from mapets_rl.statistics import (
    MIN_RUNS_FOR_INTERVAL,
    optimality_gap,
    performance_profile,
    probability_of_improvement,
)

PROFILE_POINTS = 101
"""Thresholds ``tau`` of a performance profile (``curves`` of ``rliable.json``)."""
TABLE_TAUS = 5
"""Thresholds of the profile table in ``rliable.md``: evenly spaced on the grid, its ends
included."""


def gap_thresholds(
    metrics: Sequence[str], given: Mapping[str, float] | None = None
) -> dict[str, float]:
    """The optimality gap's ``gamma`` of every metric that has one: ``given[metric]``, else the
    top of the metric's range where it is finite (safety 1). ValueError naming the metric when
    ``given`` names one not compared or a value that is not a finite number."""
    given = dict(given or {})
    unknown = sorted(set(given) - set(metrics))
    if unknown:
        raise ValueError(
            f"optimality_thresholds names {unknown}, which are not compared (compared: "
            f"{list(metrics)})"
        )
    out = {}
    for metric in metrics:
        if metric in given:
            gamma = given[metric]
            real = isinstance(gamma, numbers.Real) and not isinstance(gamma, bool)
            if not (real and math.isfinite(gamma)):
                raise ValueError(
                    f"optimality_thresholds[{metric!r}] must be a finite number, got {gamma!r}"
                )
            out[metric] = float(gamma)
        elif math.isfinite(metric_range(metric)[1]):
            out[metric] = metric_range(metric)[1]
    return out


def rliable_summary(
    finals: Mapping[str, Mapping[str, Sequence[float]]],
    metrics: Sequence[str],
    thresholds: Mapping[str, float] | None = None,
) -> dict[str, Any]:
    """Performance profiles, optimality gaps and probabilities of improvement of the groups'
    final values.

    Args:
        finals: group label -> metric -> the final value of each of its runs.
        metrics: the metrics compared, each in every group.
        thresholds: metric -> the optimality gap's ``gamma``; a metric left out takes the top
            of its range where finite (:func:`gap_thresholds`).

    Returns:
        ``{metric: {"taus": [...], "profiles": {group: {"n", "fraction", "ci95"}},
        "optimality_gap": {"gamma", "groups": {group: {"n", "gap", "ci95"}}} or None,
        "probability_of_improvement": [{"x", "y", "n_x", "n_y", "p", "ci95"}, ...]}}``:
        ``fraction`` ``[taus]``, ``ci95`` ``[[low, high] per tau]`` (``None`` below
        :data:`~mapets_rl.statistics.MIN_RUNS_FOR_INTERVAL` runs); ``gap`` the mean shortfall
        below ``gamma`` and its ``ci95`` ``[low, high]`` (``None`` below that many runs;
        ``optimality_gap`` ``None`` for a metric without ``gamma``); one pair entry per ordered
        pair of different groups, ``p`` = P(X > Y) and its ``ci95`` ``[low, high]`` (``None``
        when either group has fewer runs than that).
    """
    labels = list(finals)
    gammas = gap_thresholds(metrics, thresholds)
    out: dict[str, Any] = {}
    for metric in metrics:
        values = {label: np.asarray(finals[label][metric], dtype=float) for label in labels}
        pooled = np.concatenate(list(values.values()))
        taus = np.unique(np.linspace(pooled.min(), pooled.max(), PROFILE_POINTS))
        profiles = {}
        for label, runs in values.items():
            fraction, low, high = performance_profile(runs, taus)
            banded = len(runs) >= MIN_RUNS_FOR_INTERVAL
            profiles[label] = {
                "n": len(runs),
                "fraction": [float(f) for f in fraction],
                "ci95": [[float(a), float(b)] for a, b in zip(low, high, strict=True)]
                if banded
                else None,
            }
        pairs = []
        for x in labels:
            for y in labels:
                if x == y:
                    continue
                p, low, high = probability_of_improvement(values[x], values[y])
                banded = min(len(values[x]), len(values[y])) >= MIN_RUNS_FOR_INTERVAL
                pairs.append(
                    {
                        "x": x,
                        "y": y,
                        "n_x": len(values[x]),
                        "n_y": len(values[y]),
                        "p": p,
                        "ci95": [low, high] if banded else None,
                    }
                )
        gap = None
        if metric in gammas:
            gap = {"gamma": gammas[metric], "groups": {}}
            for label, runs in values.items():
                estimate, low, high = optimality_gap(runs, gammas[metric])
                gap["groups"][label] = {
                    "n": len(runs),
                    "gap": estimate,
                    "ci95": [low, high] if len(runs) >= MIN_RUNS_FOR_INTERVAL else None,
                }
        out[metric] = {
            "taus": [float(t) for t in taus],
            "profiles": profiles,
            "optimality_gap": gap,
            "probability_of_improvement": pairs,
        }
    return out


def _table_taus(count: int) -> list[int]:
    """Indices of :data:`TABLE_TAUS` evenly spaced thresholds of a grid of ``count``, without
    repeats (a grid of one threshold: one)."""
    return sorted({round(k * (count - 1) / (TABLE_TAUS - 1)) for k in range(TABLE_TAUS)})


def _cell(value: float, interval: Sequence[float] | None) -> str:
    return (
        f"{value:.3g}"
        if interval is None
        else f"{value:.3g} [{interval[0]:.3g}, {interval[1]:.3g}]"
    )


def rliable_table(summary: Mapping[str, Any]) -> str:
    """The markdown of :func:`rliable_summary`: per metric, the performance profile at a few
    thresholds (one row per group), the optimality gap of every group (where the metric has a
    ``gamma``) and the probability of improvement of every row's group over every column's."""
    lines = [
        "rliable protocol (Agarwal et al. 2021) over each run's final value, the runs of a "
        "group being its seeds: performance profile = fraction of runs above tau; optimality "
        "gap = mean over runs of max(gamma - value, 0); P(X > Y) = "
        "probability that a run of the row's group ends above a run of the column's (ties "
        "count 1/2; higher is not better for every metric, e.g. collisions). 95% bootstrap "
        f"intervals where every group compared has at least {MIN_RUNS_FOR_INTERVAL} runs (n)."
    ]
    for metric, part in summary.items():
        taus = part["taus"]
        shown = _table_taus(len(taus))
        lines += [
            "",
            f"Performance profile of {metric_label(metric)}: fraction of runs above tau",
            "",
            "| group | n | " + " | ".join(f"tau = {taus[i]:.4g}" for i in shown) + " |",
            "|" + "---|" * (len(shown) + 2),
        ]
        for label, profile in part["profiles"].items():
            cells = [
                _cell(profile["fraction"][i], profile["ci95"][i] if profile["ci95"] else None)
                for i in shown
            ]
            lines.append(f"| {label} | {profile['n']} | " + " | ".join(cells) + " |")
        gap = part["optimality_gap"]
        if gap is not None:
            lines += [
                "",
                f"Optimality gap of {metric_label(metric)} below gamma = {gap['gamma']:.4g}: "
                "mean over runs of max(gamma - value, 0)",
                "",
                "| group | n | optimality gap |",
                "|---|---|---|",
            ]
            lines += [
                f"| {label} | {row['n']} | {_cell(row['gap'], row['ci95'])} |"
                for label, row in gap["groups"].items()
            ]
        labels = list(part["profiles"])
        if len(labels) < 2:
            continue
        by_pair = {(p["x"], p["y"]): p for p in part["probability_of_improvement"]}
        lines += [
            "",
            f"Probability of improvement of {metric_label(metric)}: P(row > column)",
            "",
            "| X \\ Y | " + " | ".join(labels) + " |",
            "|" + "---|" * (len(labels) + 1),
        ]
        for x in labels:
            cells = [
                "" if x == y else _cell(by_pair[x, y]["p"], by_pair[x, y]["ci95"]) for y in labels
            ]
            lines.append(f"| {x} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def plot_profiles(summary: Mapping[str, Any], path: Path, title: str | None = None) -> None:
    """``performance_profiles.png``: one panel per metric, every group's profile (fraction of
    runs above tau) with its stratified-bootstrap 95% band (none below
    :data:`~mapets_rl.statistics.MIN_RUNS_FOR_INTERVAL` runs), the y axis in [0, 1]."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    n = max(len(summary), 1)
    cols = min(n, 3)
    rows = math.ceil(n / cols)
    fig, axes = plt.subplots(
        rows, cols, figsize=(5 * cols, 3.6 * rows + 0.5), squeeze=False, layout="constrained"
    )
    for ax, (metric, part) in zip(axes.flat, summary.items(), strict=False):
        for label, profile in part["profiles"].items():
            band = profile["ci95"]
            draw_band(
                ax,
                part["taus"],
                profile["fraction"],
                [lo for lo, _ in band] if band else None,
                [hi for _, hi in band] if band else None,
                bounds=(0.0, 1.0),
                label=f"{label} (n={profile['n']})",
            )
        ax.set_ylim(0.0, 1.0)
        ax.set_xlabel(f"tau: {metric_label(metric)}")
        ax.set_ylabel("fraction of runs > tau")
        ax.grid(alpha=0.3)
    for ax in list(axes.flat)[n:]:
        ax.set_visible(False)
    axes.flat[0].legend(fontsize=8)
    heading = (
        "performance profiles of the runs' final values (bootstrap 95% band for groups of "
        f">= {MIN_RUNS_FOR_INTERVAL} runs)"
    )
    fig.suptitle(textwrap.fill(f"{title}: {heading}" if title else heading, 55 * cols), fontsize=10)
    atomic_savefig(fig, path, dpi=110)
    plt.close(fig)
