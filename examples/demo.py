"""Main job of the README: a short MA-PETS training on the figure-eight (``make demo``).

Eight CAVs learn to drive the figure-eight among human-driven vehicles with MA-PETS
(``recipes/mapets.py``): episode 1 drives with random actions, every later episode each CAV
plans with the batched CEM planner through its own probabilistic ensemble, and at every
episode's end the CAVs within d = 100 m exchange their transitions and refit their ensembles.
Prints agility and safety per episode and writes a learning-curve plot (and, with ``--gif``, a
GIF of one planned episode after training).

Sizes are the ``cpu`` preset; episodes are the paper's 200 steps (20 s), and there are 6 of
them instead of the paper's 15, so that the demo takes a few minutes on two CPU cores.
``examples/mapets_figure_eight.py`` runs the full experiment (3 seeds x 15 episodes).

    python examples/demo.py [--episodes 6] [--steps 200] [--out outputs/demo] [--gif]
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

from mapets_rl.experiment import atomic_savefig, default_run_dir  # noqa: E402
from mapets_rl.plotting import draw_curve  # noqa: E402
from mapets_rl.recipes.mapets import MAPETS, MAPETSConfig  # noqa: E402


def plot(history: list[dict[str, float]], path: Path, title: str) -> None:
    """Agility and safety against the episode (one seed: no band;
    :func:`mapets_rl.plotting.draw_curve`), the random-action episodes marked."""
    episodes = [int(m["episode"]) for m in history]
    fig, (ax_a, ax_s) = plt.subplots(1, 2, figsize=(9, 3.4))
    for ax, key, label in ((ax_a, "agility", "agility [m/step]"), (ax_s, "safety", "safety")):
        values = [m[key] for m in history]
        draw_curve(
            ax,
            episodes,
            [values],
            metric=key,
            marker="o",
            color="tab:blue",
            label="MA-PETS (planner)",
        )
        random = [(e, v) for e, v, m in zip(episodes, values, history, strict=True) if m["random"]]
        if random:
            ax.plot(*zip(*random, strict=True), "s", color="tab:gray", label="random actions")
        ax.set_xlabel("episode")
        ax.set_ylabel(label)
        ax.set_xticks(episodes)
        ax.grid(alpha=0.3)
    ax_s.set_ylim(-0.02, 1.02)
    ax_a.legend(loc="lower right")
    fig.suptitle(title)
    fig.tight_layout()
    atomic_savefig(fig, path)
    plt.close(fig)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument(
        "--episodes",
        type=int,
        default=6,
        help="episodes, the first with random actions (default 6)",
    )
    parser.add_argument(
        "--steps", type=int, default=200, help="steps per episode (0.1 s each; paper: 200)"
    )
    parser.add_argument("--cavs", type=int, default=8, help="CAVs (paper: 8)")
    parser.add_argument("--comm-range", type=float, default=100.0, help="d in metres")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument(
        "--threads",
        type=int,
        default=1,
        help="torch threads (1 is fastest on a shared 2-core machine)",
    )
    parser.add_argument("--out", type=Path, default=Path("outputs/demo"))
    parser.add_argument(
        "--gif", action="store_true", help="after training, record one planned episode as a GIF"
    )
    args = parser.parse_args()
    for name in ("episodes", "steps", "cavs", "threads"):
        if getattr(args, name) < 1:
            parser.error(f"--{name} must be >= 1, got {getattr(args, name)}")
    if args.comm_range < 0:
        parser.error(f"--comm-range must be >= 0, got {args.comm_range}")
    env_config = {"n_cavs": args.cavs, "horizon": args.steps}
    if args.gif:
        env_config["render_mode"] = "rgb_array"
    config = MAPETSConfig(
        env_config=env_config,
        seed=args.seed,
        episodes=args.episodes,
        comm={"comm_range": args.comm_range},
        preset="cpu",
        num_threads=args.threads,
        progress=False,
    )
    run_dir = default_run_dir("mapets", config.env, config.seed, root=args.out)
    plan = config.planner
    print(
        f"MA-PETS on the figure-eight: {args.cavs} CAVs, d = {args.comm_range:g} m, "
        f"{args.episodes} episodes of {args.steps} steps, "
        f"cpu preset (w={plan.horizon}, Q={plan.population}, X={plan.elites}, "
        f"Y={plan.iterations}, P={plan.particles}, B={config.model.ensemble_size}, "
        f"hidden={config.model.hidden}); run dir {run_dir}",
        flush=True,
    )
    start = time.perf_counter()
    exp = MAPETS(config, run_dir)

    def report(m: dict[str, float]) -> None:
        mode = "random actions" if m["random"] else "planner"
        print(
            f"episode {int(m['episode'])} ({mode}): agility {m['agility']:.3f} m/step, "
            f"safety {m['safety']:.3f}, collisions {int(m['collisions'])}/{args.cavs}, "
            f"transitions shared {int(m['transitions_shared'])}, "
            f"[{time.perf_counter() - start:.0f} s]",
            flush=True,
        )

    exp.train(on_episode_end=report)
    history = [e["metrics"] for e in exp.results.train]
    random, planned = history[0], history[1:]
    if planned:
        print(
            f"random-action episode: safety {random['safety']:.3f}; last episode: safety "
            f"{planned[-1]['safety']:.3f}; planned episodes: mean safety "
            f"{sum(m['safety'] for m in planned) / len(planned):.3f}, collisions "
            f"{int(sum(m['collisions'] for m in planned))} in {len(planned)} episodes"
        )
    plot_path = args.out / "learning_curve.png"
    plot(
        history,
        plot_path,
        f"MA-PETS, figure-eight, {args.cavs} CAVs, d = {args.comm_range:g} m "
        f"({args.steps}-step episodes)",
    )
    print(f"wrote {plot_path} (metrics: {run_dir / 'results.json'})")
    if args.gif:
        metrics = exp.evaluate(episodes=1, video=True)
        gif = next((run_dir / "videos").glob("*.gif"))
        print(
            f"planned episode: agility {metrics['agility']:.3f} m/step, "
            f"safety {metrics['safety']:.3f}; wrote {gif}"
        )
    print(f"total {time.perf_counter() - start:.0f} s")


if __name__ == "__main__":
    from mapets_rl import quiet_dependencies

    quiet_dependencies()
    main()
