"""PettingZoo ``ParallelEnv`` views of the traffic scenarios.

Agents are named ``cav_0 .. cav_{I-1}``. A CAV that collides is terminated and removed from
``agents`` (PettingZoo convention). Per-agent ``infos`` hold ``position`` (``[2]``, metres),
``distance`` (travelled this step, m), ``speed`` (m/s) and ``collided`` (this step); the
figure-eight adds ``neighbour_changed`` (the observed neighbours changed identity) and
``neighbour_cav`` (``[K]``: which CAV each observed vehicle is, ``-1`` for others); the freeway
adds ``traffic_velocity`` and ``traffic_comfort`` (means over all vehicles this step).
Episode metrics (agility/safety or velocity/comfort) are in ``last_episode_metrics`` after an
episode ends.
"""

from __future__ import annotations

import functools
from types import MappingProxyType
from typing import Any

import numpy as np
from gymnasium import spaces
from pettingzoo import ParallelEnv

from mapets_rl.envs.figure_eight import FigureEightEnv
from mapets_rl.envs.freeway import FreewayEnv
from mapets_rl.envs.traffic import MultiAgentTrafficEnv, require


class TrafficParallelEnv(ParallelEnv):
    """Wraps a ``MultiAgentTrafficEnv`` as a PettingZoo ``ParallelEnv``."""

    metadata = {"render_modes": ["rgb_array"], "name": "traffic_v0", "is_parallelizable": True}
    env_class: type[MultiAgentTrafficEnv]
    """The raw highway-env environment class the subclass wraps."""

    def __init__(self, env: MultiAgentTrafficEnv, render_mode: str | None = None) -> None:
        self.env = env
        self.render_mode = render_mode
        n = env.config["n_cavs"]
        self.possible_agents = [f"cav_{i}" for i in range(n)]
        self.agents: list[str] = []
        self._index = {name: i for i, name in enumerate(self.possible_agents)}
        self.last_episode_metrics: dict[str, float] = {}
        self._observation_space = spaces.Box(
            -np.inf, np.inf, shape=(env.obs_dim,), dtype=np.float32
        )
        joint = env.action_space
        if isinstance(joint, spaces.MultiDiscrete):
            self._action_space: spaces.Space = spaces.Discrete(int(joint.nvec[0]))
            self._default_action = np.zeros(joint.shape, dtype=np.int64)
        else:
            self._action_space = spaces.Box(joint.low[0], joint.high[0], dtype=np.float32)
            self._default_action = np.array(joint.low, dtype=np.float32)

    @property
    def agent_index(self) -> MappingProxyType[str, int]:
        """Each agent's index in the joint arrays (the raw env's observation rows and joint
        action): ``joint[env.agent_index[agent]]`` is ``agent``'s entry. Read-only."""
        return MappingProxyType(self._index)

    @functools.cache  # noqa: B019 - spaces must be the same object each call
    def observation_space(self, agent: str) -> spaces.Box:
        return self._observation_space

    @functools.cache  # noqa: B019
    def action_space(self, agent: str) -> spaces.Space:
        return self._action_space

    def info_arrays(self, info: dict) -> dict[str, np.ndarray]:
        """Per-agent info of a raw-env ``info`` as arrays ``[I, ...]`` (see module docstring)."""
        n = len(self.possible_agents)
        arrays = {
            "position": np.asarray(info["positions"], dtype=np.float32),
            "distance": np.asarray(info["distance"], dtype=np.float32),
            "speed": np.asarray(info["speed"], dtype=np.float32),
            "collided": np.asarray(info.get("collided", np.zeros(n, dtype=bool)), dtype=bool),
        }
        if "neighbour_changed" in info:
            arrays["neighbour_changed"] = np.asarray(info["neighbour_changed"], dtype=bool)
        if "neighbour_cav" in info:
            arrays["neighbour_cav"] = np.asarray(info["neighbour_cav"], dtype=np.int64)
        if "traffic_velocity" in info:
            arrays["traffic_velocity"] = np.full(n, info["traffic_velocity"], dtype=np.float32)
            arrays["traffic_comfort"] = np.full(n, info["traffic_comfort"], dtype=np.float32)
        return arrays

    def _agent_infos(self, info: dict, agents: list[str]) -> dict[str, dict[str, Any]]:
        arrays = self.info_arrays(info)
        return {
            agent: {
                key: (
                    value[self._index[agent]]
                    if value.ndim > 1
                    else value[self._index[agent]].item()
                )
                for key, value in arrays.items()
            }
            for agent in agents
        }

    def reset_joint(
        self, seed: int | None = None, options: dict | None = None
    ) -> tuple[np.ndarray, dict]:
        """Reset; the array form of ``reset``: ``obs [I, obs]`` and the raw env's ``info``."""
        obs, info = self.env.reset(seed=seed, options=options)
        self.agents = list(self.possible_agents)
        return obs, info

    def reset(
        self, seed: int | None = None, options: dict | None = None
    ) -> tuple[dict[str, np.ndarray], dict[str, dict]]:
        obs, info = self.reset_joint(seed=seed, options=options)
        return {a: obs[self._index[a]] for a in self.agents}, self._agent_infos(info, self.agents)

    def joint_action(self, actions: dict[str, Any]) -> np.ndarray:
        """The raw env's joint action from a per-agent dict.

        Agents absent from ``actions`` get the lowest action; actions of agents that are no
        longer acting are ignored (torchrl's wrapper sends the whole group's actions).
        """
        unknown = set(actions) - set(self.possible_agents)
        require(not unknown, f"actions given for unknown agents: {sorted(unknown)}")
        joint = self._default_action.copy()
        acting = set(self.agents)
        for agent, action in actions.items():
            if agent not in acting:
                continue
            value = np.asarray(action)
            if isinstance(self._action_space, spaces.Discrete):
                require(
                    value.size == 1,
                    f"action of {agent} must be one integer in [0, {self._action_space.n - 1}]",
                )
                joint[self._index[agent]] = int(value.reshape(()))
            else:
                require(
                    value.shape == self._action_space.shape,
                    f"action of {agent} must have shape {self._action_space.shape}, "
                    f"got {value.shape}",
                )
                joint[self._index[agent]] = value
        return joint

    def step_joint(
        self, joint: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, dict]:
        """Step with a joint action ``[I, ...]``; the array form of ``step``.

        Returns:
            ``obs [I, obs]``, ``rewards [I]``, ``terminated [I]``, ``truncated [I]``,
            ``acting [I]`` (agents that acted in this step) and the raw env's ``info``.
            Entries of agents that did not act are zero (terminated/truncated: True).
        """
        acting = np.array([a in self.agents for a in self.possible_agents], dtype=bool)
        obs, _, _, truncated, info = self.env.step(joint)
        terminated = np.asarray(info["agent_terminated"], dtype=bool)
        truncated_agents = np.where(acting, bool(truncated) & ~terminated, True)
        self.agents = [
            a
            for a in self.agents
            if not (terminated[self._index[a]] or truncated_agents[self._index[a]])
        ]
        if "episode" in info:
            self.last_episode_metrics = info["episode"]
        rewards = np.asarray(info["agent_rewards"], dtype=np.float32) * acting
        return obs, rewards, terminated, truncated_agents, acting, info

    def step(self, actions: dict[str, Any]) -> tuple[dict, dict, dict, dict, dict]:
        acting = list(self.agents)
        obs, rewards, terminated, truncated, _, info = self.step_joint(self.joint_action(actions))
        index = self._index
        return (
            {a: obs[index[a]] for a in acting},
            {a: float(rewards[index[a]]) for a in acting},
            {a: bool(terminated[index[a]]) for a in acting},
            {a: bool(truncated[index[a]]) for a in acting},
            self._agent_infos(info, acting),
        )

    def render(self) -> np.ndarray | None:
        return self.env.render()

    def close(self) -> None:
        self.env.close()


