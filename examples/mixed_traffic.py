"""Mixed traffic: average velocity and comfort of all vehicles vs the CAV ratio (Shapley paper,
Table I).

For every CAV ratio the Shapley actor-critic (``recipes.shapley_ac``) is trained on the freeway
with ``--n-vehicles`` vehicles, then evaluated for ``--eval-episodes`` deterministic episodes
with the grand coalition. Ratio 0 has no CAV to train: the all-human ``FreewayEnv`` is simulated
for the same number of episodes. Average velocity (converted to mph) and average comfort
(paper eq. 9) are over all vehicles (CAVs and humans) and all steps, printed beside the
paper's numbers.

Paper scale: 30 vehicles, 100k training episodes, CARLA. Default scale here (CPU, about an hour
on a 2-core machine): 30 vehicles, ``--frames 600`` (15 episodes of 40 steps) of training per
ratio, 3 evaluation episodes. With more than 10 CAVs the Shapley value is estimated by
permutation sampling (``exact_max_agents=10``).

Run:  python examples/mixed_traffic.py [--frames 600] [--out outputs/mixed_traffic]
Writes ``<out>/table.md`` and ``<out>/results.json``; ratios whose run already finished in
``<out>/runs`` are not retrained.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from mapets_rl.envs import FreewayEnv
from mapets_rl.experiment import atomic_write_text, mean_metrics
from recipes.shapley_ac import ShapleyAC, ShapleyACConfig

RATIOS = (0.0, 0.17, 0.33, 0.5, 0.67, 0.83, 1.0)
MPS_TO_MPH = 2.2369362920544
# Paper Table I: CAV ratio -> (average velocity mph, average comfort), Shapley and COMA.
PAPER_SHAPLEY = {
    0.0: (60.06, 2.61),
    0.17: (61.75, 2.63),
    0.33: (64.71, 2.68),
    0.5: (65.12, 2.71),
    0.67: (65.19, 2.74),
    0.83: (65.49, 2.76),
    1.0: (66.14, 2.81),
}
PAPER_COMA = {
    0.0: (60.06, 2.61),
    0.17: (61.19, 2.62),
    0.33: (63.15, 2.65),
    0.5: (63.44, 2.68),
    0.67: (63.48, 2.69),
    0.83: (63.69, 2.71),
    1.0: (64.12, 2.75),
}


def all_human(n_vehicles: int, episodes: int, seed: int) -> dict[str, float]:
    """Average velocity / comfort of ``episodes`` all-human freeway episodes."""
    env = FreewayEnv(config={"n_vehicles": n_vehicles, "cav_ratio": 0.0})
    per_episode = []
    for ep in range(episodes):
        env.reset(seed=seed + ep)
        done = False
        while not done:
            _, _, terminated, truncated, info = env.step(np.zeros(0, dtype=np.int64))
            done = terminated or truncated
        per_episode.append({k: float(v) for k, v in info["episode"].items()})
    return mean_metrics(per_episode)


def train_and_evaluate(ratio: float, args: argparse.Namespace) -> dict[str, float]:
    """Train Shapley AC at ``ratio`` and return its final evaluation; a run of the same
    budget already finished in ``--out`` is reused (so an interrupted table resumes)."""
    run_dir = Path(args.out) / "runs" / f"ratio{ratio:.2f}"
    results = run_dir / "results.json"
    if results.is_file():
        done = [
            e for e in json.loads(results.read_text())["evaluations"] if e["frames"] >= args.frames
        ]
        if done:
            return done[-1]["metrics"]
    config = ShapleyACConfig(
        env_config={"n_vehicles": args.n_vehicles, "cav_ratio": ratio},
        seed=args.seed,
        total_frames=args.frames,
        eval_interval=args.frames,
        checkpoint_interval=args.frames,
        eval_episodes=args.eval_episodes,
        batch_size=args.batch_size,
        num_permutations=args.num_permutations,
        logger="csv",
        progress=args.progress,
    )
    exp = ShapleyAC(config, run_dir)
    return exp.train()[-1]["metrics"]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--ratios", nargs="+", type=float, default=list(RATIOS))
    parser.add_argument("--n-vehicles", type=int, default=30)
    parser.add_argument("--frames", type=int, default=600)
    parser.add_argument("--eval-episodes", type=int, default=3)
    parser.add_argument("--batch-size", type=int, default=64)
    parser.add_argument("--num-permutations", type=int, default=8)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", default="outputs/mixed_traffic")
    parser.add_argument("--progress", action="store_true")
    args = parser.parse_args()
    bad = [r for r in args.ratios if not 0.0 <= r <= 1.0]
    if bad:
        raise ValueError(f"--ratios must lie in [0, 1], got {bad}")
    if args.frames < 40:
        raise ValueError(f"--frames must be >= 40 (one episode), got {args.frames}")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)

    rows, results = [], {}
    for ratio in args.ratios:
        n_cavs = int(round(ratio * args.n_vehicles))
        print(f"CAV ratio {ratio:.2f} ({n_cavs} CAVs) ...", flush=True)
        if n_cavs == 0:
            metrics = all_human(args.n_vehicles, args.eval_episodes, args.seed)
        else:
            metrics = train_and_evaluate(ratio, args)
        velocity = metrics["average_velocity"] * MPS_TO_MPH
        comfort = metrics["average_comfort"]
        results[f"{ratio:.2f}"] = {
            "cavs": n_cavs,
            "velocity_mph": velocity,
            "comfort": comfort,
            "collisions": metrics.get("collisions", 0.0),
        }
        paper = PAPER_SHAPLEY.get(round(ratio, 2))
        coma = PAPER_COMA.get(round(ratio, 2))
        paper_txt = (
            f"{paper[0]:.2f} | {paper[1]:.2f} | {coma[0]:.2f} | {coma[1]:.2f}"
            if paper
            else "- | - | - | -"
        )
        rows.append(
            f"| {ratio:.2f} | {n_cavs} | {args.n_vehicles - n_cavs} | {velocity:.2f} | "
            f"{comfort:.2f} | {paper_txt} |"
        )
    table = "\n".join(
        [
            f"Average velocity (mph) and comfort of all {args.n_vehicles} vehicles; Shapley AC "
            f"trained {args.frames} frames per ratio, {args.eval_episodes} evaluation episodes.",
            "",
            "| CAV ratio | CAVs | HVs | velocity (ours) | comfort (ours) "
            "| velocity (paper, Shapley) | comfort (paper, Shapley) "
            "| velocity (paper, COMA) | comfort (paper, COMA) |",
            "|---|---|---|---|---|---|---|---|---|",
            *rows,
        ]
    )
    atomic_write_text(out / "table.md", table + "\n")
    atomic_write_text(out / "results.json", json.dumps(results, indent=1))
    print(table)


if __name__ == "__main__":
    main()
