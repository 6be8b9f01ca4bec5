"""Mixed traffic: average velocity and comfort of all vehicles vs the CAV ratio (Shapley paper,
Table I), Shapley AC and COMA side by side.

For every method (``--methods``: ``shapley_ac``, ``coma``), CAV ratio and seed the recipe is
trained on the freeway with ``--n-vehicles`` vehicles, then evaluated for ``--eval-episodes``
deterministic episodes (Shapley AC with the grand coalition, COMA with its policies' modes).
The method ``scripted`` trains nothing: every CAV keeps its lane under IDM (target speed
``cav_target_speed``, 31 m/s, against the humans' 25-30 m/s), scored on the same evaluation
episodes as the learned runs of each seed. It separates what learning adds from what the CAVs'
car-following controller gives by itself.
Ratio 0 has no CAV to train: the all-human ``FreewayEnv`` is simulated per seed. Average
velocity (m/s and mph) and comfort (paper eq. 9: 3 keep-lane with mean ``|acc| < 1.5 m/s^2``,
2 keep-lane braking/accelerating harder, 1 lane change, 0 emergency stop, averaged over all
vehicles and steps) are reported as the mean over seeds with a 95% Student-t interval, beside
the paper's Shapley and COMA columns, with collisions per episode.

Why the all-human row differs from the paper's (60.06 mph, 2.61): the humans here are
highway-env IDM/MOBIL drivers with target speeds of 25-30 m/s on a straight 3-lane road with
30 vehicles, not CARLA's autopilot on Town05; IDM drives smoothly (high comfort) and slows in
dense traffic (lower velocity).

Scales (``--scale``; ``--frames``, ``--n-vehicles``, ``--eval-episodes`` and the
``--*-override`` options refine them):

* ``smoke``: 8 vehicles, 80 frames, 1 evaluation episode (seconds; for tests).
* ``cpu``: 30 vehicles, 800 frames (20 episodes) per run, 2 evaluation episodes, Shapley AC with
  8 antithetic orderings, minibatches of 64 and the exact value up to 5 CAVs: about a minute
  per run on a 2-core CPU. At ratio 1 the default shared ego-first actor drove the 30 CAVs
  collision-free from 400-800 frames on (3 of 3 seeds), so this budget reaches the plateau of
  the freeway's reward, not the paper's 100k episodes. That plateau is the keep-lane policy
  (compare the ``scripted`` rows; ``benchmarks/freeway_headroom.py`` measures how little the
  reward leaves above it).
* ``paper``: 30 vehicles, 400,000 frames (10,000 episodes) per run, 5 evaluation episodes,
  recipe defaults (hours per run: the paper trained 100k episodes on 4 GPUs).

Training metrics: every learned run records its training episodes
(``train_episodes.jsonl``, :mod:`mapets_rl.experiment.episodes`); the table adds, beside the
greedy evaluation, the mean over each run's last ``--window`` training episodes (all of them
when it has fewer) of the episode system reward (reward summed over CAVs and steps, the paper's
Fig. 2 quantity), velocity and comfort (``train_*`` keys in ``results.json``).

Backends (``--backend``): ``highway-env`` (default) or ``torch``: ``--num-envs`` roads of the
batched torch freeway per run for the same ``--frames`` (a frame is one step of one road;
batches of ``--frames-per-batch``, default 10 steps of every road); evaluation, the scripted
rows and ratio 0 step one road of the scenario (ratio 0 on highway-env, whose all-human
``FreewayEnv`` has no torch twin). ``--schedule openai`` applies openai/maddpg's schedule
(:data:`mapets_rl.recipes.maddpg.OPENAI_MADDPG`) where the recipe has the field: Shapley AC all
of it (update interval 100 frames, one update, minibatch 1,024, learning rates 1e-2, gamma
0.95, tau 0.01, actor ``num_cells`` [64, 64], gradient clip 0.5; ``critic_cells`` stays), COMA
gamma, tau, ``lr_critic``, ``num_cells`` and ``max_grad_norm`` (its on-policy ``lr`` and its
one update per batch stay); ``--shapley-override`` / ``--coma-override`` come after it.
Interrupted runs resume from their last checkpoint (``--checkpoint-interval`` frames, default:
the end of the run only).

Run:  python examples/mixed_traffic.py [--scale cpu] [--methods shapley_ac coma scripted]
      [--ratios 0 0.5 1] [--seeds 0 1 2] [--out outputs/mixed_traffic]
      python examples/mixed_traffic.py --scale paper --backend torch --num-envs 64 \
          --frames-per-batch 1024 --schedule openai --checkpoint-interval 102400 \
          --out outputs/mixed_traffic_torch
Writes ``<out>/table.md``, ``<out>/results.json`` and ``<out>/velocity_comfort.png``; runs
that already finished in ``<out>/runs`` are not retrained.
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

from mapets_rl.config import parse_override  # noqa: E402
from mapets_rl.envs import FreewayEnv, FreewayMergeEnv  # noqa: E402
from mapets_rl.experiment import (
    ExperimentConfig,
    atomic_savefig,
    atomic_write_text,
    evaluate_scripted,
    latest_checkpoint,
    mean_metrics,
    read_train_episodes,
)
from mapets_rl.metrics import MPH_PER_MPS  # noqa: E402
from mapets_rl.plotting import draw_curve  # noqa: E402
from mapets_rl.recipes.coma import COMA, COMAConfig  # noqa: E402
from mapets_rl.recipes.maddpg import OPENAI_MADDPG  # noqa: E402
from mapets_rl.recipes.shapley_ac import ShapleyAC, ShapleyACConfig  # noqa: E402
from mapets_rl.statistics import mean_ci95  # noqa: E402

RATIOS = (0.0, 0.17, 0.33, 0.5, 0.67, 0.83, 1.0)
SCALES = {
    "smoke": {"n_vehicles": 8, "frames": 80, "eval_episodes": 1},
    "cpu": {"n_vehicles": 30, "frames": 800, "eval_episodes": 2},
    "paper": {"n_vehicles": 30, "frames": 400_000, "eval_episodes": 5},
}
# recipe overrides of each scale, applied before --shapley-override / --coma-override
SCALE_OVERRIDES = {
    "smoke": {},
    "cpu": {"shapley_ac": ["num_permutations=8", "batch_size=64", "exact_max_agents=5"]},
    "paper": {},
}
METHODS = {"shapley_ac": (ShapleyAC, ShapleyACConfig), "coma": (COMA, COMAConfig)}
SCRIPTED = "scripted"  # keep lane under IDM, nothing trained
OPENAI_FIELDS = {
    "shapley_ac": frozenset(parse_override(item)[0] for item in OPENAI_MADDPG),
    "coma": frozenset({"gamma", "tau", "lr_critic", "num_cells", "max_grad_norm"}),
}
"""``--schedule openai``: the fields of :data:`OPENAI_MADDPG` each method gets."""
TRAIN_KEYS = {
    "system_return": "train_system_return",
    "average_velocity": "train_average_velocity",
    "average_comfort": "train_average_comfort",
}
"""Training-episode metric -> its key in a run's results (mean over the last ``--window``)."""
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