class FigureEightParallelEnv(TrafficParallelEnv):
    """Figure-eight scenario as a PettingZoo ``ParallelEnv``.

    Args:
        n_cavs: number of CAVs (agents), >= 1 (paper: 8 single-lane, 22 two-lane).
        n_hvs: human-driven vehicles, an int or an inclusive range drawn per episode.
        lanes: 1 or 2.
        render_mode: ``None`` or ``"rgb_array"``.
        **config: further ``FigureEightEnv`` config keys (``horizon``, ``length``, ...);
            unknown keys raise ``ValueError`` listing the accepted ones.
    """

    metadata = {**TrafficParallelEnv.metadata, "name": "figure_eight_v0"}
    env_class = FigureEightEnv

    def __init__(
        self,
        n_cavs: int = 8,
        n_hvs: int | tuple[int, int] = (8, 20),
        lanes: int = 1,
        render_mode: str | None = None,
        **config: Any,
    ) -> None:
        env = self.env_class(
            {"n_cavs": n_cavs, "n_hvs": n_hvs, "lanes": lanes, **config}, render_mode=render_mode
        )
        super().__init__(env, render_mode)


class FreewayParallelEnv(TrafficParallelEnv):
    """Freeway scenario as a PettingZoo ``ParallelEnv``.

    Args:
        n_vehicles: vehicles in total, >= 1 (paper: 30).
        cav_ratio: fraction of CAVs in ``[0, 1]``; at least one CAV is needed for agents.
        render_mode: ``None`` or ``"rgb_array"``.
        **config: further ``FreewayEnv`` config keys.
    """

    metadata = {**TrafficParallelEnv.metadata, "name": "freeway_v0"}
    env_class = FreewayEnv

    def __init__(
        self,
        n_vehicles: int = 30,
        cav_ratio: float = 1.0,
        render_mode: str | None = None,
        **config: Any,
    ) -> None:
        env = self.env_class(
            {"n_vehicles": n_vehicles, "cav_ratio": cav_ratio, **config}, render_mode=render_mode
        )
        require(
            env.config["n_cavs"] >= 1,
            f"cav_ratio={cav_ratio} with n_vehicles={n_vehicles} gives no CAV; the multi-agent "
            "env needs cav_ratio * n_vehicles >= 0.5 (use FreewayEnv for all-human traffic)",
        )
        super().__init__(env, render_mode)
