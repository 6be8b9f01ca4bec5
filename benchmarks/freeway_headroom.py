"""How much room does the freeway's reward leave above "every CAV keeps its lane"?

The learned Shapley AC, MADDPG and COMA policies at 30 vehicles end on exactly the scripted
keep-lane policy's evaluation numbers (issue 13). This script asks whether anything better
exists: it scores a hand-written greedy overtaking rule against keep-lane on the same
evaluation episodes (``evaluate_scripted``), per CAV ratio and seed. A CAV whose leader in its
lane is slower and close changes to an adjacent lane (left first) when that lane's front gap is
longer by ``--gain-gap`` metres and its rear gap exceeds ``--rear-gap`` metres; otherwise it
keeps its lane. Speeds stay under IDM in both policies. If the rule beats keep-lane, the reward
has headroom the learners did not find; if not, keep-lane is hard to beat on this reward.

On ``--env freeway-merge`` (the freeway with an on-ramp, issue 21) a third, cooperative rule
joins them (``CooperativeMerge``): a CAV in the rightmost lane before the merge point moves
left when a ramp vehicle is beside it (60 m ahead to 30 m behind) and the left lane has room;
otherwise it keeps its lane.

Run:  python benchmarks/freeway_headroom.py [--env freeway-merge] [--ratios 0.5 1]
          [--seeds 0 1 2] [--eval-episodes 5] [--env-override velocity_weight=1.0]
Prints a markdown table: system return (sum over CAVs and steps) and average velocity of all
vehicles, mean +- 95% interval over seeds, the per-seed difference policy - keep-lane, and the
mean system return relative to keep-lane's (and, for the cooperative rule, to the greedy
rule's).
"""

from __future__ import annotations

import argparse

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torchrl.envs import EnvBase

from mapets_rl.envs import scenario_config
from mapets_rl.envs.freeway import CL, CR, KL, OBS_DIM
from mapets_rl.envs.freeway_merge import OBS_DIM as MERGE_OBS_DIM
from mapets_rl.experiment import ExperimentConfig, evaluate_scripted
from mapets_rl.machine import machine_line
from mapets_rl.metrics import MPH_PER_MPS
from mapets_rl.modules import ACTION, OBS
from mapets_rl.statistics import mean_ci95