SCENARIO_ENVS = {"freeway": FreewayEnv, "freeway-merge": FreewayMergeEnv}
"""``--env`` -> the raw highway-env scenario driven by humans only (ratio 0)."""


def all_human(
    n_vehicles: int, episodes: int, seed: int, scenario: str = "freeway"
) -> dict[str, float]:
    """Average velocity / comfort / collisions of ``episodes`` all-human episodes."""
    env = SCENARIO_ENVS[scenario](config={"n_vehicles": n_vehicles, "cav_ratio": 0.0})
    per_episode = []
    for ep in range(episodes):
        env.reset(seed=1000 * seed + ep)
        done = False
        while not done:
            _, _, terminated, truncated, info = env.step(np.zeros(0, dtype=np.int64))
            done = terminated or truncated
        per_episode.append({k: float(v) for k, v in info["episode"].items()})
    return mean_metrics(per_episode)


def scripted(ratio: float, seed: int, args: argparse.Namespace) -> dict[str, float]:
    """Evaluation metrics of the scripted keep-lane CAVs at ``ratio`` on the evaluation
    episodes of ``seed`` (the ones the learned runs of that seed are scored on)."""
    return evaluate_scripted(
        ExperimentConfig(
            env=args.env,
            env_config=env_config(args, ratio, batched=False),  # evaluation steps one road
            seed=seed,
            eval_episodes=args.eval_episodes,
        )
    )


