"""Calibration of the batched torch freeway against highway-env, on identical scenes.

For every scenario, scripted rule and CAV ratio, ``--episodes`` highway-env episodes are reset
with seeds ``0 .. episodes - 1``; each start scene is loaded into one road of a
:class:`~mapets_rl.envs.torch_freeway.simulator.BatchedFreeway` (all episodes are the roads of
one batch), and both simulators then run the rule closed-loop on their own observations for the
40-step episode. The table compares the means over episodes of the four episode numbers the
papers' tables use: system return (sum of the CAVs' rewards over the episode), average velocity
and comfort of all vehicles, and ramp vehicles stuck at the end (``freeway-merge``), with the
relative difference of the torch mean to highway-env's and the standard deviation over
episodes of highway-env's. Trajectories: the largest position difference over the 40 steps of
each episode (median and maximum over episodes) and the share of episodes whose vehicles stay
within 0.5 m of highway-env's.

Rules (reference policies, ``mapets_rl.envs.references``): ``keep-lane``, ``greedy``
(overtaking) and, on ``freeway-merge``, ``cooperative`` (yield to ramp vehicles).

    python benchmarks/freeway_calibration.py [--episodes 100]
        [--ratios 0.17 0.33 0.5 0.67 0.83 1] [--envs freeway-merge freeway]
        [--dtype float32] [--kernel native] [--out calibration.json]
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from pathlib import Path

import numpy as np
import torch
from tensordict import TensorDict

from mapets_rl.envs import FreewayEnv, FreewayMergeEnv
from mapets_rl.envs.freeway import KL
from mapets_rl.envs.references import CooperativeMerge, GreedyOvertaking
from mapets_rl.envs.torch_freeway.highway_state import load_scene
from mapets_rl.envs.torch_freeway.simulator import BatchedFreeway
from mapets_rl.machine import machine_line
from mapets_rl.modules import ACTION, OBS

METRICS = ("system_return", "average_velocity", "average_comfort", "ramp_stuck")


def rule(name: str, lanes: int) -> torch.nn.Module | None:
    """The reference rule ``name`` (None: keep lane), with its published settings."""
    if name == "greedy":
        return GreedyOvertaking(lanes)
    if name == "cooperative":
        return CooperativeMerge(lanes)
    return None


def decide(policy: torch.nn.Module | None, obs: torch.Tensor) -> torch.Tensor:
    """Action indices ``[..., I]`` of ``policy`` on observations ``[..., I, obs]``."""
    if policy is None:
        return torch.full(obs.shape[:-1], KL, dtype=torch.long)
    td = TensorDict({OBS: obs.float()}, batch_size=obs.shape[:-2])
    return policy(td).get(ACTION).argmax(-1)


def run(
    env_class: type[FreewayEnv],
    ratio: float,
    rule_name: str,
    episodes: int,
    dtype: torch.dtype,
    kernel: str,
) -> dict:
    """Both simulators on ``episodes`` identical start scenes; per-episode numbers of each."""
    merge = env_class is FreewayMergeEnv
    config = {"n_vehicles": 30, "cav_ratio": ratio}
    envs = []
    for seed in range(episodes):
        env = env_class(config)
        env.reset(seed=seed)
        envs.append(env)
    sim = BatchedFreeway(dict(envs[0].config), merge, episodes, dtype=dtype, kernel=kernel)
    for road, env in enumerate(envs):
        load_scene(sim, road, env)
    policy = rule(rule_name, int(envs[0].config["lanes"]))
    horizon = int(envs[0].config["horizon"])
    start = time.process_time()
    highway: dict[str, list[float]] = {key: [] for key in METRICS}
    highway_positions = np.zeros((episodes, horizon, 30, 2))
    for k, env in enumerate(envs):
        obs, total = env.observe_agents(), 0.0
        for t in range(horizon):
            action = decide(policy, torch.as_tensor(obs)).numpy()
            obs, _, terminated, truncated, info = env.step(action)
            total += float(info["agent_rewards"].sum())
            highway_positions[k, t] = [v.position for v in env.vehicles_all]
            if terminated or truncated:
                highway_positions[k, t + 1 :] = highway_positions[k, t]
                break
        metrics = env.episode_metrics()
        highway["system_return"].append(total)
        for key in METRICS[1:]:
            highway[key].append(float(metrics.get(key, 0.0)))
    highway_seconds = time.process_time() - start
    start = time.process_time()
    obs, total = sim.observe(), torch.zeros(episodes, dtype=torch.float64)
    torch_positions = np.zeros_like(highway_positions)
    running = torch.ones(episodes, dtype=torch.bool)
    for t in range(horizon):
        result = sim.step(decide(policy, obs))
        obs = result.observation
        total += torch.where(running, result.reward.double().sum(1), 0.0)
        xy = torch.stack([sim.state["bodies", "x"], sim.state["bodies", "y"]], -1)[:, :30]
        torch_positions[:, t] = xy.double().numpy()
        running &= ~(result.terminated | result.truncated)
    torch_seconds = time.process_time() - start
    ours = {key: value.tolist() for key, value in sim.episode_metrics().items()}
    ours["system_return"] = total.tolist()
    ours.setdefault("ramp_stuck", [0.0] * episodes)
    worst = np.abs(torch_positions - highway_positions).max(axis=(1, 2, 3))
    return {
        "highway": highway,
        "torch": {key: ours[key] for key in METRICS},
        "max_position_difference": worst.tolist(),
        "cpu_seconds": {"highway": highway_seconds, "torch": torch_seconds},
    }


def relative(ours: float, theirs: float) -> str:
    if theirs == 0:
        return "0" if ours == 0 else "n/a"
    return f"{100 * (ours - theirs) / abs(theirs):+.2f}%"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--envs", nargs="+", default=["freeway-merge", "freeway"],
                        choices=["freeway", "freeway-merge"])  # fmt: skip
    parser.add_argument("--ratios", nargs="+", type=float,
                        default=[0.17, 0.33, 0.5, 0.67, 0.83, 1.0])  # fmt: skip
    parser.add_argument("--episodes", type=int, default=100)
    parser.add_argument("--dtype", choices=["float32", "float64"], default="float32")
    parser.add_argument(
        "--kernel", choices=["native", "torch"], default="native",
        help="the fused CPU kernel (the default on CPUs) or the torch program",
    )  # fmt: skip
    parser.add_argument("--out", type=Path, default=None, help="write the per-episode numbers")
    args = parser.parse_args()
    if args.episodes < 2:
        parser.error(f"--episodes must be >= 2, got {args.episodes}")
    if not all(0.0 < r <= 1.0 for r in args.ratios):
        parser.error(f"--ratios must lie in (0, 1], got {args.ratios}")
    torch.set_num_threads(1)
    dtype = getattr(torch, args.dtype)
    print(
        f"# {machine_line()}, {args.dtype}, {args.kernel}, "
        f"{args.episodes} episodes (seeds 0..{args.episodes - 1}) per row"
    )
    print(
        "| scenario | rule | ratio | system return hw / torch (diff) | velocity [m/s] hw / torch "
        "(diff) | comfort hw / torch (diff) | ramp stuck hw / torch | episodes within 0.5 m | "
        "max position diff median / max [m] |"
    )
    print("|---|---|---|---|---|---|---|---|---|")
    everything = {}
    for name in args.envs:
        env_class = FreewayMergeEnv if name == "freeway-merge" else FreewayEnv
        rules = ["keep-lane", "greedy"] + (["cooperative"] if name == "freeway-merge" else [])
        for rule_name in rules:
            for ratio in args.ratios:
                out = run(env_class, ratio, rule_name, args.episodes, dtype, args.kernel)
                everything[f"{name}/{rule_name}/{ratio}"] = out
                cells = []
                for key in METRICS[:3]:
                    theirs = statistics.mean(out["highway"][key])
                    ours = statistics.mean(out["torch"][key])
                    spread = statistics.stdev(out["highway"][key])
                    cells.append(
                        f"{theirs:.3f} / {ours:.3f} ({relative(ours, theirs)}; sd {spread:.2f})"
                    )
                stuck = (statistics.mean(out["highway"]["ramp_stuck"]),
                         statistics.mean(out["torch"]["ramp_stuck"]))  # fmt: skip
                worst = out["max_position_difference"]
                within = sum(w <= 0.5 for w in worst) / len(worst)
                print(
                    f"| {name} | {rule_name} | {ratio} | {' | '.join(cells)} | "
                    f"{stuck[0]:.2f} / {stuck[1]:.2f} | {100 * within:.0f}% | "
                    f"{statistics.median(worst):.2g} / {max(worst):.2g} |",
                    flush=True,
                )
    if args.out is not None:
        args.out.write_text(json.dumps(everything))


if __name__ == "__main__":
    from mapets_rl import quiet_dependencies

    quiet_dependencies()
    main()