class GreedyOvertaking(TensorDictModuleBase):
    """The overtaking rule above, vectorised over CAVs: observation ``[*, n, >= 22]`` (own speed,
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
        nb = obs[..., 4:OBS_DIM].unflatten(-1, (3, 2, 3))  # [*, n, lane (L, own, R), front/rear, 3]
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


class CooperativeMerge(TensorDictModuleBase):
    """The cooperative rule of ``freeway-merge``, vectorised over CAVs: observation
    ``[*, n, 24]`` (the freeway's 22 entries, whose right block is the ramp for a CAV in the
    rightmost lane; then the distances to the acceleration lane's start and to the merge
    point) -> one-hot action ``[*, n, 4]``.

    A CAV in the rightmost lane (``lanes - 1``) less than ``approach`` metres before the
    acceleration lane (the distance is clipped at the perception range, so ``approach`` should
    not exceed it) and before the merge point changes left when a ramp vehicle is beside it (the
    nearest ramp vehicle ahead within ``ramp_ahead`` metres or behind within ``ramp_behind``
    metres) and the left lane has room (front gap > ``front_gap``, rear gap > ``rear_gap`` +
    ``closing_time`` x the speed at which the left rear vehicle comes up);
    every other CAV keeps its lane (a CAV on the ramp merges by MOBIL under KL)."""

    in_keys = [OBS]
    out_keys = [ACTION]

    def __init__(
        self,
        lanes: int,
        approach: float,
        ramp_ahead: float,
        ramp_behind: float,
        front_gap: float,
        rear_gap: float,
        closing_time: float,
        dtype: torch.dtype,
    ) -> None:
        super().__init__()
        self.lanes, self.approach, self.dtype = lanes, approach, dtype
        self.closing_time = closing_time
        self.ramp_ahead, self.ramp_behind = ramp_ahead, ramp_behind
        self.front_gap, self.rear_gap = front_gap, rear_gap

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        obs = tensordict.get(OBS)
        if obs.shape[-1] != MERGE_OBS_DIM:
            raise ValueError(
                f"CooperativeMerge needs freeway-merge observations ({MERGE_OBS_DIM} entries), "
                f"got {obs.shape[-1]}"
            )
        lane = obs[..., 1]
        nb = obs[..., 4:OBS_DIM].unflatten(-1, (3, 2, 3))  # [*, n, lane (L, own, R), front/rear, 3]
        to_start, to_end = obs[..., OBS_DIM], obs[..., OBS_DIM + 1]
        near = (lane == self.lanes - 1) & (to_start < self.approach) & (to_end > 0)
        ramp_front = (nb[..., 2, 0, 0] > 0) & (nb[..., 2, 0, 1] <= self.ramp_ahead)
        ramp_rear = (nb[..., 2, 1, 0] > 0) & (-nb[..., 2, 1, 1] <= self.ramp_behind)
        closing = nb[..., 0, 1, 2].clamp(min=0.0)  # how fast the left rear vehicle comes up
        room = (nb[..., 0, 0, 1] > self.front_gap) & (
            -nb[..., 0, 1, 1] > self.rear_gap + self.closing_time * closing
        )
        yield_left = near & (ramp_front | ramp_rear) & room
        index = torch.where(yield_left, CL, KL).long()
        tensordict.set(ACTION, torch.nn.functional.one_hot(index, 4).to(self.dtype))
        return tensordict


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--env", choices=["freeway", "freeway-merge"], default="freeway")
    parser.add_argument("--ratios", nargs="+", type=float, default=[0.5, 1.0])
    parser.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2])
    parser.add_argument("--n-vehicles", type=int, default=30)
    parser.add_argument("--eval-episodes", type=int, default=5)
    parser.add_argument("--follow-gap", type=float, default=40.0, help="m")
    parser.add_argument("--gain-gap", type=float, default=15.0, help="m")
    parser.add_argument("--rear-gap", type=float, default=15.0, help="m")
    parser.add_argument(
        "--approach",
        type=float,
        default=float("inf"),
        help="m before the acceleration lane (merge); default: anywhere before the merge point",
    )
    parser.add_argument("--ramp-ahead", type=float, default=60.0, help="m (merge)")
    parser.add_argument("--ramp-behind", type=float, default=30.0, help="m (merge)")
    parser.add_argument("--yield-front-gap", type=float, default=15.0, help="m (merge)")
    parser.add_argument("--yield-rear-gap", type=float, default=15.0, help="m (merge)")
    parser.add_argument("--closing-time", type=float, default=1.5, help="s (merge)")
    parser.add_argument("--env-override", nargs="*", default=[], metavar="KEY=VALUE")
    parser.add_argument(
        "--backend", choices=["highway-env", "torch"], default="highway-env",
        help="the scenario's simulator (benchmarks/freeway_calibration.py compares both on "
        "identical start scenes)",
    )  # fmt: skip
    args = parser.parse_args(argv)
    if not all(0.0 < r <= 1.0 for r in args.ratios):
        parser.error(f"--ratios must lie in (0, 1] (some CAVs), got {args.ratios}")
    if args.eval_episodes < 1:
        parser.error(f"--eval-episodes must be >= 1, got {args.eval_episodes}")
    print(f"# {machine_line()}")

    def overtaking(env: EnvBase) -> TensorDictModuleBase:
        spec = env.full_action_spec[ACTION]
        lanes = int(scenario_config(env)["lanes"])
        return GreedyOvertaking(lanes, args.follow_gap, args.gain_gap, args.rear_gap, spec.dtype)

    def cooperative(env: EnvBase) -> TensorDictModuleBase:
        spec = env.full_action_spec[ACTION]
        lanes = int(scenario_config(env)["lanes"])
        return CooperativeMerge(
            lanes,
            args.approach,
            args.ramp_ahead,
            args.ramp_behind,
            args.yield_front_gap,
            args.yield_rear_gap,
            args.closing_time,
            spec.dtype,
        )

    policies = {"keep lane": None, "greedy overtaking": overtaking}
    if args.env == "freeway-merge":
        policies["cooperative merge"] = cooperative

    print(
        f"# env {args.env} ({args.backend} backend), {args.n_vehicles} vehicles, overrides "
        f"{args.env_override or 'none'}"
    )
    print(
        "| CAV ratio | policy | system return | velocity (mph) | comfort | collisions / episode "
        + ("| ramp vehicles stuck / episode " if args.env == "freeway-merge" else "")
        + "| policy - keep lane, per seed | vs keep lane | vs greedy |"
    )
    print("|---|---|---|---|---|---|---|---|" + ("---|" if args.env == "freeway-merge" else ""))
    for ratio in args.ratios:
        rows: dict[str, list[dict[str, float]]] = {name: [] for name in policies}
        for seed in args.seeds:
            config = ExperimentConfig(
                env=args.env,
                env_config={
                    "n_vehicles": args.n_vehicles,
                    "cav_ratio": ratio,
                    **({"backend": "torch"} if args.backend == "torch" else {}),
                },
                seed=seed,
                eval_episodes=args.eval_episodes,
            ).with_overrides([f"env_config.{o}" for o in args.env_override])
            for name, policy in policies.items():
                rows[name].append(
                    evaluate_scripted(config)
                    if policy is None
                    else evaluate_scripted(config, policy)
                )

        system = {name: [r["system_return"] for r in runs] for name, runs in rows.items()}
        for name, runs in rows.items():
            diff = [p - k for p, k in zip(system[name], system["keep lane"], strict=True)]
            cells = []
            for key, scale, digits in (
                ("system_return", 1.0, 1),
                ("average_velocity", MPH_PER_MPS, 2),
                ("average_comfort", 1.0, 2),
                ("collisions", 1.0, 1),
                *((("ramp_stuck", 1.0, 1),) if args.env == "freeway-merge" else ()),
            ):
                mean, half = mean_ci95([r[key] * scale for r in runs])
                cells.append(f"{mean:.{digits}f} ± {half:.{digits}f}")
            extra = ", ".join(f"{d:+.1f}" for d in diff) if name != "keep lane" else ""
            relative = [
                f"{100 * (sum(system[name]) / sum(system[other]) - 1):+.1f}%"
                if name != other
                else ""
                for other in ("keep lane", "greedy overtaking")
            ]
            cells += [extra, *relative]
            print(f"| {ratio:.2f} | {name} | {' | '.join(cells)} |", flush=True)


if __name__ == "__main__":
    from mapets_rl import quiet_dependencies

    quiet_dependencies()
    main()