def env_config(args: argparse.Namespace, ratio: float, batched: bool = True) -> dict[str, Any]:
    """The runs' ``env_config`` at ``ratio``, plus ``backend: torch`` and (when ``batched``)
    ``num_envs`` on the torch backend."""
    config: dict[str, Any] = {"n_vehicles": args.n_vehicles, "cav_ratio": ratio}
    if args.backend == "torch":
        config["backend"] = "torch"
        if batched:
            config["num_envs"] = args.num_envs
    return config


def training_metrics(run_dir: Path, window: int) -> dict[str, float]:
    """``train_*`` means over the run's last ``window`` training episodes (all when it has
    fewer) and ``train_episodes``, the number it recorded; ``{}`` when it recorded none."""
    episodes = read_train_episodes(run_dir)
    count = len(episodes["system_return"])
    if count == 0:
        return {}
    out = {"train_episodes": float(count)}
    for key, name in TRAIN_KEYS.items():
        if key in episodes:
            values = episodes[key][-window:]
            values = values[np.isfinite(values)]
            if len(values):
                out[name] = float(values.mean())
    return out


def train_and_evaluate(
    method: str, ratio: float, seed: int, args: argparse.Namespace
) -> dict[str, float]:
    """Train ``method`` at ``ratio`` and return its final evaluation with its training
    metrics (:func:`training_metrics`); a run of the same budget already finished in
    ``--out`` is reused, one with a checkpoint resumed (so an interrupted table resumes)."""
    run_dir = Path(args.out) / "runs" / method / f"ratio{ratio:.2f}" / f"seed{seed}"
    results = run_dir / "results.json"
    if results.is_file():
        done = [
            e for e in json.loads(results.read_text())["evaluations"] if e["frames"] >= args.frames
        ]
        if done:
            return {**done[-1]["metrics"], **training_metrics(run_dir, args.window)}
    recipe, config_cls = METHODS[method]
    if latest_checkpoint(run_dir) is not None:
        exp = recipe.from_run_dir(run_dir, overrides=[f"total_frames={args.frames}"])
    else:
        batch = args.frames_per_batch or config_cls.default_frames_per_batch
        sizes = {}
        if method == "coma":
            sizes["minibatch_size"] = min(config_cls.minibatch_size, batch)
        config = config_cls(
            env=args.env,
            env_config=env_config(args, ratio),
            seed=seed,
            total_frames=args.frames,
            frames_per_batch=batch,
            **sizes,
            eval_interval=args.frames,
            checkpoint_interval=args.checkpoint_interval or args.frames,
            eval_episodes=args.eval_episodes,
            logger="csv",
            progress=args.progress,
        )
        exp = recipe(config.with_overrides(args.override.get(method, [])), run_dir)
    final = exp.train()[-1]["metrics"]
    return {**final, **training_metrics(run_dir, args.window)}


def _cell(values: list[float], digits: int = 2) -> str:
    mean, half = mean_ci95(values)
    return f"{mean:.{digits}f} ± {half:.{digits}f}" if len(values) > 1 else f"{mean:.{digits}f}"


def _train_cell(runs: list[dict[str, float]], key: str, scale: float = 1.0, digits: int = 2) -> str:
    """The table cell of training metric ``key`` over the seeds' runs; ``-`` unless every run
    has it."""
    if not all(key in r for r in runs):
        return "-"
    return _cell([r[key] * scale for r in runs], digits)


