"""A stock highway-env env as a PettingZoo ``ParallelEnv``, wrapped with ``wrap_pettingzoo`` and
trained by MA-PETS (with a planner reward written here) and by MAPPO.

The env: highway-env's ``highway-v0`` in its multi-agent configuration (``controlled_vehicles``
> 1, ``MultiAgentObservation`` of ``Kinematics``, ``MultiAgentAction`` of longitudinal
``ContinuousAction``): ``n_agents`` controlled vehicles among ``n_others`` IDM drivers on
``lanes`` lanes, one decision per second. Each controlled vehicle observes itself and its
``observed - 1`` nearest neighbours (``presence, x, y, vx, vy``, normalised to [-1, 1] by
highway-env; the neighbours relative to it) and sets its acceleration (``[-1, 1]`` ->
``[-5, 5]`` m/s^2).

The library turns highway-env's multi-agent configurations into ``ParallelEnv`` classes
(:class:`~mapets_rl.envs.HighwayMultiAgentParallelEnv`; four of them are registered scenarios,
``highway-multi`` among them, with highway-v0's own reward). This study wants another reward and
its own settings under a name nobody registered, so :class:`HighwayParallelEnv` subclasses the
adapter and rescores its ``step``: each vehicle's forward speed term of highway-v0 (no lane
term, no normalisation), ``COLLISION_REWARD`` in a crash step. Agents are ``cav_0 ..``; the
adapter gives the per-agent terminations (a crashed vehicle leaves ``agents``), infos
(``position``, ``speed``, ``collided``) and ``last_episode_metrics`` (``speed``,
``collisions``), the conventions of :mod:`mapets_rl.envs.pettingzoo_wrapper`.

The two lines that make it the torchrl env of every recipe (positions from a callable of the
``ParallelEnv``: highway-env's vehicles know where they are)::

    parallel_env = HighwayParallelEnv(n_agents=3)
    env = wrap_pettingzoo(parallel_env, position=vehicle_positions)

:func:`highway_reward` / :func:`highway_collision` are the known reward and crash test MA-PETS
plans with (vectorised functions of the normalised ``(obs, action, next_obs)``).

Run it (about 20 s of CPU time; MA-PETS' speed rose from 23 m/s in the random first episode to
37 m/s in the third, with one crash, at the defaults and seed 0):

    python examples/extending/highway_pettingzoo.py [--episodes 3] [--frames 40] [--duration 10]
"""

from __future__ import annotations

import argparse
import tempfile
from typing import Any

import numpy as np
import torch
from torchrl.envs import EnvBase

from mapets_rl.envs import HighwayMultiAgentParallelEnv, register_env, wrap_pettingzoo
from mapets_rl.recipes.mapets import MAPETS, MAPETSConfig
from mapets_rl.recipes.mappo import MAPPO, MAPPOConfig

FEATURES = ("presence", "x", "y", "vx", "vy")
"""Kinematics features of each observed vehicle (row 0: the observer)."""
MAX_SPEED = 40.0
"""highway-env's ``Vehicle.MAX_SPEED`` [m/s]: Kinematics normalises x by 5x, vx by 2x it."""
LANE_WIDTH = 4.0
"""highway-env's ``AbstractLane.DEFAULT_WIDTH`` [m]: Kinematics normalises y by ``lanes`` x it."""
SPEED_RANGE = (20.0, 30.0)
"""highway-v0's ``reward_speed_range`` [m/s]: the speed reward rises from 0 to 1 across it."""
COLLISION_REWARD = -1.0
"""highway-v0's ``collision_reward``."""


# ------------------------------------------------------------- 1. the ParallelEnv
class HighwayParallelEnv(HighwayMultiAgentParallelEnv):
    """highway-env's ``highway-v0`` with ``n_agents`` controlled vehicles as a PettingZoo
    ``ParallelEnv`` with this study's own reward (see the module docstring): the library's
    adapter, whose ``step`` this subclass rescores.

    Args:
        n_agents: controlled vehicles (agents), >= 1.
        n_others: IDM-driven vehicles, >= 0.
        lanes: lanes, >= 1.
        duration: episode length [s] (= steps: one decision per second), >= 1.
        observed: vehicles each agent observes (itself included), >= 1.
        render_mode: ``None`` or ``"rgb_array"``.
    """

    def __init__(
        self,
        n_agents: int = 3,
        n_others: int = 6,
        lanes: int = 3,
        duration: int = 10,
        observed: int = 3,
        render_mode: str | None = None,
    ) -> None:
        for name, value, low in (
            ("n_agents", n_agents, 1),
            ("n_others", n_others, 0),
            ("lanes", lanes, 1),
            ("duration", duration, 1),
            ("observed", observed, 1),
        ):
            if isinstance(value, bool) or not isinstance(value, int) or value < low:
                raise ValueError(f"{name} must be an integer >= {low}, got {value!r}")
        config = {
            "controlled_vehicles": n_agents,
            "vehicles_count": n_others,
            "lanes_count": lanes,
            "duration": duration,
            "simulation_frequency": 5,
            "policy_frequency": 1,
            "observation": {
                "type": "MultiAgentObservation",
                "observation_config": {
                    "type": "Kinematics",
                    "vehicles_count": observed,
                    "see_behind": True,
                    "features": list(FEATURES),
                },
            },
            "action": {
                "type": "MultiAgentAction",
                "action_config": {"type": "ContinuousAction", "lateral": False},
            },
        }
        super().__init__("highway-v0", config, render_mode)
        self.lanes = lanes

    def step(self, actions: dict[str, np.ndarray]) -> tuple[dict, dict, dict, dict, dict]:
        """The adapter's step, each acting vehicle rescored: ``COLLISION_REWARD`` in a crash
        step, else its forward speed mapped from ``SPEED_RANGE`` onto [0, 1]."""
        observations, rewards, terminations, truncations, infos = super().step(actions)
        for agent in rewards:
            vehicle = self.vehicles[self.possible_agents.index(agent)]
            forward = vehicle.speed * np.cos(vehicle.heading)
            speed = np.clip((forward - SPEED_RANGE[0]) / (SPEED_RANGE[1] - SPEED_RANGE[0]), 0, 1)
            rewards[agent] = COLLISION_REWARD if vehicle.crashed else float(speed)
        return observations, rewards, terminations, truncations, infos


