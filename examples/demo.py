"""Main job of the README (scripted baseline until the MA-PETS recipe takes over).

Runs the figure-eight scenario (8 CAVs + human-driven vehicles) with the scripted CAV policy,
prints per-episode agility and safety, writes a GIF of the last episode and a plot.

    python examples/demo.py [--episodes 3] [--out outputs/demo]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import imageio.v2 as imageio
import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

from mapets_rl.envs import FigureEightEnv  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--episodes", type=int, default=3)
    parser.add_argument("--out", type=Path, default=Path("outputs/demo"))
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    env = FigureEightEnv({"n_cavs": 8}, render_mode="rgb_array")
    history = []
    for episode in range(1, args.episodes + 1):
        env.reset(seed=episode)
        frames, done = [], False
        while not done:
            _, _, terminated, truncated, info = env.step(env.scripted_action())
            done = terminated or truncated
            if episode == args.episodes and env.steps_taken % 4 == 0:
                frames.append(env.render())
        metrics = info["episode"]
        history.append(metrics)
        print(
            f"episode {episode}: agility {metrics['agility']:.3f} m/step, "
            f"safety {metrics['safety']:.3f}"
        )
    imageio.mimsave(args.out / "episode.gif", frames, duration=0.1)
    fig, ax = plt.subplots(figsize=(5, 3))
    ax.plot([m["agility"] for m in history], marker="o", label="agility [m/step]")
    ax.plot([m["safety"] for m in history], marker="s", label="safety")
    ax.set_xlabel("episode")
    ax.legend()
    fig.tight_layout()
    fig.savefig(args.out / "metrics.png")
    print(f"wrote {args.out / 'episode.gif'} and {args.out / 'metrics.png'}")


if __name__ == "__main__":
    main()