def build_table(results: dict[str, Any], args: argparse.Namespace) -> str:
    """Markdown Table I from ``results[method][ratio] = [per-seed metrics]``."""
    lines = [
        f"Average velocity and comfort of all {args.n_vehicles} vehicles (mean ± 95% Student-t "
        f"interval over seeds {', '.join(map(str, args.seeds))}); each run trained "
        f"{args.frames} frames, {args.eval_episodes} evaluation episode(s). Paper: CARLA, "
        "100k episodes.",
        "",
        f"Training columns: mean over each run's last {args.window} training episodes "
        "(system reward: summed over CAVs and steps); '-' for rows that train nothing.",
        "",
        "| method | CAV ratio | CAVs | velocity (mph) | velocity (m/s) | comfort "
        "| collisions / episode | training velocity (mph) | training comfort "
        "| training system reward | paper velocity (mph) | paper comfort |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for method, by_ratio in results.items():
        paper = {"shapley_ac": PAPER_SHAPLEY, "coma": PAPER_COMA}.get(method, {})
        for key, runs in by_ratio.items():
            ratio = float(key)
            v = [r["average_velocity"] for r in runs]
            ref = paper.get(round(ratio, 2))
            lines.append(
                f"| {method} | {ratio:.2f} | {int(round(ratio * args.n_vehicles))} "
                f"| {_cell([x * MPH_PER_MPS for x in v])} | {_cell(v)} "
                f"| {_cell([r['average_comfort'] for r in runs])} "
                f"| {_cell([r.get('collisions', 0.0) for r in runs], 1)} "
                f"| {_train_cell(runs, 'train_average_velocity', MPH_PER_MPS)} "
                f"| {_train_cell(runs, 'train_average_comfort')} "
                f"| {_train_cell(runs, 'train_system_return', digits=1)} "
                f"| {ref[0] if ref else '-'} | {ref[1] if ref else '-'} |"
            )
    return "\n".join(lines)


def plot_table(results: dict[str, Any], path: Path) -> None:
    """Velocity (mph) and comfort against the CAV ratio, one line per method with its
    bootstrap 95% band over seeds (:func:`mapets_rl.plotting.draw_curve`, inside each metric's
    range), and the paper's Shapley and COMA columns dashed."""
    fig, axes = plt.subplots(1, 2, figsize=(10, 4))
    for method, by_ratio in results.items():
        ratios = [float(k) for k in by_ratio]
        for ax, key, scale in zip(
            axes, ("average_velocity", "average_comfort"), (MPH_PER_MPS, 1.0), strict=True
        ):
            seeds = np.array([[r[key] * scale for r in runs] for runs in by_ratio.values()])
            draw_curve(ax, ratios, seeds.T, metric=key, marker="o", ms=3, label=method)
    for name, paper in (("paper Shapley", PAPER_SHAPLEY), ("paper COMA", PAPER_COMA)):
        for ax, k in zip(axes, (0, 1), strict=True):
            ax.plot(list(paper), [v[k] for v in paper.values()], "--", label=name)
    for ax, label in zip(axes, ("average velocity (mph)", "average comfort"), strict=True):
        ax.set_xlabel("CAV ratio")
        ax.set_ylabel(label)
    axes[0].legend(fontsize=8)
    fig.tight_layout()
    atomic_savefig(fig, path)
    plt.close(fig)


def last_wins(*groups: list[str]) -> list[str]:
    """``key=value`` overrides of ``groups`` in order, a key given again replacing the
    earlier value (a config refuses a key given twice)."""
    merged: dict[str, str] = {}
    for group in groups:
        for item in group:
            key = parse_override(item)[0]
            merged.pop(key, None)
            merged[key] = item
    return list(merged.values())


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scale", choices=sorted(SCALES), default="cpu")
    parser.add_argument(
        "--methods",
        nargs="+",
        choices=sorted([*METHODS, SCRIPTED]),
        default=[*METHODS, SCRIPTED],
    )
    parser.add_argument("--ratios", nargs="+", type=float, default=list(RATIOS))
    parser.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2])
    parser.add_argument("--n-vehicles", type=int, default=None)
    parser.add_argument("--frames", type=int, default=None)
    parser.add_argument("--eval-episodes", type=int, default=None)
    parser.add_argument(
        "--shapley-override",
        nargs="*",
        default=[],
        help="extra key=value overrides of the shapley_ac config",
    )
    parser.add_argument(
        "--coma-override", nargs="*", default=[], help="extra key=value overrides of coma"
    )
    parser.add_argument(
        "--env",
        default="freeway",
        choices=sorted(SCENARIO_ENVS),
        help="freeway-merge: the on-ramp social dilemma (issue 21)",
    )
    parser.add_argument(
        "--backend",
        default="highway-env",
        choices=["highway-env", "torch"],
        help="torch: --num-envs roads of the batched torch freeway per run",
    )
    parser.add_argument("--num-envs", type=int, default=4, help="roads (torch backend)")
    parser.add_argument(
        "--frames-per-batch",
        type=int,
        default=None,
        help="frames per collected batch (default: the recipe's; torch: 10 x --num-envs)",
    )
    parser.add_argument(
        "--schedule",
        choices=["default", "openai"],
        default="default",
        help="openai: openai/maddpg's update schedule where a recipe has the field",
    )
    parser.add_argument(
        "--window",
        type=int,
        default=1000,
        help="training episodes (the last ones of each run) the training columns average",
    )
    parser.add_argument(
        "--checkpoint-interval",
        type=int,
        default=None,
        help="frames between checkpoints (default: one at the end of each run)",
    )
    parser.add_argument("--out", default="outputs/mixed_traffic")
    parser.add_argument("--progress", action="store_true")
    args = parser.parse_args(argv)
    for key, value in SCALES[args.scale].items():
        if getattr(args, key) is None:
            setattr(args, key, value)
    bad = [r for r in args.ratios if not 0.0 <= r <= 1.0]
    if bad:
        parser.error(f"--ratios must lie in [0, 1], got {bad}")
    if args.n_vehicles < 1:
        parser.error(f"--n-vehicles must be >= 1, got {args.n_vehicles}")
    if args.frames < 40:
        parser.error(f"--frames must be >= 40 (one episode), got {args.frames}")
    if args.eval_episodes < 1:
        parser.error(f"--eval-episodes must be >= 1, got {args.eval_episodes}")
    if args.num_envs < 1:
        parser.error(f"--num-envs must be >= 1, got {args.num_envs}")
    if args.window < 1:
        parser.error(f"--window must be >= 1, got {args.window}")
    if args.frames_per_batch is None and args.backend == "torch":
        args.frames_per_batch = 10 * args.num_envs
    preset = SCALE_OVERRIDES[args.scale]

    def schedule(method: str) -> list[str]:
        if args.schedule == "default":
            return []
        return [i for i in OPENAI_MADDPG if parse_override(i)[0] in OPENAI_FIELDS[method]]

    args.override = {
        "shapley_ac": last_wins(
            preset.get("shapley_ac", []), schedule("shapley_ac"), args.shapley_override
        ),
        "coma": last_wins(preset.get("coma", []), schedule("coma"), args.coma_override),
    }
    return args


def main(argv: list[str] | None = None) -> dict[str, Any]:
    args = parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    results: dict[str, Any] = {method: {} for method in args.methods}
    for method in args.methods:
        for ratio in args.ratios:
            n_cavs = int(round(ratio * args.n_vehicles))
            runs = []
            for seed in args.seeds:
                print(f"{method}: CAV ratio {ratio:.2f} ({n_cavs} CAVs), seed {seed}", flush=True)
                if n_cavs == 0:
                    runs.append(all_human(args.n_vehicles, args.eval_episodes, seed, args.env))
                elif method == SCRIPTED:
                    runs.append(scripted(ratio, seed, args))
                else:
                    runs.append(train_and_evaluate(method, ratio, seed, args))
            results[method][f"{ratio:.2f}"] = runs
    table = build_table(results, args)
    atomic_write_text(out / "table.md", table + "\n")
    atomic_write_text(out / "results.json", json.dumps(results, indent=1))
    plot_table(results, out / "velocity_comfort.png")
    print(table)
    return results


if __name__ == "__main__":
    from mapets_rl import quiet_dependencies

    quiet_dependencies()
    main()
