"""MAPPO, MADDPG and SAC on the figure-eight at MA-PETS's sample budget, optionally on one plot
with MA-PETS (the MA-PETS paper's Figs. 3-4).

``--scenario figure-eight`` (8 CAVs, 200-step episodes, paper Fig. 3) or
``figure-eight-multilane`` (2 lanes, 22 CAVs, 400-step episodes, paper Fig. 4). MA-PETS trains
for 15 episodes (``--episodes``): 3000 environment steps on one lane, 6000 on two. This script
trains each baseline for that budget (``--budget-multiplier 1``, the default) or a multiple of
it (``10``: 30 000 steps on one lane), over several seeds, then runs ``mapets-rl compare`` on
the runs: learning curves with a bootstrap 95% band over seeds (PNG) and a markdown table of
the final agility, safety and reward. ``--mapets RUN_DIR ...`` adds MA-PETS runs (e.g. the
trials of ``benchmarks/ablations/comm_range.py``) to the same plot, one group per
communication range; MA-PETS's points are its training episodes (its planner acts the same
way in training and evaluation), the baselines' are deterministic evaluations.

    python examples/baselines_figure_eight.py                       # 3 x 3 runs of 3000 steps
    python examples/baselines_figure_eight.py --budget-multiplier 10 --workers 4
    python examples/baselines_figure_eight.py --scenario figure-eight-multilane \
        --eval-interval 400 --out outputs/baselines_multilane      # paper Fig. 4's baselines
    python examples/baselines_figure_eight.py --episodes 10 --eval-interval 200 \
        --mapets outputs/ablations/comm_range/trials/comm.comm_range={0,100}__seed=*

Runs live in ``OUT/steps<N>/<recipe>_seed<S>``; re-running the script skips finished runs and
resumes interrupted ones from their last checkpoint (bit-exact), so a long sweep can be spread
over several sessions.
"""

from __future__ import annotations

import argparse
import json
import os
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

SCENARIOS: dict[str, dict] = {
    "figure-eight": {"episode_steps": 200, "title": "figure-eight, 8 CAVs"},
    "figure-eight-multilane": {"episode_steps": 400, "title": "two-lane figure-eight, 22 CAVs"},
}
"""Per scenario: the paper's episode length H (its CAVs are the scenario's default) and the
plot's title."""

RECIPES = ("maddpg", "mappo", "sac")


def recipe_overrides(recipe: str, episode_steps: int) -> list[str]:
    """Hyper-parameters chosen for the small budget: one episode per collected batch, and for
    the off-policy methods one episode of random actions first (as MA-PETS's first episode)
    and 50 gradient steps per episode."""
    batch = f"frames_per_batch={episode_steps}"
    off_policy = [
        batch,
        "updates_per_batch=50",
        "batch_size=256",
        f"init_random_frames={episode_steps}",
    ]
    return {
        "mappo": [batch, f"minibatch_size={episode_steps // 4}", "epochs=10", "lr=1e-3"],
        "maddpg": off_policy,
        "sac": [*off_policy, "lr_actor=1e-3", "lr_critic=1e-3", "lr_alpha=1e-3"],
    }[recipe]


