"""How much room does the freeway's reward leave above "every CAV keeps its lane"?

The learned Shapley AC, MADDPG and COMA policies at 30 vehicles end on exactly the scripted
keep-lane policy's evaluation numbers (issue 13). This script asks whether anything better
exists: it scores a hand-written greedy overtaking rule against keep-lane on the same
evaluation episodes (``evaluate_scripted``), per CAV ratio and seed. A CAV whose leader in its
lane is slower and close changes to an adjacent lane (left first) when that lane's front gap is
longer by ``--gain-gap`` metres and its rear gap exceeds ``--rear-gap`` metres; otherwise it
keeps its lane. Speeds stay under IDM in both policies. If the rule beats keep-lane, the reward
has headroom the learners did not find; if not, keep-lane is hard to beat on this reward.

Run:  python benchmarks/freeway_headroom.py [--ratios 0.5 1] [--seeds 0 1 2]
          [--eval-episodes 5] [--env-override velocity_weight=1.0]
Prints a markdown table: system return (sum over CAVs and steps) and average velocity of all
vehicles, mean +- 95% interval over seeds, and the per-seed difference overtaking - keep-lane.
"""

from __future__ import annotations

import argparse
import platform

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torchrl.envs import EnvBase

from mapets_rl.envs import traffic_env
from mapets_rl.envs.freeway import CL, CR, KL
from mapets_rl.experiment import ExperimentConfig, evaluate_scripted, mean_ci95
from mapets_rl.metrics import MPH_PER_MPS
from mapets_rl.modules import ACTION, OBS


class GreedyOvertaking(TensorDictModuleBase):
    """The overtaking rule above, vectorised over CAVs: observation ``[*, n, 22]`` (own speed,
    lane, lateral offset, acceleration; then ``(present, dx, dv)`` for front/rear in the
    left/own/right lane) -> one-hot action ``[*, n, 4]``."""

    in_keys = [OBS]
    out_keys = [ACTION]

    def __init__(
        self, lanes: int, follow_gap: float, gain_gap: float, rear_gap: float, dtype: torch.dtype
    ) -> None:
        super().__init__()
        self.lanes, self.follow_gap = lanes, follow_gap
        self.gain_gap, self.rear_gap, self.dtype = gain_gap, rear_gap, dtype

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        obs = tensordict.get(OBS)
        lane = obs[..., 1]
        nb = obs[..., 4:].unflatten(-1, (3, 2, 3))  # [*, n, lane (L, own, R), front/rear, 3]
        front_dx, front_dv = nb[..., 1, 0, 1], nb[..., 1, 0, 2]
        blocked = (nb[..., 1, 0, 0] > 0) & (front_dx < self.follow_gap) & (front_dv < -0.5)

        def free(k: int, exists: torch.Tensor) -> torch.Tensor:
            longer = nb[..., k, 0, 1] > front_dx + self.gain_gap
            clear_behind = -nb[..., k, 1, 1] > self.rear_gap
            return exists & longer & clear_behind

        left = blocked & free(0, lane >= 1)
        right = blocked & ~left & free(2, lane <= self.lanes - 2)
        index = torch.full_like(lane, KL, dtype=torch.long)
        index = torch.where(left, CL, torch.where(right, CR, index))
        tensordict.set(ACTION, torch.nn.functional.one_hot(index, 4).to(self.dtype))
        return tensordict


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--ratios", nargs="+", type=float, default=[0.5, 1.0])
    parser.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2])
    parser.add_argument("--n-vehicles", type=int, default=30)
    parser.add_argument("--eval-episodes", type=int, default=5)
    parser.add_argument("--follow-gap", type=float, default=40.0, help="m")
    parser.add_argument("--gain-gap", type=float, default=15.0, help="m")
    parser.add_argument("--rear-gap", type=float, default=15.0, help="m")
    parser.add_argument("--env-override", nargs="*", default=[], metavar="KEY=VALUE")
    args = parser.parse_args(argv)
    if not all(0.0 < r <= 1.0 for r in args.ratios):
        parser.error(f"--ratios must lie in (0, 1] (some CAVs), got {args.ratios}")
    if args.eval_episodes < 1:
        parser.error(f"--eval-episodes must be >= 1, got {args.eval_episodes}")
    print(
        f"# {platform.processor() or platform.machine()}, torch {torch.__version__}, "
        f"CPU capability {torch.backends.cpu.get_cpu_capability()}"
    )

    def overtaking(env: EnvBase) -> TensorDictModuleBase:
        spec = env.full_action_spec[ACTION]
        lanes = int(traffic_env(env).config["lanes"])
        return GreedyOvertaking(lanes, args.follow_gap, args.gain_gap, args.rear_gap, spec.dtype)

    print(
        "| CAV ratio | policy | system return | velocity (mph) | comfort | collisions / episode "
        "| overtaking - keep lane, per seed |"
    )
    print("|---|---|---|---|---|---|---|")
    for ratio in args.ratios:
        rows: dict[str, list[dict[str, float]]] = {"keep lane": [], "greedy overtaking": []}
        for seed in args.seeds:
            config = ExperimentConfig(
                env="freeway",
                env_config={"n_vehicles": args.n_vehicles, "cav_ratio": ratio},
                seed=seed,
                eval_episodes=args.eval_episodes,
            ).with_overrides([f"env_config.{o}" for o in args.env_override])
            rows["keep lane"].append(evaluate_scripted(config))
            rows["greedy overtaking"].append(evaluate_scripted(config, overtaking))
        diff = [
            o["system_return"] - k["system_return"]
            for o, k in zip(rows["greedy overtaking"], rows["keep lane"], strict=True)
        ]
        for name, runs in rows.items():
            cells = []
            for key, scale, digits in (
                ("system_return", 1.0, 1),
                ("average_velocity", MPH_PER_MPS, 2),
                ("average_comfort", 1.0, 2),
                ("collisions", 1.0, 1),
            ):
                mean, half = mean_ci95([r[key] * scale for r in runs])
                cells.append(f"{mean:.{digits}f} ± {half:.{digits}f}")
            extra = ", ".join(f"{d:+.1f}" for d in diff) if name != "keep lane" else ""
            print(f"| {ratio:.2f} | {name} | {' | '.join(cells)} | {extra} |", flush=True)


if __name__ == "__main__":
    main()