def vehicle_positions(parallel_env: HighwayParallelEnv) -> np.ndarray:
    """``[I, 2]`` positions [m] of the controlled vehicles: the ``position`` of
    ``wrap_pettingzoo``."""
    return np.array([vehicle.position for vehicle in parallel_env.vehicles], dtype=np.float32)


def make_highway(**config: Any) -> EnvBase:
    """The scenario factory: ``factory(**env_config)`` -> the torchrl env every recipe uses."""
    return wrap_pettingzoo(HighwayParallelEnv(**config), position=vehicle_positions)


# ------------------------------------------------------------------ 2. the planner reward
def highway_collision(
    obs: torch.Tensor, action: torch.Tensor, next_obs: torch.Tensor, lanes: int = 3
) -> torch.Tensor:
    """Predicted crash: an observed vehicle within 6 m along and 2.5 m across the road (a car's
    5 x 2 m and a margin: highway-env stops crashed cars where they touched). ``[...]`` bool.

    Args:
        obs, action: unused (the test reads the predicted outcome).
        next_obs: ``[..., observed * 5]`` predicted observation (rows of ``FEATURES``).
        lanes: lanes of the road (highway-env normalises ``y`` by ``lanes`` lane widths).
    """
    rows = next_obs.unflatten(-1, (-1, len(FEATURES)))[..., 1:, :]  # the neighbours
    dx = rows[..., 1] * 5.0 * MAX_SPEED
    dy = rows[..., 2] * LANE_WIDTH * lanes
    close = (rows[..., 0] > 0.5) & (dx.abs() <= 6.0) & (dy.abs() <= 2.5)
    return close.any(-1)


def highway_reward(
    obs: torch.Tensor, action: torch.Tensor, next_obs: torch.Tensor, lanes: int = 3
) -> torch.Tensor:
    """highway-v0's per-vehicle reward on a predicted step: the speed term in [0, 1],
    ``COLLISION_REWARD`` on a predicted crash. ``[...]``; arguments as :func:`highway_collision`.
    """
    speed = next_obs[..., 3] * 2.0 * MAX_SPEED  # the observer's vx [m/s]
    reward = ((speed - SPEED_RANGE[0]) / (SPEED_RANGE[1] - SPEED_RANGE[0])).clamp(0.0, 1.0)
    crash = highway_collision(obs, action, next_obs, lanes)
    return torch.where(crash, torch.full_like(reward, COLLISION_REWARD), reward)


# ------------------------------------------------------------------------------ 3. train
def train_mapets(episodes: int, env_config: dict[str, Any], run_dir: str) -> list[dict]:
    """MA-PETS (cpu preset, a small uncompiled planner, data shared within 200 m) with
    :func:`highway_reward` / :func:`highway_collision`; its per-episode entries."""
    observed = env_config.get("observed", 3) * len(FEATURES)
    config = MAPETSConfig(
        env="highway",
        env_config=env_config,
        episodes=episodes,
        preset="cpu",
        planner={"horizon": 5, "population": 16, "elites": 4, "iterations": 2, "compile": False},
        model={"epochs": 5, "hidden": [32, 32]},
        tile_coding={"obs_low": [-1.0] * observed, "obs_high": [1.0] * observed},
        comm={"comm_range": 200.0},
        logger="none",
        progress=False,
        seed=0,
    )
    return MAPETS(
        config, run_dir, reward_fn=highway_reward, termination_fn=highway_collision
    ).train()


def train_mappo(frames: int, env_config: dict[str, Any], run_dir: str) -> list[dict]:
    """MAPPO for ``frames`` frames in batches of 20, evaluated after each; its evaluations."""
    config = MAPPOConfig(
        env="highway",
        env_config=env_config,
        total_frames=frames,
        frames_per_batch=20,
        minibatch_size=20,
        eval_interval=20,
        logger="none",
        progress=False,
        seed=0,
    )
    return MAPPO(config, run_dir).train()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--episodes", type=int, default=3, help="MA-PETS episodes (1 random)")
    parser.add_argument("--frames", type=int, default=40, help="MAPPO frames")
    parser.add_argument("--duration", type=int, default=10, help="steps per episode")
    args = parser.parse_args()
    register_env("highway", make_highway)
    env_config = {"duration": args.duration}
    with tempfile.TemporaryDirectory() as run_dir:
        for entry in train_mapets(args.episodes, env_config, f"{run_dir}/mapets"):
            m = entry["metrics"]
            print(
                f"mapets episode {int(m['episode'])}: return {m['return']:.3f} speed "
                f"{m['speed']:.2f} m/s collisions {int(m['collisions'])} "
                f"transitions_shared {int(m['transitions_shared'])}"
            )
        for entry in train_mappo(args.frames, env_config, f"{run_dir}/mappo"):
            m = entry["metrics"]
            print(
                f"mappo frames {entry['frames']}: return {m['return']:.3f} speed "
                f"{m['speed']:.2f} m/s collisions {int(m['collisions'])}"
            )


if __name__ == "__main__":
    main()
