"""Shapley actor-critic vs MADDPG, M3DDPG, COMA and MAPPO on the freeway (Shapley paper, Fig. 2).

Every algorithm trains on the same freeway configuration for the same number of environment
frames with ``--seeds`` seeds; each evaluation runs ``--eval-episodes`` deterministic episodes
(Shapley AC with the grand coalition). The scripted policy "every CAV keeps its lane" (speed
under IDM, no lane change, no emergency stop) is scored on the same evaluation episodes as a
reference line: it shows whether a learned policy does better than never acting. The reported
quantity is the paper's *mean episode system reward*: the reward summed over all CAVs and the
40 steps of an episode, i.e. the recipes' per-CAV ``return`` times the number of CAVs.

Paper scale: 30 CAVs, 100k episodes x 5 seeds on a 4-GPU server. Default scale here (CPU, about
an hour for the 15 runs on a 2-core machine): 8 vehicles of which 4 CAVs, 1600 frames (40
episodes) per run, 3 seeds. The paper's setting is ``--n-vehicles 30 --cav-ratio 1``. COMA
(on-policy) updates once per collected batch of ``--frames-per-batch`` frames. Runs are
resumable: an interrupted invocation continues from the runs' last checkpoints.

Run:  python examples/shapley_freeway.py [--frames 1600] [--seeds 0 1 2] [--out outputs/...]
      python examples/shapley_freeway.py --env freeway-merge ...   # the on-ramp dilemma
Writes ``<out>/system_reward.png`` (mean and bootstrap 95% band over seeds,
:func:`mapets_rl.plotting.draw_curve`), ``<out>/system_reward.md``
and ``<out>/summary.json``; prints the table.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from mapets_rl.app.plugins import load_recipe
from mapets_rl.experiment import (
    ExperimentConfig,
    atomic_savefig,
    atomic_write_text,
    evaluate_scripted,
    latest_checkpoint,
    read_results,
)
from mapets_rl.plotting import draw_curve  # noqa: E402
from mapets_rl.statistics import mean_ci95  # noqa: E402

ALGORITHMS = ("shapley_ac", "maddpg", "m3ddpg", "coma", "mappo")
LABELS = {
    "shapley_ac": "Shapley AC",
    "maddpg": "MADDPG",
    "m3ddpg": "M3DDPG",
    "coma": "COMA",
    "mappo": "MAPPO",
}
# On-policy MAPPO collects 5 episodes per PPO update (its minibatch is 100 transitions).
ON_POLICY_FRAMES_PER_BATCH = 200


def env_overrides(args: argparse.Namespace) -> list[str]:
    """``--env-override KEY=VALUE`` as recipe-config overrides ``env_config.KEY=VALUE``."""
    return [f"env_config.{item}" for item in args.env_override]


def keep_lane_reference(seed: int, args: argparse.Namespace) -> tuple[float, float, float]:
    """System reward, collisions and ramp vehicles stuck (freeway-merge; 0 elsewhere) per
    episode of the scripted keep-lane policy (:func:`~mapets_rl.experiment.evaluate_scripted`)
    on the evaluation episodes the learned runs of ``seed`` are scored on."""
    config = ExperimentConfig(
        env=args.env,
        env_config={"n_vehicles": args.n_vehicles, "cav_ratio": args.cav_ratio},
        seed=seed,
        eval_episodes=args.eval_episodes,
    ).with_overrides(env_overrides(args))
    metrics = evaluate_scripted(config)
    n_cavs = int(round(args.cav_ratio * args.n_vehicles))
    return (
        metrics["return"] * n_cavs,
        float(metrics.get("collisions", 0.0)),
        float(metrics.get("ramp_stuck", 0.0)),
    )


def run_one(algo: str, seed: int, args: argparse.Namespace) -> Path:
    """Train (or finish training) one run; returns its run directory."""
    cls = load_recipe(algo)
    run_dir = Path(args.out) / "runs" / f"{algo}_seed{seed}"
    overrides = [f"total_frames={args.frames}"]
    if latest_checkpoint(run_dir) is not None:
        # a run whose results.json is gone is still resumed (its checkpoint holds the results)
        if trained(run_dir, args.frames):
            return run_dir  # finished: nothing is rebuilt or rewritten
        # a finished run's train() only rewrites what is missing (results.json)
        exp = cls.from_run_dir(run_dir, overrides=overrides)
    else:
        batch = args.frames_per_batch
        sizes = {}
        if algo == "mappo":  # a longer on-policy batch, within the budget
            batch = min(ON_POLICY_FRAMES_PER_BATCH, args.frames)
            sizes["minibatch_size"] = min(cls.Config.minibatch_size, batch)
        config = cls.Config(
            env=args.env,
            env_config={"n_vehicles": args.n_vehicles, "cav_ratio": args.cav_ratio},
            seed=seed,
            total_frames=args.frames,
            frames_per_batch=batch,
            **sizes,
            eval_interval=args.eval_interval,
            eval_episodes=args.eval_episodes,
            checkpoint_interval=args.eval_interval,
            logger="csv",
            progress=args.progress,
        )
        exp = cls(config.with_overrides(env_overrides(args)), run_dir)
    exp.train()
    return run_dir


def system_curves(run_dir: Path, n_cavs: int) -> tuple[np.ndarray, np.ndarray, float, float]:
    """Evaluation frames ``[E]``, mean episode system reward ``[E]`` (per-CAV return x CAVs),
    and the final evaluation's collisions and ramp vehicles stuck (freeway-merge) per
    episode."""
    evals = read_results(run_dir)["evaluations"]
    frames = np.array([e["frames"] for e in evals])
    system = np.array([e["metrics"]["return"] * n_cavs for e in evals])
    final = evals[-1]["metrics"]
    return frames, system, float(final.get("collisions", 0.0)), float(final.get("ramp_stuck", 0))


def trained(run_dir: Path, frames: int) -> bool:
    """Whether ``run_dir`` holds a run evaluated at ``frames`` frames or later."""
    if not (run_dir / "results.json").is_file():
        return False
    evaluations = read_results(run_dir)["evaluations"]
    return bool(evaluations) and evaluations[-1]["frames"] >= frames


def final_columns(
    finals: np.ndarray, collisions: list[float], stuck: list[float]
) -> tuple[dict[str, Any], str]:
    """Summary fields and table cells of the final evaluation of each seed: system reward
    ``finals [seeds]`` (mean ± 95% CI, per seed, spread), collisions and ramp vehicles stuck
    per episode."""
    mean, half = mean_ci95(finals.tolist())
    spread = float(finals.max() - finals.min())
    fields = {
        "final_mean": mean,
        "final_ci95": half,
        "final_per_seed": finals.tolist(),
        "final_spread": spread,
        "final_collisions_per_seed": collisions,
        "final_ramp_stuck_per_seed": stuck,
        "seeds": len(finals),
    }
    cells = (
        f"{mean:.1f} ± {half:.1f} | {', '.join(f'{v:.1f}' for v in finals)} | {spread:.1f} "
        f"| {', '.join(f'{c:g}' for c in collisions)} | {', '.join(f'{c:g}' for c in stuck)}"
    )
    return fields, cells


def main(argv: list[str] | None = None) -> dict[str, dict[str, Any]]:
    """Train (or resume) every run, then write the plot, table and summary; returns the
    summary."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--algorithms", nargs="+", default=list(ALGORITHMS))
    parser.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2])
    parser.add_argument("--frames", type=int, default=1600)
    parser.add_argument("--frames-per-batch", type=int, default=40)
    parser.add_argument("--eval-interval", type=int, default=400)
    parser.add_argument("--eval-episodes", type=int, default=2)
    parser.add_argument("--n-vehicles", type=int, default=8)
    parser.add_argument("--cav-ratio", type=float, default=0.5)
    parser.add_argument(
        "--env-override",
        nargs="*",
        default=[],
        metavar="KEY=VALUE",
        help="freeway config values for every run and the reference (velocity_weight=1.0)",
    )
    parser.add_argument(
        "--env",
        default="freeway",
        choices=["freeway", "freeway-merge"],
        help="freeway-merge: the on-ramp social dilemma (issue 21)",
    )
    parser.add_argument("--out", default="outputs/shapley_freeway")
    parser.add_argument("--progress", action="store_true")
    parser.add_argument(
        "--report-only",
        action="store_true",
        help="train nothing: plot and tabulate the runs under --out that reached --frames "
        "(the others are listed as skipped)",
    )
    args = parser.parse_args(argv)
    for name, val in (("frames", args.frames), ("eval_interval", args.eval_interval)):
        if val < 1:
            raise ValueError(f"--{name.replace('_', '-')} must be >= 1, got {val}")
    unknown = sorted(set(args.algorithms) - set(ALGORITHMS))
    if unknown:
        raise ValueError(f"--algorithms must be among {ALGORITHMS}, got {unknown}")
    n_cavs = int(round(args.cav_ratio * args.n_vehicles))
    # first: a bad --n-vehicles / --cav-ratio / --env-override fails here, before any training
    reference = [keep_lane_reference(seed, args) for seed in args.seeds]
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)

    curves: dict[str, list[tuple[np.ndarray, np.ndarray, float]]] = {}
    for algo in args.algorithms:
        for seed in args.seeds:
            run_dir = out / "runs" / f"{algo}_seed{seed}"
            if args.report_only:
                if not trained(run_dir, args.frames):
                    print(f"skipped {algo} seed {seed}: not trained to {args.frames} frames")
                    continue
            else:
                print(f"training {algo} seed {seed} ...", flush=True)
                run_dir = run_one(algo, seed, args)
            curves.setdefault(algo, []).append(system_curves(run_dir, n_cavs))

    fig, ax = plt.subplots(figsize=(6, 4))
    summary: dict[str, dict[str, Any]] = {}
    rows = []
    for algo, runs in curves.items():
        frames = runs[0][0]
        length = min(len(r[1]) for r in runs)
        values = np.stack([r[1][:length] for r in runs])  # [seeds, evals]
        draw_curve(ax, frames[:length] / 40, values, metric="return", label=LABELS[algo])
        first = mean_ci95(values[:, 0].tolist())
        fields, cells = final_columns(values[:, -1], [r[2] for r in runs], [r[3] for r in runs])
        summary[algo] = {
            "first_mean": first[0],
            "first_ci95": first[1],
            **fields,
            "frames": int(frames[length - 1]),
        }
        rows.append(f"| {LABELS[algo]} | {first[0]:.1f} ± {first[1]:.1f} | {cells} |")
    fields, cells = final_columns(
        np.array([r[0] for r in reference]), [r[1] for r in reference], [r[2] for r in reference]
    )
    summary["keep_lane"] = {**fields, "frames": 0}
    rows.append(f"| keep lane (scripted, untrained) | - | {cells} |")
    reference_line = {"color": "black", "linestyle": "--", "linewidth": 1}
    ax.axhline(fields["final_mean"], label="keep lane (scripted)", **reference_line)
    ax.set_xlabel("training episodes (40 steps)")
    ax.set_ylabel("mean episode system reward")
    ax.set_title(
        f"{args.env}, {n_cavs} CAVs / {args.n_vehicles} vehicles {' '.join(args.env_override)}"
    )
    ax.legend()
    fig.tight_layout()
    atomic_savefig(fig, out / "system_reward.png")
    table = "\n".join(
        [
            f"Mean episode system reward (sum over {n_cavs} CAVs and 40 steps), mean ± 95% CI over "
            f"seeds, {args.frames} training frames per run"
            f"{' (' + ', '.join(args.env_override) + ')' if args.env_override else ''}. "
            "The scripted keep-lane policy "
            "(speed under IDM) is scored on the same evaluation episodes per seed.",
            "",
            "| algorithm | first evaluation | final evaluation | final, per seed "
            "| spread (max - min) | collisions / episode (final, per seed) "
            "| ramp vehicles stuck / episode (final, per seed) |",
            "|---|---|---|---|---|---|---|",
            *rows,
        ]
    )
    atomic_write_text(out / "system_reward.md", table + "\n")
    atomic_write_text(out / "summary.json", json.dumps(summary, indent=1))
    print(table)
    return summary


if __name__ == "__main__":
    from mapets_rl import quiet_dependencies

    quiet_dependencies()
    main()
