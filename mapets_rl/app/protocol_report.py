"""The evaluation protocol over seeds: what ``mapets-rl compare`` writes as ``protocol.md`` and
``protocol.json`` when its runs were scored by ``mapets-rl evaluate RUN --roads B``
(:mod:`mapets_rl.experiment.protocol`).

Per group of runs (the groups of ``compare``) and reference policy: each seed's gain over the
reference on its own evaluation roads, their mean with a percentile-bootstrap 95% interval and
their interquartile mean with a stratified-bootstrap one (no interval below three seeds: each
seed's gain is shown instead); the mean system reward per episode;
the training return (the Shapley paper's Fig. 2 quantity: the mean system return of the
training episodes in the last :data:`TRAINING_WINDOW` of each run's frames); the behaviour
metrics (the scenario's episode metrics, mean over seeds). Each reference's own row (mean over
the same seeds' roads) is printed first.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from mapets_rl.experiment.episodes import read_train_episodes
from mapets_rl.experiment.protocol import read_protocol
from mapets_rl.statistics import MIN_RUNS_FOR_INTERVAL, bootstrap_interval, interquartile_mean

TRAINING_WINDOW = 0.1
"""The share of a run's frames, at its end, whose training episodes give its training return."""


def read_protocols(run_dirs: Sequence[str]) -> list[dict[str, Any]] | None:
    """The protocol result of every run, or None when one of them has none. ValueError when
    they were scored on different road counts or references."""
    results = [read_protocol(run) for run in run_dirs]
    if any(r is None for r in results):
        return None
    shapes = {(r["roads"], tuple(sorted(r["references"]))) for r in results}
    if len(shapes) > 1:
        raise ValueError(
            "the runs were scored by the protocol on different roads or references "
            f"({sorted(shapes)}): score them alike with mapets-rl evaluate RUN --roads B "
            "--references ..."
        )
    return results


def training_return(run_dir: str) -> float:
    """The mean system return of the training episodes that ended in the last
    :data:`TRAINING_WINDOW` of the run's frames (NaN without any)."""
    episodes = read_train_episodes(run_dir)
    frames = episodes["frames"]
    if not len(frames):
        return float("nan")
    late = frames > frames.max() * (1.0 - TRAINING_WINDOW)
    return float(np.mean(episodes["system_return"][late]))


def _gains(results: Sequence[Mapping[str, Any]], reference: str) -> np.ndarray:
    return np.array([r["gain_percent"][reference] for r in results], dtype=np.float64)


def _interval(values: np.ndarray) -> dict[str, Any]:
    """Mean and IQM of ``values`` (one per seed), each with its bootstrap 95% interval (null
    below :data:`~mapets_rl.statistics.MIN_RUNS_FOR_INTERVAL` seeds: the interval of two is
    their range; with fewer than 4 seeds the IQM is the mean)."""
    if len(values) < MIN_RUNS_FOR_INTERVAL:
        return {
            "mean": float(np.mean(values)),
            "mean_ci95": None,
            "iqm": interquartile_mean(values),
            "iqm_ci95": None,
        }
    mean, low, high = bootstrap_interval(values)
    iqm, iqm_low, iqm_high = bootstrap_interval(values, statistic="iqm")
    return {"mean": mean, "mean_ci95": [low, high], "iqm": iqm, "iqm_ci95": [iqm_low, iqm_high]}


def protocol_summary(
    groups: Mapping[str, Sequence[str]], results: Mapping[str, Mapping[str, Any]]
) -> dict[str, Any]:
    """``{"references": {name: {system_reward, metrics}}, "groups": {label: {...}}}`` over the
    runs of each group (``groups``: label -> run dirs; ``results``: run dir -> its protocol
    result, :func:`read_protocols`)."""
    every = [results[run] for runs in groups.values() for run in runs]
    names = sorted(every[0]["references"])
    references = {}
    for name in names:
        rows = [r["references"][name] for r in every]
        references[name] = {
            "system_reward": float(np.mean([row["system_reward_mean"] for row in rows])),
            "metrics": _mean_metrics([row["metrics"] for row in rows]),
        }
    out: dict[str, Any] = {"references": references, "groups": {}}
    for label, runs in groups.items():
        rows = [results[run] for run in runs]
        gains = {name: _gains(rows, name) for name in names}
        out["groups"][label] = {
            "runs": list(runs),
            "seeds": [r["seed"] for r in rows],
            "frames": [r["frames"] for r in rows],
            "system_reward": float(np.mean([r["policy"]["system_reward_mean"] for r in rows])),
            "training_return": float(np.mean([training_return(run) for run in runs])),
            "gain_percent": {
                name: {"per_seed": values.tolist(), **_interval(values)}
                for name, values in gains.items()
            },
            "metrics": _mean_metrics([r["policy"]["metrics"] for r in rows]),
        }
    return out


def _mean_metrics(rows: Sequence[Mapping[str, float]]) -> dict[str, float]:
    """The mean of every metric the rows share."""
    shared = set.intersection(*(set(row) for row in rows))
    return {key: float(np.mean([row[key] for row in rows])) for key in sorted(shared)}


def protocol_table(summary: Mapping[str, Any], roads: int) -> str:
    """The markdown of :func:`protocol_summary`: one row per reference, then one per group."""
    names = list(summary["references"])
    metric_names = sorted(
        set.intersection(
            *(set(row["metrics"]) for row in summary["references"].values()),
            *(set(row["metrics"]) for row in summary["groups"].values()),
        )
    )
    head = (
        "| policy | seeds | system reward / episode | training return | "
        + " | ".join(f"vs {name}: mean [95%] / IQM / per seed" for name in names)
        + " | "
        + " | ".join(metric_names)
        + " |"
    )
    lines = [
        f"Greedy policies on {roads} evaluation roads per seed (each seed's own roads, the same "
        "for every policy); gain = system reward over the reference's on the same roads, in "
        "percent; training return = mean system return of the training episodes in the last "
        f"{TRAINING_WINDOW:.0%} of each run's frames. A group of fewer than "
        f"{MIN_RUNS_FOR_INTERVAL} seeds has no interval (the bootstrap interval of two seeds is "
        "their range): its mean gain, then each seed's in parentheses.",
        "",
        head,
        "|" + "---|" * (4 + len(names) + len(metric_names)),
    ]
    for name, row in summary["references"].items():
        gains = ["0" if other == name else "" for other in names]
        cells = [f"{row['metrics'][m]:.3g}" for m in metric_names]
        lines.append(
            f"| {name} (reference) | | {row['system_reward']:.1f} | | "
            + " | ".join(gains)
            + " | "
            + " | ".join(cells)
            + " |"
        )
    for label, row in summary["groups"].items():
        gains = [_gain_cell(row["gain_percent"][name]) for name in names]
        cells = [f"{row['metrics'][m]:.3g}" for m in metric_names]
        lines.append(
            f"| {label} | {len(row['seeds'])} | {row['system_reward']:.1f} | "
            f"{row['training_return']:.1f} | "
            + " | ".join(gains)
            + " | "
            + " | ".join(cells)
            + " |"
        )
    return "\n".join(lines) + "\n"


def _gain_cell(gain: Mapping[str, Any]) -> str:
    per_seed = ", ".join(f"{g:+.1f}" for g in gain["per_seed"])
    if gain["mean_ci95"] is None:
        return f"{gain['mean']:+.1f}% ({per_seed})"
    low, high = gain["mean_ci95"]
    return f"{gain['mean']:+.1f}% [{low:+.1f}, {high:+.1f}] / {gain['iqm']:+.1f}% / {per_seed}"
