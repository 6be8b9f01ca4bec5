"""Calibration of the SUMO figure-eights against the highway-env ones, on the same scripted
policies (issue 54).

For each scenario (``figure-eight``, ``figure-eight-multilane``), back end (``highway-env``,
``sumo``) and policy, ``--seeds`` episodes (seeds ``0 .. seeds - 1``) run to their horizon
through ``make_env(name, backend=...)``; the table gives the median over episodes and the
interquartile range of: agility (paper eq. 27, m/step), safety (eq. 28), CAVs crashed per
episode, the human drivers' mean speed (m/s, over the vehicles on the road and the steps of the
episode) and env steps per second (the env's ``step`` alone, policy excluded).

Policies: ``random`` (uniform target speed and, on two lanes, uniform lane-change flag),
``keep-speed`` (target speed = the CAV's own speed, no lane change: a CAV holds its initial
speed) and ``oracle`` (the cpu-preset CEM planner over the exact own-motion model,
:class:`~mapets_rl.envs.figure_eight_kinematics.FigureEightKinematicModel`, scored with the
scenario's planner reward; slow, so off by default).

    python benchmarks/sumo_calibration.py [--seeds 8] [--policies random keep-speed]
        [--envs figure-eight figure-eight-multilane] [--out calibration.json]
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
import torch
from _common import RandomPolicy, oracle_planner
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torchrl.envs.utils import step_mdp

from mapets_rl.envs import FigureEightPlannerReward, make_env
from mapets_rl.machine import machine_line

BACKENDS = ("highway-env", "sumo")
POLICIES = ("random", "keep-speed", "oracle")
METRICS = ("agility", "safety", "crashes", "human_speed", "steps_per_s")


class KeepSpeed(TensorDictModuleBase):
    """Target speed = the CAV's own speed (observation column 0), no lane change."""

    in_keys = [("agents", "observation")]
    out_keys = [("agents", "action")]

    def __init__(self, env) -> None:
        super().__init__()
        self.action_dim = env.full_action_spec["agents", "action"].shape[-1]

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        speed = tensordict.get(("agents", "observation"))[..., :1]
        action = torch.cat([speed, torch.zeros_like(speed)], -1)[..., : self.action_dim]
        return tensordict.set(("agents", "action"), action)


def human_speeds(env) -> np.ndarray:
    """``[H]`` speeds of the human drivers on the road now, of either back end."""
    raw = env._env.env
    if hasattr(raw, "human_speeds"):
        return raw.human_speeds()
    cavs = {id(cav) for cav in raw.cavs}
    return np.array([v.speed for v in raw.road.vehicles if id(v) not in cavs])


def episode(name: str, backend: str, policy_name: str, seed: int) -> dict[str, float]:
    """One episode's metrics (see the module docstring)."""
    env = make_env(name, backend=backend, seed=seed)
    if policy_name == "random":
        policy = RandomPolicy(env, keep_lane=False, seed=seed)
    elif policy_name == "keep-speed":
        policy = KeepSpeed(env)
    else:
        policy = oracle_planner(env, FigureEightPlannerReward(), seed)
    td = env.reset()
    stepping, steps, speeds = 0.0, 0, []
    while True:
        td = policy(td)
        start = time.perf_counter()
        td = env.step(td)
        stepping += time.perf_counter() - start
        steps += 1
        speeds.append(human_speeds(env))
        if td["next", "done"].item():
            break
        td = step_mdp(td)
    metrics = env.last_episode_metrics
    env.close()
    speeds = np.concatenate(speeds)
    return {
        "agility": metrics["agility"],
        "safety": metrics["safety"],
        "crashes": metrics["collisions"],
        "human_speed": float(speeds.mean()) if speeds.size else float("nan"),
        "steps_per_s": steps / stepping,
    }


DIGITS = {"agility": 2, "safety": 3, "crashes": 1, "human_speed": 2, "steps_per_s": 0}
"""Decimals of each metric in the table."""


def summary(values: list[float], digits: int) -> str:
    """``median [q1, q3]`` with ``digits`` decimals."""
    q1, median, q3 = np.percentile(values, [25, 50, 75])
    return f"{median:.{digits}f} [{q1:.{digits}f}, {q3:.{digits}f}]"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seeds", type=int, default=8)
    parser.add_argument("--policies", nargs="+", default=["random", "keep-speed"], choices=POLICIES)
    parser.add_argument("--envs", nargs="+", default=["figure-eight", "figure-eight-multilane"])
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args()
    torch.set_num_threads(1)
    print(f"# {machine_line()}")
    print(f"# torch.backends.cpu.get_cpu_capability() = {torch.backends.cpu.get_cpu_capability()}")
    print(f"# {args.seeds} episodes per row (seeds 0..{args.seeds - 1}); median [q1, q3]")
    print(
        "| scenario | policy | back end | agility (m/step) | safety | crashes/episode "
        "| humans' speed (m/s) | env steps/s |"
    )
    print("|---|---|---|---|---|---|---|---|")
    results = []
    for name in args.envs:
        for policy in args.policies:
            for backend in BACKENDS:
                rows = [episode(name, backend, policy, seed) for seed in range(args.seeds)]
                results.append(
                    {"env": name, "policy": policy, "backend": backend, "episodes": rows}
                )
                cells = " | ".join(summary([row[m] for row in rows], DIGITS[m]) for m in METRICS)
                print(f"| {name} | {policy} | {backend} | {cells} |", flush=True)
    if args.out is not None:
        args.out.write_text(json.dumps({"machine": machine_line(), "results": results}, indent=1))


if __name__ == "__main__":
    main()