def run_one(
    recipe: str,
    seed: int,
    steps: int,
    run_dir: str,
    eval_interval: int,
    eval_episodes: int,
    scenario: str = "figure-eight",
) -> dict:
    """Train (or resume, or skip if finished) one run; returns its last evaluation."""
    import torch

    torch.set_num_threads(1)
    from mapets_rl.app.plugins import load_recipe
    from mapets_rl.experiment import latest_checkpoint, read_results

    cls = load_recipe(recipe)
    overrides = [
        *recipe_overrides(recipe, SCENARIOS[scenario]["episode_steps"]),
        f"total_frames={steps}",
        f"seed={seed}",
        f"eval_interval={eval_interval}",
        f"eval_episodes={eval_episodes}",
        f"checkpoint_interval={eval_interval}",
        "keep_last=1",
        "progress=false",
    ]
    if recipe == "maddpg":  # anneal the exploration noise over the whole budget
        overrides.append(f"sigma_anneal_frames={steps}")
    if latest_checkpoint(run_dir) is not None:
        done = read_results(run_dir)["evaluations"]
        if done and done[-1]["frames"] >= steps:
            return done[-1]
        exp = cls.from_run_dir(run_dir, overrides=[f"total_frames={steps}"])
    else:
        config = cls.Config(env=scenario).with_overrides(overrides)
        exp = cls(config, run_dir)
    return exp.train()[-1]


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "--budget-multiplier",
        type=int,
        default=1,
        help="multiple of MA-PETS's budget in environment steps (default 1)",
    )
    parser.add_argument(
        "--scenario",
        default="figure-eight",
        choices=list(SCENARIOS),
        help="one lane, 8 CAVs (paper Fig. 3) or two lanes, 22 CAVs (paper Fig. 4)",
    )
    parser.add_argument(
        "--episodes",
        type=int,
        default=15,
        help="MA-PETS's budget in episodes of the scenario's length (default 15, the paper's)",
    )
    parser.add_argument(
        "--eval-interval",
        type=int,
        default=None,
        help="frames between evaluations (default: a third of the budget, a tenth with "
        "--budget-multiplier > 1); the episode length gives one point per episode",
    )
    parser.add_argument(
        "--mapets",
        nargs="+",
        default=[],
        metavar="RUN_DIR",
        help="MA-PETS run directories to draw on the same plot (grouped by comm.comm_range)",
    )
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--recipes", nargs="+", default=["mappo", "maddpg", "sac"], choices=RECIPES)
    parser.add_argument("--out", default="runs/baselines_figure_eight")
    parser.add_argument("--workers", type=int, default=1, help="runs in parallel processes")
    parser.add_argument("--eval-episodes", type=int, default=3)
    args = parser.parse_args(argv)
    if args.budget_multiplier < 1:
        parser.error(f"--budget-multiplier must be >= 1, got {args.budget_multiplier}")
    if args.workers < 1:
        parser.error(f"--workers must be >= 1, got {args.workers}")
    if args.episodes < 1:
        parser.error(f"--episodes must be >= 1, got {args.episodes}")
    if args.eval_interval is not None and args.eval_interval < 1:
        parser.error(f"--eval-interval must be >= 1 frame, got {args.eval_interval}")
    if args.eval_episodes < 1:
        parser.error(f"--eval-episodes must be >= 1, got {args.eval_episodes}")
    missing = [d for d in args.mapets if not (Path(d) / "results.json").is_file()]
    if missing:
        parser.error(f"--mapets: no results.json in {missing}")

    episode_steps = SCENARIOS[args.scenario]["episode_steps"]
    steps = args.budget_multiplier * args.episodes * episode_steps
    eval_interval = args.eval_interval or (
        steps // 3 if args.budget_multiplier == 1 else steps // 10
    )
    root = Path(args.out) / f"steps{steps}"
    jobs = [
        (r, s, steps, str(root / f"{r}_seed{s}"), eval_interval, args.eval_episodes, args.scenario)
        for r in args.recipes
        for s in args.seeds
    ]
    print(f"{len(jobs)} runs of {steps} environment steps into {root}", flush=True)
    with ProcessPoolExecutor(max_workers=args.workers) as pool:
        futures = {job[:2]: pool.submit(run_one, *job) for job in jobs}
        for (recipe, seed), fut in futures.items():
            last = fut.result()
            m = last["metrics"]
            print(
                f"{recipe:7s} seed {seed}: frames {last['frames']}  agility "
                f"{m['agility']:.3f}  safety {m['safety']:.3f}  reward {m['reward']:.2f}",
                flush=True,
            )

    from mapets_rl.app.comparison import compare

    out = compare(
        [job[3] for job in jobs] + args.mapets,
        root / ("compare_with_mapets" if args.mapets else "compare"),
        metrics=["agility", "safety", "reward", "collisions"],
        group_by="comm.comm_range" if args.mapets else None,
        x_grid=episode_steps if args.mapets else None,  # MA-PETS episodes may end early
        title=SCENARIOS[args.scenario]["title"],
    )
    print(out["table"].read_text())
    print(json.dumps({k: os.fspath(v) for k, v in out.items()}))


if __name__ == "__main__":
    from mapets_rl import quiet_dependencies

    quiet_dependencies()
    main()
