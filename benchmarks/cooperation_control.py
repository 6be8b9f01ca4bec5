"""Fig. 2's comparison on ``freeway-merge``: published configurations trained per seed, each
run's greedy policy scored beside the reference policies on the same evaluation roads.

Each arm is a published configuration (``mapets-rl configs``; the table of
``docs/results/shapley.md``: ``freeway-merge/maddpg-individual``, ``maddpg-team``,
``shapley-arm``, ``mappo``, ``coma``), trained per seed as ``mapets-rl train --config NAME
--seed S`` would (``key=value`` arguments override every arm), then scored by the library's
protocol, what ``mapets-rl evaluate RUN --roads 256 --references keep-lane cooperative-merge``
prints. ``--explored`` also scores an epsilon-greedy arm's final collection policy.

Resumable (runs and scores are kept under ``--out``; one seed per process, then one call with
every seed prints the tables):

    OMP_NUM_THREADS=1 MAPETS_RL_THREADS=1 python benchmarks/cooperation_control.py \\
        --configs freeway-merge/maddpg-individual freeway-merge/shapley-arm \\
        --seeds 0 1 2 3 4 --out outputs/cooperation_control

Prints, and writes to ``<out>/control.md`` and ``.json``: per arm the system reward, the gain
over keep lane per seed and its mean [bootstrap 95% over seeds], the behaviour metrics per
episode; then each run's training episodes in windows of ``--window-frames``.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tensordict.nn import TensorDictSequential
from torchrl.envs.utils import ExplorationType

from mapets_rl.app.plugins import load_recipe
from mapets_rl.experiment import atomic_write_text, latest_checkpoint, read_train_episodes
from mapets_rl.experiment.protocol import (
    ROAD_EVAL_SEED_OFFSET,
    evaluate_protocol,
    score_roads,
)
from mapets_rl.experiment.published import load_published
from mapets_rl.machine import machine_line
from mapets_rl.statistics import bootstrap_interval

REFERENCES = ("keep-lane", "cooperative-merge")
METRICS = ("ramp_stuck", "mainline_changes_near_merge", "mainline_changes_elsewhere",
           "ramp_forced_merges", "collisions", "shielded", "average_comfort")  # fmt: skip
"""The behaviour columns: the scenario's episode metrics, per episode."""


def run_dir(out: Path, name: str, seed: int) -> Path:
    """Where the run of the published config ``name`` at ``seed`` is kept."""
    return out / "runs" / f"{name.replace('/', '__')}_seed{seed}"


def trained(name: str, seed: int, args: argparse.Namespace) -> Path:
    """The run of the published config ``name`` at ``seed``, trained (or its training
    finished, ``total_frames=`` overrides applied) under ``--out``."""
    published = load_published(name)
    cls, path = load_recipe(published.recipe), run_dir(Path(args.out), name, seed)
    if latest_checkpoint(path) is None:
        overrides = [f"seed={seed}", *args.overrides]
        config = cls.Config.from_fields(published.fields, overrides, name)
        cls(config, path).train()
        return path
    budget = [o for o in args.overrides if o.startswith("total_frames=")]
    exp = cls.from_run_dir(path, overrides=budget)
    if exp.frames < exp.config.total_frames:
        exp.train()
    exp.close()
    return path


def scores(name: str, path: Path, args: argparse.Namespace) -> dict[str, Any]:
    """The protocol's result for the newest checkpoint of ``path`` (with ``--explored``, the
    key ``explored``: the scores of its collection policy), cached in ``<out>/evals/``."""
    cache = Path(args.out) / "evals" / f"{path.name}_{args.roads}roads.json"
    newest = latest_checkpoint(path).name
    kept = json.loads(cache.read_text()) if cache.is_file() else {}
    if kept.get("checkpoint") == newest and (not args.explored or "explored" in kept):
        return kept
    exp = load_recipe(load_published(name).recipe).from_run_dir(path)
    try:
        result = {**evaluate_protocol(exp, args.roads, REFERENCES), "checkpoint": newest}
        if args.explored and getattr(exp.config, "exploration", None) == "epsilon":
            torch.manual_seed(exp.config.seed + ROAD_EVAL_SEED_OFFSET)  # the random moves
            policy = TensorDictSequential(exp.eval_policy, exp.exploration)
            explored = score_roads(
                exp.config, lambda env: policy, args.roads, ExplorationType.RANDOM
            )
            result["explored"] = explored.to_json()
    finally:
        exp.close()
    cache.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_text(cache, json.dumps(result))
    return result


