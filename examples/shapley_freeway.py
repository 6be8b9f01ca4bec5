"""Shapley actor-critic vs MADDPG, M3DDPG, COMA and MAPPO on the freeway (Shapley paper, Fig. 2).

Every algorithm trains on the same freeway configuration for the same number of environment
frames with ``--seeds`` seeds; each evaluation runs ``--eval-episodes`` deterministic episodes
(Shapley AC with the grand coalition). The scripted policy "every CAV keeps its lane" (speed
under IDM, no lane change, no emergency stop) is scored on the same evaluation episodes as a
reference line: it shows whether a learned policy does better than never acting. The reported
quantity is the paper's *mean episode system reward*: the reward summed over all CAVs and the
40 steps of an episode, i.e. the recipes' per-CAV ``return`` times the number of CAVs.

The paper's Fig. 2 plots this quantity over the *training* episodes, averaged over every
1,000 of them; the runs record every training episode (``train_episodes.jsonl``,
:mod:`mapets_rl.experiment.episodes`), and the script reports their mean system reward per
window of ``--window`` consecutive training episodes (default 1,000, the paper's) beside the
greedy evaluations. Only complete windows are reported: a run of fewer training episodes than
``--window`` has none (set a smaller ``--window`` for small runs).

Paper scale: 30 CAVs, 100k episodes x 5 seeds on a 4-GPU server. Default scale here (CPU, about
an hour for the 15 runs on a 2-core machine): 8 vehicles of which 4 CAVs, 1600 frames (40
episodes) per run, 3 seeds. The paper's setting is ``--n-vehicles 30 --cav-ratio 1``. COMA
(on-policy) updates once per collected batch of ``--frames-per-batch`` frames. Runs are
resumable: an interrupted invocation continues from the runs' last checkpoints.

Backends (``--backend``): ``highway-env`` (default) steps one road per run; ``torch`` trains
every algorithm on ``--num-envs`` roads of the batched torch freeway
(``env_config={backend: torch, num_envs: B}``, :class:`~mapets_rl.envs.TorchFreewayEnv`) for
the same ``--frames`` budget, a frame being one step of one road: each collected batch holds
``--frames-per-batch / B`` steps of every road (default ``--frames-per-batch``: 40 on one
road, 10 steps of every road on ``B``). Evaluations and the keep-lane reference step one road
of the same backend. The collector is reset at every checkpoint (every ``--eval-interval``
frames), which drops the episodes under way: the torch backend's default interval is a
multiple of ``40 B`` frames (whole episodes of every road), and so should an explicit one be.

Schedules (``--schedule``): ``default`` keeps each recipe's defaults; ``openai`` applies
openai/maddpg's (:data:`mapets_rl.recipes.maddpg.OPENAI_MADDPG`: one gradient step per 100
frames on minibatches of 1,024, Adam at 1e-2, gamma 0.95, tau 0.01, two hidden layers of 64,
gradient clip 0.5) where the recipe has the field (:data:`OPENAI_FIELDS`): MADDPG, M3DDPG
and Shapley AC (its actor; ``critic_cells`` stays) get all of it; COMA gets gamma, tau,
``lr_critic``, ``num_cells`` and ``max_grad_norm`` (its policy step, on-policy, keeps its
``lr`` and its one update per batch); MAPPO gets gamma, ``num_cells`` and ``max_grad_norm``.
``--frames-per-batch`` is the same for every method but MAPPO, whose batches are longer (up to
200 frames, a divisor of ``--frames``: :func:`on_policy_batch`).

Run:  python examples/shapley_freeway.py [--frames 1600] [--seeds 0 1 2] [--out outputs/...]
      python examples/shapley_freeway.py --env freeway-merge ...   # the on-ramp dilemma
      python examples/shapley_freeway.py --backend torch --num-envs 64 --schedule openai \
          --frames 4000000 --frames-per-batch 1024 --eval-interval 102400 --window 1000 \
          --n-vehicles 30 --cav-ratio 1 --seeds 0 1 2 3 4 --out outputs/fig2_torch
Writes ``<out>/system_reward.png`` (greedy evaluations: mean and bootstrap 95% band over seeds,
:func:`mapets_rl.plotting.draw_curve`), ``<out>/train_system_reward.png`` (mean training
system reward per window of ``--window`` training episodes, same bands),
``<out>/system_reward.md`` (both tables) and ``<out>/summary.json``; prints the tables.
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
from mapets_rl.config import parse_override
from mapets_rl.experiment import (
    ExperimentConfig,
    atomic_savefig,
    atomic_write_text,
    evaluate_scripted,
    latest_checkpoint,
    read_results,
    read_train_episodes,
    window_means,
)
from mapets_rl.plotting import draw_curve  # noqa: E402
from mapets_rl.recipes.maddpg import OPENAI_MADDPG  # noqa: E402
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
EPISODE_STEPS = 40
"""Steps of a freeway episode (the scenario's horizon)."""
_ALL_OPENAI = frozenset(parse_override(item)[0] for item in OPENAI_MADDPG)
OPENAI_FIELDS: dict[str, frozenset[str]] = {
    "shapley_ac": _ALL_OPENAI,
    "maddpg": _ALL_OPENAI,
    "m3ddpg": _ALL_OPENAI,
    "coma": frozenset({"gamma", "tau", "lr_critic", "num_cells", "max_grad_norm"}),
    "mappo": frozenset({"gamma", "num_cells", "max_grad_norm"}),
}
"""``--schedule openai``: the fields of :data:`OPENAI_MADDPG` each algorithm gets."""


def schedule_overrides(algo: str, schedule: str) -> list[str]:
    """The recipe-config overrides of ``schedule`` (``default``: none; ``openai``: the
    fields of :data:`OPENAI_MADDPG` in :data:`OPENAI_FIELDS` of ``algo``)."""
    if schedule == "default":
        return []
    return [item for item in OPENAI_MADDPG if parse_override(item)[0] in OPENAI_FIELDS[algo]]


def on_policy_batch(args: argparse.Namespace) -> int:
    """MAPPO's frames per batch: the largest multiple of the roads' count (1 on highway-env)
    up to ``ON_POLICY_FRAMES_PER_BATCH`` (rounded up to whole steps of every road) that
    divides ``--frames``, so that MAPPO trains the others' frame budget; ``--frames-per-batch``
    when none is longer."""
    roads = args.num_envs if args.backend == "torch" else 1
    longest = min(-(-ON_POLICY_FRAMES_PER_BATCH // roads) * roads, args.frames // roads * roads)
    for batch in range(longest, args.frames_per_batch, -roads):
        if args.frames % batch == 0:
            return batch
    return args.frames_per_batch


def env_config(args: argparse.Namespace, batched: bool = True) -> dict[str, Any]:
    """The runs' ``env_config``: vehicles and CAV ratio, plus ``backend: torch`` and (when
    ``batched``) ``num_envs`` on the torch backend."""
    config: dict[str, Any] = {"n_vehicles": args.n_vehicles, "cav_ratio": args.cav_ratio}
    if args.backend == "torch":
        config["backend"] = "torch"
        if batched:
            config["num_envs"] = args.num_envs
    return config


def env_overrides(args: argparse.Namespace) -> list[str]:
    """``--env-override KEY=VALUE`` as recipe-config overrides ``env_config.KEY=VALUE``."""
    return [f"env_config.{item}" for item in args.env_override]


def keep_lane_reference(seed: int, args: argparse.Namespace) -> tuple[float, float, float]:
    """System reward, collisions and ramp vehicles stuck (freeway-merge; 0 elsewhere) per
    episode of the scripted keep-lane policy (:func:`~mapets_rl.experiment.evaluate_scripted`)
    on the evaluation episodes the learned runs of ``seed`` are scored on."""
    config = ExperimentConfig(
        env=args.env,
        env_config=env_config(args, batched=False),  # evaluation steps one road
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
            batch = on_policy_batch(args)
        if algo in ("mappo", "coma"):
            sizes["minibatch_size"] = min(cls.Config.minibatch_size, batch)
        config = cls.Config(
            env=args.env,
            env_config=env_config(args),
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
        overrides = [*schedule_overrides(algo, args.schedule), *env_overrides(args)]
        exp = cls(config.with_overrides(overrides), run_dir)
    exp.train()
    return run_dir


def training_windows(run_dir: Path, window: int) -> tuple[np.ndarray, int]:
    """Mean system reward of the run's training episodes per window of ``window`` consecutive
    episodes ``[W]`` (complete windows only) and the number of training episodes recorded."""
    returns = read_train_episodes(run_dir)["system_return"]
    return window_means(returns, window), len(returns)


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
    parser.add_argument(
        "--frames-per-batch",
        type=int,
        default=None,
        help="frames per collected batch (default: 40; torch backend: 10 x --num-envs)",
    )
    parser.add_argument(
        "--eval-interval",
        type=int,
        default=None,
        help="frames between evaluations and checkpoints (default: 400; torch backend: the "
        "least multiple of 40 x --num-envs from 400)",
    )
    parser.add_argument(
        "--backend",
        default="highway-env",
        choices=["highway-env", "torch"],
        help="torch: --num-envs roads of the batched torch freeway per run",
    )
    parser.add_argument("--num-envs", type=int, default=4, help="roads (torch backend)")
    parser.add_argument(
        "--schedule",
        default="default",
        choices=["default", "openai"],
        help="openai: openai/maddpg's update schedule where a recipe has the field "
        "(module docstring)",
    )
    parser.add_argument(
        "--window",
        type=int,
        default=1000,
        help="training episodes per point of the training curve (the paper's 1000)",
    )
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
    if args.num_envs < 1:
        raise ValueError(f"--num-envs must be >= 1, got {args.num_envs}")
    roads = args.num_envs if args.backend == "torch" else 1
    if args.frames_per_batch is None:
        args.frames_per_batch = 40 if roads == 1 else 10 * roads
    if args.eval_interval is None:
        episode = EPISODE_STEPS * roads
        args.eval_interval = 400 if roads == 1 else -(-400 // episode) * episode
    for name, val in (
        ("frames", args.frames),
        ("eval_interval", args.eval_interval),
        ("window", args.window),
        ("frames_per_batch", args.frames_per_batch),
    ):
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

    curves: dict[str, list[tuple[np.ndarray, np.ndarray, float, float]]] = {}
    windows: dict[str, list[tuple[np.ndarray, int]]] = {}
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
            windows.setdefault(algo, []).append(training_windows(run_dir, args.window))

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
    plt.close(fig)
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
    train_table = training_report(windows, summary, args, n_cavs, fields["final_mean"], out)
    table = f"{table}\n\n{train_table}"
    atomic_write_text(out / "system_reward.md", table + "\n")
    atomic_write_text(out / "summary.json", json.dumps(summary, indent=1))
    print(table)
    return summary


def training_report(
    windows: dict[str, list[tuple[np.ndarray, int]]],
    summary: dict[str, dict[str, Any]],
    args: argparse.Namespace,
    n_cavs: int,
    keep_lane: float,
    out: Path,
) -> str:
    """The paper's Fig. 2 metric: draw ``<out>/train_system_reward.png`` (per algorithm the
    mean training system reward per window of ``--window`` episodes, ``windows[algo]`` one
    ``([W], episodes)`` per seed, over the windows every seed completed), add the
    ``train_*`` fields to ``summary[algo]`` and return the markdown table."""
    fig, ax = plt.subplots(figsize=(6, 4))
    rows = []
    for algo, runs in windows.items():
        counts = [episodes for _, episodes in runs]
        length = min(len(w) for w, _ in runs)
        fields: dict[str, Any] = {
            "train_window": args.window,
            "train_episodes_per_seed": counts,
            "train_windows": length,
        }
        if length == 0:
            summary[algo].update(fields)
            rows.append(f"| {LABELS[algo]} | {', '.join(map(str, counts))} | 0 | - | - | - |")
            continue
        values = np.stack([w[:length] for w, _ in runs])  # [seeds, windows]
        episodes = args.window * np.arange(1, length + 1)
        draw_curve(ax, episodes, values, metric="return", marker="o", ms=3, label=LABELS[algo])
        first = mean_ci95(values[:, 0].tolist())
        last = mean_ci95(values[:, -1].tolist())
        fields.update(
            {
                "train_curve_mean": values.mean(0).tolist(),
                "train_first_mean": first[0],
                "train_first_ci95": first[1],
                "train_last_mean": last[0],
                "train_last_ci95": last[1],
                "train_last_per_seed": values[:, -1].tolist(),
            }
        )
        summary[algo].update(fields)
        rows.append(
            f"| {LABELS[algo]} | {', '.join(map(str, counts))} | {length} "
            f"| {first[0]:.1f} ± {first[1]:.1f} | {last[0]:.1f} ± {last[1]:.1f} "
            f"| {', '.join(f'{v:.1f}' for v in values[:, -1])} |"
        )
    ax.axhline(keep_lane, label="keep lane (scripted, evaluation)", color="black", ls="--", lw=1)
    ax.set_xlabel(f"training episodes (mean over each {args.window})")
    ax.set_ylabel("mean training episode system reward")
    ax.set_title(f"{args.env} ({args.backend}), {n_cavs} CAVs / {args.n_vehicles} vehicles")
    ax.legend()
    fig.tight_layout()
    atomic_savefig(fig, out / "train_system_reward.png")
    plt.close(fig)
    return "\n".join(
        [
            f"Mean *training* episode system reward (the paper's Fig. 2 metric: sum over "
            f"{n_cavs} CAVs and the steps of each training episode, averaged over each window "
            f"of {args.window} consecutive training episodes), mean ± 95% CI over seeds; "
            "complete windows only, over the windows every seed completed.",
            "",
            "| algorithm | training episodes (per seed) | windows | first window "
            "| last window | last window, per seed |",
            "|---|---|---|---|---|---|",
            *rows,
        ]
    )


if __name__ == "__main__":
    from mapets_rl import quiet_dependencies

    quiet_dependencies()
    main()
