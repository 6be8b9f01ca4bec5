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
joins them (``mapets_rl.envs.references.CooperativeMerge``; the overtaking rule is
``GreedyOvertaking``): a CAV in the rightmost lane before the merge point moves
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

from tensordict.nn import TensorDictModuleBase
from torchrl.data import OneHot
from torchrl.envs import EnvBase

from mapets_rl.envs import scenario_config
from mapets_rl.envs.references import CooperativeMerge, GreedyOvertaking
from mapets_rl.experiment import ExperimentConfig, evaluate_scripted
from mapets_rl.machine import machine_line
from mapets_rl.metrics import MPH_PER_MPS
from mapets_rl.statistics import mean_ci95


def action_format(env: EnvBase) -> dict:
    """The rules' keyword arguments for ``env``'s CAV action (one-hot or index, its dtype)."""
    spec = env.full_action_spec[("agents", "action")]
    return {"one_hot": isinstance(spec, OneHot), "dtype": spec.dtype}


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
        lanes = int(scenario_config(env)["lanes"])
        gaps = (args.follow_gap, args.gain_gap, args.rear_gap)
        return GreedyOvertaking(lanes, *gaps, **action_format(env))

    def cooperative(env: EnvBase) -> TensorDictModuleBase:
        lanes = int(scenario_config(env)["lanes"])
        gaps = (args.ramp_ahead, args.ramp_behind, args.yield_front_gap, args.yield_rear_gap)
        return CooperativeMerge(
            lanes, args.approach, *gaps, args.closing_time, **action_format(env)
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