def row(label: str, runs: list[dict], keep: list[dict]) -> tuple[str, dict[str, Any]]:
    """One table row (and its fields) of ``runs`` (one score per seed) against keep lane's
    scores on the same roads."""
    gains = [
        100.0 * (r["system_reward_mean"] / k["system_reward_mean"] - 1.0)
        for r, k in zip(runs, keep, strict=True)
    ]
    mean, low, high = bootstrap_interval(gains)
    fields = {
        "gain_percent_per_seed": gains,
        "gain_percent_mean": float(mean),
        "gain_percent_ci95": [float(low), float(high)],
        "system_reward": float(np.mean([r["system_reward_mean"] for r in runs])),
    }
    fields.update({k: float(np.mean([r["metrics"].get(k, np.nan) for r in runs])) for k in METRICS})
    cells = [
        f"{fields['system_reward']:.1f}",
        f"{mean:+.1f}% [{low:+.1f}, {high:+.1f}]",
        ", ".join(f"{g:+.1f}" for g in gains),
        *(f"{fields[k]:.2f}" for k in METRICS),
    ]
    return f"| {label} | " + " | ".join(cells) + " |", fields


def windows(path: Path, width: int) -> str:
    """The run's training episodes (the Shapley paper's Fig. 2 quantity) in windows of
    ``width`` frames: mean system return / ramp vehicles stuck per episode."""
    episodes = read_train_episodes(path)
    if not len(episodes["frames"]):
        return ""
    bins = (episodes["frames"] - 1) // width
    stuck = episodes.get("ramp_stuck", np.full(len(bins), np.nan))
    cells = []
    for index in range(int(bins.max()) + 1):
        inside = bins == index
        mean = episodes["system_return"][inside].mean() if inside.any() else np.nan
        cells.append(f"{mean:.0f} / {stuck[inside].mean() if inside.any() else np.nan:.1f}")
    return " | ".join(cells)


def main(argv: list[str] | None = None) -> dict[str, Any]:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--configs", nargs="+", required=True, help="published configs")
    parser.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2, 3, 4])
    parser.add_argument("--roads", type=int, default=256, help="evaluation roads per seed")
    parser.add_argument("--out", default="outputs/cooperation_control")
    parser.add_argument("--window-frames", type=int, default=100_000)
    parser.add_argument("--explored", action="store_true")
    parser.add_argument("overrides", nargs="*", help="key=value, applied to every arm")
    args = parser.parse_args(argv)
    if args.window_frames < 1:
        parser.error(f"--window-frames must be >= 1, got {args.window_frames}")
    for name in args.configs:  # a bad name fails before any training
        load_published(name)
    print(f"# {machine_line()}")
    runs = {(n, s): scores(n, trained(n, s, args), args) for n in args.configs for s in args.seeds}
    summary: dict[str, Any] = {"args": vars(args)}
    lines = [
        f"freeway-merge, greedy evaluation on {args.roads} roads per seed (seeds "
        f"{' '.join(map(str, args.seeds))}); gain = system reward vs keep lane on the same "
        "roads, mean over seeds [bootstrap 95%]; behaviour per episode",
        "",
        "| policy | system reward | vs keep lane | per seed | " + " | ".join(METRICS) + " |",
        "|---|---|---|---|" + "---|" * len(METRICS),
    ]
    training = []
    for name in args.configs:
        per_seed = [runs[name, seed] for seed in args.seeds]
        keep = [r["references"]["keep-lane"] for r in per_seed]
        arms = {
            f"{reference} (reference, {name}'s scenario)": [
                r["references"][reference] for r in per_seed
            ]
            for reference in REFERENCES
        }
        arms[name] = [r["policy"] for r in per_seed]
        if all("explored" in r for r in per_seed):
            arms[f"{name} (its final epsilon-greedy)"] = [r["explored"] for r in per_seed]
        for label, scored in arms.items():
            line, summary[label] = row(label, scored, keep)
            lines.append(line)
        width = args.window_frames
        training += [
            f"{name} seed {seed}, training system reward / ramp stuck per {width} "
            f"frames: {windows(run_dir(Path(args.out), name, seed), width)}"
            for seed in args.seeds
        ]
    table = "\n".join([*lines, "", *training])
    atomic_write_text(Path(args.out) / "control.md", table + "\n")
    atomic_write_text(Path(args.out) / "control.json", json.dumps(summary, indent=1))
    print(table)
    return summary


if __name__ == "__main__":
    from mapets_rl import quiet_dependencies

    quiet_dependencies()
    main()
