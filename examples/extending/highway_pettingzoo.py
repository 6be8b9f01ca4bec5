"""A stock highway-env env as a PettingZoo ``ParallelEnv``, wrapped with ``wrap_pettingzoo`` and
trained by MA-PETS (with a planner reward written here) and by MAPPO.

The env: highway-env's ``highway-v0`` in its multi-agent configuration (``controlled_vehicles``
> 1, ``MultiAgentObservation`` of ``Kinematics``, ``MultiAgentAction`` of longitudinal
``ContinuousAction``): ``n_agents`` controlled vehicles among ``n_others`` IDM drivers on
``lanes`` lanes, one decision per second. Each controlled vehicle observes itself and its
``observed - 1`` nearest neighbours (``presence, x, y, vx, vy``, normalised to [-1, 1] by
highway-env; the neighbours relative to it) and sets its acceleration (``[-1, 1]`` ->
``[-5, 5]`` m/s^2).

highway-env has no PettingZoo API (its multi-agent envs return tuples, and ``highway-v0`` scores
and terminates the first controlled vehicle only), nor does PettingZoo adapt gymnasium
multi-agent envs, so :class:`HighwayParallelEnv` is the small adapter: agents ``vehicle_0 ..``,
per-agent flattened observations, per-agent rewards (highway-v0's speed term, ``collision_reward``
in a crash step) and terminations (a crashed vehicle leaves ``agents``), per-agent infos
(``speed``, m/s) and ``last_episode_metrics`` (``speed``: the controlled vehicles' mean speed,
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

import gymnasium
import highway_env  # noqa: F401 - registers highway-v0 with gymnasium
import numpy as np
import torch
from gymnasium import spaces
from pettingzoo import ParallelEnv
from torchrl.envs import EnvBase

from mapets_rl.envs import register_env, wrap_pettingzoo
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


# ----------------------------------------------------------------------- 1. the adapter
class HighwayParallelEnv(ParallelEnv):
    """highway-env's ``highway-v0`` with ``n_agents`` controlled vehicles as a PettingZoo
    ``ParallelEnv`` (see the module docstring).

    Args:
        n_agents: controlled vehicles (agents), >= 1.
        n_others: IDM-driven vehicles, >= 0.
        lanes: lanes, >= 1.
        duration: episode length [s] (= steps: one decision per second), >= 1.
        observed: vehicles each agent observes (itself included), >= 1.
        render_mode: ``None`` or ``"rgb_array"``.
    """

    metadata = {"render_modes": ["rgb_array"], "name": "highway_v0", "is_parallelizable": True}

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
        self.env = gymnasium.make("highway-v0", config=config, render_mode=render_mode).unwrapped
        self.render_mode = render_mode
        self.lanes = lanes
        self.possible_agents = [f"vehicle_{i}" for i in range(n_agents)]
        self.agents: list[str] = []
        self.last_episode_metrics: dict[str, float] = {}
        obs_space = self.env.observation_space[0]
        self.observation_spaces = {
            agent: spaces.Box(-1.0, 1.0, shape=(int(np.prod(obs_space.shape)),), dtype=np.float32)
            for agent in self.possible_agents
        }
        self.action_spaces = dict(zip(self.possible_agents, self.env.action_space, strict=True))

    def observation_space(self, agent: str) -> spaces.Box:
        return self.observation_spaces[agent]

    def action_space(self, agent: str) -> spaces.Box:
        return self.action_spaces[agent]

    @property
    def vehicles(self) -> list[Any]:
        """The controlled vehicles, in the order of ``possible_agents``."""
        return self.env.controlled_vehicles

    def _observations(
        self, obs: tuple[np.ndarray, ...], agents: list[str]
    ) -> dict[str, np.ndarray]:
        index = {agent: i for i, agent in enumerate(self.possible_agents)}
        return {agent: obs[index[agent]].reshape(-1).astype(np.float32) for agent in agents}

    def _infos(self, agents: list[str]) -> dict[str, dict[str, float]]:
        speeds = dict(zip(self.possible_agents, (v.speed for v in self.vehicles), strict=True))
        return {agent: {"speed": float(speeds[agent])} for agent in agents}

    def reset(
        self, seed: int | None = None, options: dict | None = None
    ) -> tuple[dict[str, np.ndarray], dict[str, dict[str, float]]]:
        obs, _ = self.env.reset(seed=seed, options=options)
        self.agents = list(self.possible_agents)
        self._speeds: list[float] = []
        return self._observations(obs, self.agents), self._infos(self.agents)

    def step(self, actions: dict[str, np.ndarray]) -> tuple[dict, dict, dict, dict, dict]:
        acting = list(self.agents)
        zero = np.zeros(self.action_spaces[self.possible_agents[0]].shape, dtype=np.float32)
        joint = tuple(np.asarray(actions.get(agent, zero)) for agent in self.possible_agents)
        obs, _, _, truncated, _ = self.env.step(joint)
        rewards, terminations, truncations = {}, {}, {}
        for agent, vehicle in zip(self.possible_agents, self.vehicles, strict=True):
            if agent not in acting:
                continue
            forward = vehicle.speed * np.cos(vehicle.heading)
            speed = np.clip((forward - SPEED_RANGE[0]) / (SPEED_RANGE[1] - SPEED_RANGE[0]), 0, 1)
            rewards[agent] = COLLISION_REWARD if vehicle.crashed else float(speed)
            terminations[agent] = bool(vehicle.crashed)
            truncations[agent] = bool(truncated) and not vehicle.crashed
            self._speeds.append(float(vehicle.speed))
        self.agents = [a for a in acting if not (terminations[a] or truncations[a])]
        if not self.agents:
            self.last_episode_metrics = {
                "speed": float(np.mean(self._speeds)),
                "collisions": float(sum(v.crashed for v in self.vehicles)),
            }
        observations, infos = self._observations(obs, acting), self._infos(acting)
        return observations, rewards, terminations, truncations, infos

    def render(self) -> np.ndarray | None:
        return self.env.render()

    def close(self) -> None:
        self.env.close()


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
