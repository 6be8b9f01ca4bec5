"""Compare runs: learning curves (mean and 95% confidence band over seeds) and a final-metrics
markdown table, from the ``results.json`` of each run directory."""

from __future__ import annotations

import json
import math
import os
from collections import defaultdict
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from mapets_rl.experiment.config import (
    atomic_savefig,
    atomic_write_text,
    check_writable_dir,
    make_writable_dir,
)
from mapets_rl.experiment.results import read_results


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


def _label(res: dict, multi_env: bool) -> str:
    return f"{res['recipe']} ({res['env']})" if multi_env else res["recipe"]


def compare(run_dirs: Sequence[str | os.PathLike], out_dir: str | os.PathLike,
            metrics: Sequence[str] | None = None) -> dict[str, Path]:
    """Group runs by recipe (and scenario when several), and write to ``out_dir``:

    - ``learning_curves.png``: one panel per metric, x = environment frames, the mean over
      seeds with a shaded 95% Student-t confidence band (at evaluation frames every seed of
      the group reached);
    - ``final_metrics.md``: markdown table of the last evaluation, ``mean ± half-width (n=seeds)``;
    - ``summary.json``: the same numbers, machine-readable.

    Args:
        run_dirs: run directories, each holding ``results.json``.
        out_dir: output directory (created).
        metrics: metric names to show (default: every metric present in all runs); when
            given, at least one.
    Returns:
        ``{"plot": Path, "table": Path, "summary": Path}``.
    Raises:
        ValueError: one line, before anything is written, when a run has no usable results,
            a metric is unknown, ``metrics`` is empty or ``out_dir`` cannot be written.
    """
    if not run_dirs:
        raise ValueError("run_dirs must name at least one run directory")
    if metrics is not None and not list(metrics):
        raise ValueError("metrics must name at least one metric (or None for all common ones)")
    check_writable_dir(out_dir, "out_dir")
    results = [read_results(d) for d in run_dirs]
    for d, res in zip(run_dirs, results, strict=True):
        if not res["evaluations"]:
            raise ValueError(f"run_dir {str(d)!r} has no evaluations yet")
    multi_env = len({r["env"] for r in results}) > 1
    groups: dict[str, list[dict]] = defaultdict(list)
    for res in results:
        groups[_label(res, multi_env)].append(res)
    common = set.intersection(*(set(e["metrics"]) for r in results for e in r["evaluations"]))
    if metrics is None:
        metrics = sorted(common)
        if not metrics:
            raise ValueError("the runs have no metric in common to compare")
    unknown = [m for m in metrics if m not in common]
    if unknown:
        raise ValueError(f"metrics {unknown} are not in every run (available: {sorted(common)})")

    out_dir = make_writable_dir(out_dir, "out_dir")
    summary: dict[str, dict[str, dict[str, float]]] = {}
    for label, runs in groups.items():
        summary[label] = {}
        for m in metrics:
            mean, half = mean_ci95([r["evaluations"][-1]["metrics"][m] for r in runs])
            summary[label][m] = {"mean": mean, "ci95": half, "n": len(runs),
                                 "frames": min(r["evaluations"][-1]["frames"] for r in runs)}

    plot = out_dir / "learning_curves.png"
    _plot(groups, metrics, plot)
    table = out_dir / "final_metrics.md"
    header = "| recipe | frames | " + " | ".join(metrics) + " |"
    lines = [header, "|" + "---|" * (len(metrics) + 2)]
    for label, row in summary.items():
        cells = [f"{row[m]['mean']:.4g} ± {row[m]['ci95']:.2g} (n={row[m]['n']})"
                 for m in metrics]
        frames = row[metrics[0]]["frames"] if metrics else 0
        lines.append(f"| {label} | {frames} | " + " | ".join(cells) + " |")
    atomic_write_text(table, "\n".join(lines) + "\n")
    summary_path = out_dir / "summary.json"
    atomic_write_text(summary_path, json.dumps(summary, indent=1))
    return {"plot": plot, "table": table, "summary": summary_path}


def _plot(groups: dict[str, list[dict]], metrics: Sequence[str], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    n = max(len(metrics), 1)
    cols = min(n, 3)
    rows = math.ceil(n / cols)
    fig, axes = plt.subplots(rows, cols, figsize=(5 * cols, 3.6 * rows), squeeze=False)
    for ax, m in zip(list(axes.flat)[:n], metrics, strict=False):
        for label, runs in groups.items():
            frames = sorted(set.intersection(*({e["frames"] for e in r["evaluations"]}
                                               for r in runs)))
            if not frames:
                continue
            by_frame = [{e["frames"]: e["metrics"][m] for e in r["evaluations"]} for r in runs]
            stats = [mean_ci95([bf[f] for bf in by_frame]) for f in frames]
            mean = np.array([s[0] for s in stats])
            half = np.array([s[1] for s in stats])
            (line,) = ax.plot(frames, mean, marker="o", ms=3, label=f"{label} (n={len(runs)})")
            ax.fill_between(frames, mean - half, mean + half, alpha=0.2, color=line.get_color())
        ax.set_title(m)
        ax.set_xlabel("environment frames")
        ax.grid(alpha=0.3)
    for ax in list(axes.flat)[n:]:
        ax.set_visible(False)
    axes.flat[0].legend(fontsize=8)
    fig.tight_layout()
    atomic_savefig(fig, path, dpi=110)
    plt.close(fig)
