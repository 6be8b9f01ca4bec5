"""highway-env's multi-agent configurations as PettingZoo ``ParallelEnv`` classes, and four of them
registered as scenarios (``highway-intersection``, ``highway-roundabout``, ``highway-merge``,
``highway-multi``).

:class:`HighwayMultiAgentParallelEnv` turns any highway-env gymnasium id whose config has
``controlled_vehicles >= 1``, a ``MultiAgentObservation`` and a ``MultiAgentAction`` into a
``ParallelEnv``; :func:`~mapets_rl.envs.make_env` (through
:func:`~mapets_rl.envs.pettingzoo_wrapper.wrap_pettingzoo`) makes the registered ones the torchrl
env every recipe trains on. Agents ``cav_0 .. cav_{I-1}`` are highway-env's
``controlled_vehicles`` in order; each one's

- observation is its entry of the ``MultiAgentObservation`` tuple, flattened (``float32``);
- action is its entry of the ``MultiAgentAction``: an index of a ``DiscreteMetaAction`` /
  ``DiscreteAction`` (one-hot or an index in torchrl, ``categorical_actions``) or a
  ``ContinuousAction`` vector in ``[-1, 1]``; an agent that left ``agents`` drives on with its
  idle action (:func:`idle_action`: keep lane and speed);
- reward is ``info["agents_rewards"]`` where highway-env reports it (the intersection), else the
  env's own ``_reward`` computed with that vehicle as the ego (highway-env's single-agent envs
  score ``controlled_vehicles[0]`` only);
- termination is ``info["agents_terminated"]`` where highway-env reports it, else the env's
  ``_is_terminated`` with that vehicle as the ego (a crash, the merge's end of the ramp);
- the episode ends as highway-env defines it: where the env reports per-agent terminations its
  ``terminated`` flag ends the episode for every agent (the intersection: one crash, or every
  agent arrived), elsewhere each agent ends on its own termination; ``truncated`` (the env's
  ``duration``) ends every agent still driving;
- per-agent info: ``position`` (``[2]`` m, where the communication graph reads it: the
  wrapper moves it to ``("agents", "position")``), ``speed`` (m/s) and ``collided``.

``last_episode_metrics`` (after the step that ends an episode): ``speed`` (the agents' mean
speed over the episode, m/s) and ``collisions`` (agents that crashed).

MA-PETS plans with highway-env's longitudinal ``ContinuousAction`` (``lateral: false``, steering
0), so only where every agent's route is straight: ``highway-multi`` and ``highway-merge`` with
``ramp_agent: false`` (:data:`PLANNER_REWARDS`: highway-v0's and merge-v0's rewards on
predicted steps).

highway-env 1.12's ``merge-v0`` and ``roundabout-v0`` spawn one controlled vehicle whatever
``controlled_vehicles`` says; :class:`MultiAgentMergeEnv` and :class:`MultiAgentRoundaboutEnv`
build the same scene and hand its first ``controlled_vehicles`` vehicles to agents. highway-env's
intersection sets the jam distance and comfort accelerations of its ``other_vehicles_type``
*class* (``IDMVehicle.DISTANCE_WANTED = 7``); the scenario drives :class:`IntersectionIDMVehicle`
instead, so no other scenario of the process changes with it.
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import inspect
from collections.abc import Iterator, Mapping, Sequence
from typing import Any, ClassVar

import gymnasium
import highway_env  # noqa: F401 - registers highway-env's ids with gymnasium
import numpy as np
import torch
from gymnasium import spaces
from highway_env.envs.common.abstract import AbstractEnv
from highway_env.envs.common.action import (
    ActionType,
    ContinuousAction,
    DiscreteAction,
    DiscreteMetaAction,
)
from highway_env.envs.highway_env import HighwayEnv
from highway_env.envs.intersection_env import (
    ConnectedLaneMultiAgentIntersectionEnv,
    MultiAgentIntersectionEnv,
)
from highway_env.envs.merge_env import MergeEnv
from highway_env.envs.roundabout_env import RoundaboutEnv
from highway_env.road.lane import StraightLane
from highway_env.vehicle.behavior import IDMVehicle
from highway_env.vehicle.kinematics import Vehicle
from pettingzoo import ParallelEnv

from mapets_rl.envs.factory import make_env
from mapets_rl.envs.planner_reward import PlannerReward
from mapets_rl.envs.registry import register_builtin
from mapets_rl.envs.validation import check_seed

__all__ = [
    "HighwayMergePlannerReward",
    "HighwayMultiAgentParallelEnv",
    "HighwayPlannerReward",
    "IntersectionIDMVehicle",
    "MultiAgentMergeEnv",
    "MultiAgentRoundaboutEnv",
    "idle_action",
]


# ----------------------------------------------------------------- highway-env scenes
class IntersectionIDMVehicle(IDMVehicle):
    """highway-env's ``IDMVehicle`` under its own class: the intersection writes its jam
    distance (7 m) and comfort accelerations (6, -3 m/s^2) onto the class of its other vehicles,
    which would otherwise change every IDM driver of the process (the freeways' included)."""


def _hand_over(env: AbstractEnv, count: int, order: Sequence[int]) -> None:
    """Make ``env.road.vehicles[order[k]]`` (``k < count``) the controlled vehicles: each
    replaced, at its position, heading, speed, lane and route, by a vehicle of the action type's
    class. ValueError unless ``1 <= count <= len(order)``."""
    if not 1 <= count <= len(order):
        raise ValueError(
            f"controlled_vehicles must be in [1, {len(order)}] for {type(env).__name__} (the "
            f"vehicles of its scene), got {count}"
        )
    make = env.action_type.vehicle_class
    keeps_route = "route" in inspect.signature(make).parameters
    controlled = []
    for index in order[:count]:
        vehicle = env.road.vehicles[index]
        extra = (
            {"target_lane_index": vehicle.target_lane_index, "route": vehicle.route}
            if keeps_route
            else {}
        )
        agent = make(
            env.road, vehicle.position, heading=vehicle.heading, speed=vehicle.speed, **extra
        )
        env.road.vehicles[index] = agent
        controlled.append(agent)
    env.controlled_vehicles = controlled


class MultiAgentMergeEnv(MergeEnv):
    """highway-env's ``merge-v0`` scene with up to 5 controlled vehicles, in this order: the ego
    on the highway, the vehicle on the access ramp (it must merge before the ramp's end), then
    the three other highway vehicles. With ``ramp_agent: false`` the ramp vehicle stays
    highway-env's IDM/MOBIL driver and up to 4 controlled vehicles are the highway's (ego
    first): the agents then only follow their straight lanes, as merge-v0's ego does, and make
    room for the merging driver (merge-v0's ``merging_speed_reward`` charges every agent for the
    ramp vehicle's slowdown). ``duration`` [s] truncates an episode (``merge-v0`` has no time
    limit: a vehicle ends when it crashes or passes x = 370 m)."""

    HAND_OVER_ORDER = (0, 4, 1, 2, 3)
    """Indices in ``road.vehicles`` after ``MergeEnv._make_vehicles``: ego, ramp, highway."""
    HIGHWAY_ORDER = (0, 1, 2, 3)
    """The same indices without the ramp vehicle (``ramp_agent: false``)."""

    @classmethod
    def default_config(cls) -> dict:
        return {
            **super().default_config(),
            "controlled_vehicles": 2,
            "duration": 20,
            "ramp_agent": True,
        }

    def _make_vehicles(self) -> None:
        ramp_agent = self.config["ramp_agent"]
        if not isinstance(ramp_agent, bool):
            raise ValueError(f"ramp_agent must be true or false, got {ramp_agent!r}")
        super()._make_vehicles()
        order = self.HAND_OVER_ORDER if ramp_agent else self.HIGHWAY_ORDER
        _hand_over(self, self.config["controlled_vehicles"], order)

    def _is_truncated(self) -> bool:
        return self.time >= self.config["duration"]


class MultiAgentRoundaboutEnv(RoundaboutEnv):
    """highway-env's ``roundabout-v0`` scene with up to 5 controlled vehicles, in this order: the
    ego (south entry, to the north exit), the vehicle entering from the east, the vehicle
    already in the ring's outer lane, then the two in its inner lane; each keeps its route."""

    HAND_OVER_ORDER = (0, 4, 1, 2, 3)
    """Indices in ``road.vehicles`` after ``RoundaboutEnv._make_vehicles``."""

    @classmethod
    def default_config(cls) -> dict:
        return {**super().default_config(), "controlled_vehicles": 2}

    def _make_vehicles(self) -> None:
        super()._make_vehicles()
        _hand_over(self, self.config["controlled_vehicles"], self.HAND_OVER_ORDER)


# ------------------------------------------------------------------------- the adapter
def idle_action(action_type: ActionType) -> int | np.ndarray:
    """The action of ``action_type`` that keeps the vehicle's lane and speed: ``IDLE`` of a
    ``DiscreteMetaAction``, the zero action of a ``DiscreteAction`` (an odd
    ``actions_per_axis``) or of a ``ContinuousAction``. ValueError for another type."""
    if isinstance(action_type, DiscreteMetaAction):
        return action_type.actions_indexes["IDLE"]
    if isinstance(action_type, DiscreteAction):
        n = action_type.actions_per_axis
        if n % 2 == 0:
            raise ValueError(
                f"DiscreteAction needs an odd actions_per_axis (one of them the zero action), "
                f"got {n}"
            )
        return (n**action_type.size - 1) // 2
    if isinstance(action_type, ContinuousAction):
        return np.zeros(action_type.size, dtype=np.float32)
    raise ValueError(
        "each agent's action_config type must be DiscreteMetaAction, DiscreteAction or "
        f"ContinuousAction, got {type(action_type).__name__}"
    )


class HighwayMultiAgentParallelEnv(ParallelEnv):
    """A highway-env env with a multi-agent config as a PettingZoo ``ParallelEnv`` (see the
    module docstring for what each agent observes, does and is rewarded).

    Args:
        env_id: a highway-env gymnasium id (``"intersection-multi-agent-v2"``, ``"highway-v0"``,
            ...).
        config: the env's config on top of its defaults; with its defaults it must have
            ``controlled_vehicles`` >= 1, ``observation.type == "MultiAgentObservation"`` (a
            ``Box`` per agent) and ``action.type == "MultiAgentAction"``.
        render_mode: ``None`` or ``"rgb_array"``.

    Raises:
        ValueError: an unknown id, a config key the env does not have, a config that is not
            multi-agent, an env that spawns another
            number of controlled vehicles than ``controlled_vehicles``, or an action type other
            than ``DiscreteMetaAction``, ``DiscreteAction`` and ``ContinuousAction``.
    """

    metadata = {"render_modes": ["rgb_array"], "name": "highway_multi_agent_v0"}

    def __init__(
        self,
        env_id: str,
        config: Mapping[str, Any] | None = None,
        render_mode: str | None = None,
    ) -> None:
        if render_mode not in (None, "rgb_array"):
            raise ValueError(f"render_mode must be None or 'rgb_array', got {render_mode!r}")
        if not isinstance(env_id, str) or env_id not in gymnasium.registry:
            raise ValueError(f"env_id must be a registered gymnasium id, got {env_id!r}")
        entry = gymnasium.spec(env_id).entry_point
        env_class = gymnasium.envs.registration.load_env_creator(entry)
        if not (isinstance(env_class, type) and issubclass(env_class, AbstractEnv)):
            raise ValueError(f"env_id {env_id!r} is no highway-env env ({entry})")
        config = dict(config or {})
        accepted = sorted({*env_class.default_config(), "controlled_vehicles"})
        unknown = sorted(set(config) - set(accepted))
        if unknown:
            raise ValueError(
                f"unknown config key(s) {unknown} for {env_id}; accepted keys: {accepted}"
            )
        full = {**env_class.default_config(), **config}
        n = full.get("controlled_vehicles")
        if isinstance(n, bool) or not isinstance(n, int) or n < 1:
            raise ValueError(f"controlled_vehicles must be an integer >= 1, got {n!r}")
        for key, kind in (("observation", "MultiAgentObservation"), ("action", "MultiAgentAction")):
            given = full.get(key)
            if not isinstance(given, Mapping) or given.get("type") != kind:
                raise ValueError(
                    f"config[{key!r}] must be {{'type': {kind!r}, ...}} (one entry per "
                    f"controlled vehicle), got {given!r}"
                )
        self.env_id = env_id
        self.env: AbstractEnv = gymnasium.make(
            env_id, config=config, render_mode=render_mode
        ).unwrapped
        self.render_mode = render_mode
        spawned = len(self.env.controlled_vehicles)
        if spawned != n:
            raise ValueError(
                f"{env_id} spawned {spawned} controlled vehicle(s), controlled_vehicles asks for "
                f"{n} (highway-env's merge-v0 and roundabout-v0 spawn one: use "
                "mapets_rl's MultiAgentMergeEnv / MultiAgentRoundaboutEnv)"
            )
        self.possible_agents = [f"cav_{i}" for i in range(n)]
        self.agents: list[str] = []
        self._index = {agent: i for i, agent in enumerate(self.possible_agents)}
        self.observation_spaces = {}
        self.action_spaces: dict[str, spaces.Space] = {}
        for agent, obs_space, act_space in zip(
            self.possible_agents,
            self.env.observation_space,
            self.env.action_space,
            strict=True,
        ):
            if not isinstance(obs_space, spaces.Box):
                raise ValueError(
                    f"each agent's observation must be a Box (Kinematics, OccupancyGrid, ...), "
                    f"got {obs_space!r}"
                )
            self.observation_spaces[agent] = spaces.Box(
                obs_space.low.reshape(-1).astype(np.float32),
                obs_space.high.reshape(-1).astype(np.float32),
                dtype=np.float32,
            )
            if isinstance(act_space, spaces.Box):
                act_space = spaces.Box(
                    act_space.low.astype(np.float32),
                    act_space.high.astype(np.float32),
                    dtype=np.float32,
                )
            self.action_spaces[agent] = act_space
        self._idle = [idle_action(t) for t in self.env.action_type.agents_action_types]
        self._speeds: list[float] = []
        self.last_episode_metrics: dict[str, float] = {}

    def observation_space(self, agent: str) -> spaces.Box:
        return self.observation_spaces[agent]

    def action_space(self, agent: str) -> spaces.Space:
        return self.action_spaces[agent]

    @property
    def vehicles(self) -> list[Vehicle]:
        """The controlled vehicles, in the order of ``possible_agents``."""
        return self.env.controlled_vehicles

    def positions(self) -> np.ndarray:
        """``[I, 2]`` float32: every controlled vehicle's position [m]."""
        return np.array([v.position for v in self.vehicles], dtype=np.float32)

    def _observations(self, obs: tuple, agents: list[str]) -> dict[str, np.ndarray]:
        return {a: np.asarray(obs[self._index[a]], dtype=np.float32).reshape(-1) for a in agents}

    def _infos(self, agents: list[str]) -> dict[str, dict[str, Any]]:
        positions = self.positions()
        return {
            agent: {
                "position": positions[self._index[agent]],
                "speed": float(self.vehicles[self._index[agent]].speed),
                "collided": bool(self.vehicles[self._index[agent]].crashed),
            }
            for agent in agents
        }

    def reset(
        self, seed: int | None = None, options: dict | None = None
    ) -> tuple[dict[str, np.ndarray], dict[str, dict[str, Any]]]:
        obs, _ = self.env.reset(seed=check_seed(seed), options=options)
        self.agents = list(self.possible_agents)
        self._speeds = []
        return self._observations(obs, self.agents), self._infos(self.agents)

    def _joint_action(self, actions: Mapping[str, Any]) -> tuple:
        """highway-env's tuple of actions: the acting agents' from ``actions``, the idle action
        for the others. ValueError for an unknown agent or an action outside its space."""
        unknown = set(actions) - set(self.possible_agents)
        if unknown:
            raise ValueError(f"actions given for unknown agents {sorted(unknown)}")
        joint = list(self._idle)
        for agent in self.agents:
            if agent not in actions:
                continue
            space = self.action_spaces[agent]
            value = np.asarray(actions[agent])
            if isinstance(space, spaces.Discrete):
                if value.size != 1 or not 0 <= int(value.reshape(())) < space.n:
                    raise ValueError(
                        f"action of {agent} must be one integer in [0, {space.n - 1}], got "
                        f"{value.tolist()}"
                    )
                value = int(value.reshape(()))
            elif value.shape != space.shape:
                raise ValueError(
                    f"action of {agent} must have shape {space.shape}, got {value.shape}"
                )
            joint[self._index[agent]] = value
        return tuple(joint)

    @contextlib.contextmanager
    def _as_ego(self, index: int) -> Iterator[None]:
        """highway-env's single-agent reward and termination read ``controlled_vehicles[0]``:
        within this block, controlled vehicle ``index`` is that vehicle."""
        vehicles = self.env.controlled_vehicles
        self.env.controlled_vehicles = [vehicles[index], *vehicles[:index], *vehicles[index + 1 :]]
        try:
            yield
        finally:
            self.env.controlled_vehicles = vehicles

    def _agent_outcomes(self, joint: tuple, info: dict) -> tuple[np.ndarray, np.ndarray]:
        """``rewards [I]`` and ``terminated [I]`` as highway-env defines them (module
        docstring)."""
        n = len(self.possible_agents)
        rewards = info.get("agents_rewards")
        terminated = info.get("agents_terminated")
        if rewards is None or terminated is None:
            own = []
            for i in range(n):
                with self._as_ego(i):
                    own.append((self.env._reward(joint[i]), self.env._is_terminated()))
            rewards = [r for r, _ in own] if rewards is None else rewards
            terminated = [t for _, t in own] if terminated is None else terminated
        return np.asarray(rewards, dtype=np.float32), np.asarray(terminated, dtype=bool)

    def step(self, actions: Mapping[str, Any]) -> tuple[dict, dict, dict, dict, dict]:
        acting = list(self.agents)
        joint = self._joint_action(actions)
        obs, _, episode_terminated, truncated, info = self.env.step(joint)
        rewards, terminated = self._agent_outcomes(joint, info)
        if "agents_terminated" in info and episode_terminated:
            terminated[:] = True
        index = self._index
        self._speeds.extend(float(self.vehicles[index[a]].speed) for a in acting)
        terminations = {a: bool(terminated[index[a]]) for a in acting}
        truncations = {a: bool(truncated) and not terminations[a] for a in acting}
        self.agents = [a for a in acting if not (terminations[a] or truncations[a])]
        if not self.agents:
            self.last_episode_metrics = {
                "speed": float(np.mean(self._speeds)),
                "collisions": float(sum(v.crashed for v in self.vehicles)),
            }
        return (
            self._observations(obs, acting),
            {a: float(rewards[index[a]]) for a in acting},
            terminations,
            truncations,
            self._infos(acting),
        )

    def render(self) -> np.ndarray | None:
        return self.env.render()

    def close(self) -> None:
        self.env.close()


# ------------------------------------------------------------------------ the scenarios
class HighwayScenarioParallelEnv(HighwayMultiAgentParallelEnv):
    """A registered highway-env multi-agent scenario: :attr:`env_id` with ``config`` (the
    highway-env config keys, flat: ``controlled_vehicles=3``, ``duration=10``, ...)."""

    env_id: ClassVar[str]
    env_class: ClassVar[type[AbstractEnv]]
    """highway-env's env class behind :attr:`env_id` (its ``default_config`` gives the keys)."""

    def __init__(self, render_mode: str | None = None, **config: Any) -> None:
        super().__init__(type(self).env_id, config, render_mode)


def _multi_agent(observation: dict[str, Any], action: dict[str, Any]) -> dict[str, Any]:
    """The ``observation`` / ``action`` config of one agent, for every controlled vehicle."""
    return {
        "observation": {"type": "MultiAgentObservation", "observation_config": observation},
        "action": {"type": "MultiAgentAction", "action_config": action},
    }


LONGITUDINAL_META = {
    "type": "DiscreteMetaAction",
    "longitudinal": True,
    "lateral": False,
}
"""SLOWER / IDLE / FASTER: the vehicle follows its lane and route."""
META = {"type": "DiscreteMetaAction"}
"""LANE_LEFT / IDLE / LANE_RIGHT / FASTER / SLOWER."""
KINEMATICS_FEATURES = ("presence", "x", "y", "vx", "vy")
"""Features of each observed vehicle (row 0: the observer) on the highway and the merge."""
KINEMATICS_RANGE = {
    "x": (-100.0, 100.0),
    "y": (-12.0, 12.0),
    "vx": (-40.0, 40.0),
    "vy": (-40.0, 40.0),
}
"""Normalisation of the highway's and the merge's observations (to ``[-1, 1]``, clipped): fixed,
so that the planner reward reads metres and m/s whatever the number of lanes."""
LANE_WIDTH = float(StraightLane.DEFAULT_WIDTH)
"""highway-env's lane width [m] on the highway and the merge (4 m)."""


def _kinematics(vehicles: int) -> dict[str, Any]:
    """A normalised ``Kinematics`` observation of the observer and its ``vehicles - 1`` nearest
    neighbours (relative to it; the observer absolute)."""
    return {
        "type": "Kinematics",
        "vehicles_count": vehicles,
        "features": list(KINEMATICS_FEATURES),
        "features_range": {k: list(v) for k, v in KINEMATICS_RANGE.items()},
        "absolute": False,
        "normalize": True,
        "see_behind": True,
    }


class HighwayIntersectionParallelEnv(HighwayScenarioParallelEnv):
    """``highway-intersection``: highway-env's ``intersection-multi-agent-v2``."""

    env_id = "intersection-multi-agent-v2"
    env_class = ConnectedLaneMultiAgentIntersectionEnv


class HighwayRoundaboutParallelEnv(HighwayScenarioParallelEnv):
    """``highway-roundabout``: :class:`MultiAgentRoundaboutEnv`."""

    env_id = "mapets_rl/MultiAgentRoundabout-v0"
    env_class = MultiAgentRoundaboutEnv


class HighwayMergeParallelEnv(HighwayScenarioParallelEnv):
    """``highway-merge``: :class:`MultiAgentMergeEnv`."""

    env_id = "mapets_rl/MultiAgentMerge-v0"
    env_class = MultiAgentMergeEnv


class HighwayMultiParallelEnv(HighwayScenarioParallelEnv):
    """``highway-multi``: highway-env's ``highway-v0``."""

    env_id = "highway-v0"
    env_class = HighwayEnv


# --------------------------------------------------------------- the planner reward
@dataclasses.dataclass(frozen=True)
class HighwayPlannerReward(PlannerReward):
    """highway-v0's per-vehicle reward on a predicted step of ``highway-multi`` (its
    observation: :data:`KINEMATICS_FEATURES` of ``vehicles_count`` vehicles, normalised by
    :data:`KINEMATICS_RANGE`): ``lmap(collision_reward * crash + high_speed_reward * s,
    [collision_reward, high_speed_reward], [0, 1])`` with ``s`` the observer's forward speed
    mapped from ``[speed_low, speed_high]`` onto ``[0, 1]`` (clipped) and ``crash`` an observed
    vehicle within ``gap_x`` along and ``gap_y`` across the road (a car is 5 x 2 m). The
    scenario sets ``right_lane_reward = 0``, so this is highway-env's reward; keep the weights
    equal to ``env_config``'s if you change them there.

    Attributes:
        collision_reward: highway-v0's ``collision_reward`` (< ``high_speed_reward``).
        high_speed_reward: highway-v0's ``high_speed_reward``.
        speed_low: ``reward_speed_range[0]`` [m/s].
        speed_high: ``reward_speed_range[1]`` [m/s], above ``speed_low``.
        gap_x: longitudinal distance [m] under which a neighbour counts as a crash, > 0.
        gap_y: lateral distance [m] under which a neighbour counts as a crash, > 0.
    """

    collision_reward: float = -1.0
    high_speed_reward: float = 0.4
    speed_low: float = 20.0
    speed_high: float = 30.0
    gap_x: float = 6.0
    gap_y: float = 2.5

    def __post_init__(self) -> None:
        super().__post_init__()
        if not self.collision_reward < self.high_speed_reward:
            raise ValueError(
                f"collision_reward must be below high_speed_reward ({self.high_speed_reward}), "
                f"got {self.collision_reward}"
            )
        if not self.speed_low < self.speed_high:
            raise ValueError(
                f"speed_high must be above speed_low ({self.speed_low}), got {self.speed_high}"
            )
        for name in ("gap_x", "gap_y"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be > 0, got {getattr(self, name)}")

    def crash(
        self, obs: torch.Tensor, action: torch.Tensor, next_obs: torch.Tensor
    ) -> torch.Tensor:
        """``[...]`` bool: a neighbour of ``next_obs [..., V * 5]`` within the gaps (``obs`` and
        ``action`` unused)."""
        rows = next_obs.unflatten(-1, (-1, len(KINEMATICS_FEATURES)))[..., 1:, :]
        dx = rows[..., 1] * KINEMATICS_RANGE["x"][1]
        dy = rows[..., 2] * KINEMATICS_RANGE["y"][1]
        close = (rows[..., 0] > 0.5) & (dx.abs() <= self.gap_x) & (dy.abs() <= self.gap_y)
        return close.any(-1)

    def reward(
        self, obs: torch.Tensor, action: torch.Tensor, next_obs: torch.Tensor
    ) -> torch.Tensor:
        speed = next_obs[..., 3] * KINEMATICS_RANGE["vx"][1]  # the observer's vx [m/s]
        scaled = ((speed - self.speed_low) / (self.speed_high - self.speed_low)).clamp(0.0, 1.0)
        crash = self.crash(obs, action, next_obs).to(scaled.dtype)
        raw = self.collision_reward * crash + self.high_speed_reward * scaled * (1 - crash)
        low, high = self.collision_reward, self.high_speed_reward
        return (raw - low) / (high - low)

    @property
    def termination_fn(self):  # noqa: ANN201 - the base class's type
        return self.crash


MERGE_LANE_Y = 8.0
"""Lateral position [m] of merge-v0's merging lane ``("b", "c", 2)`` (the highway's lanes at 0
and 4 m, lanes 4 m wide)."""


@dataclasses.dataclass(frozen=True)
class HighwayMergePlannerReward(HighwayPlannerReward):
    """merge-v0's per-vehicle reward on a predicted step of ``highway-merge`` with highway
    agents (``ramp_agent: false``) and continuous longitudinal actions (the observation as
    :class:`HighwayPlannerReward`'s, without obstacles): ``lmap(collision_reward * crash +
    right_lane_reward * lane + high_speed_reward * s + merging_speed_reward * m,
    [collision_reward + merging_speed_reward, high_speed_reward + right_lane_reward], [0, 1])``
    with ``lane`` the observer's lane index (its ``y`` over the 4 m lane width), ``s`` its
    forward speed mapped from ``[speed_low, speed_high]`` onto ``[0, 1]`` (not clipped, as
    merge-v0) and ``m`` the merging vehicles' slowdown, ``sum (ramp_target_speed - speed) /
    ramp_target_speed`` over the observed vehicles within 2 m of the merging lane. merge-v0's
    ``lane_change_reward`` (``action in [0, 2]``: for a continuous action, an acceleration of
    exactly 0 or 2) is left out, so set it to 0 in ``env_config``; merge-v0 sums the slowdown
    of every vehicle on the merging lane, observed or not, so the two differ when the merging
    vehicle is out of view.

    Attributes:
        collision_reward, high_speed_reward, speed_low, speed_high, gap_x, gap_y: as
            :class:`HighwayPlannerReward`, at merge-v0's values.
        right_lane_reward: merge-v0's ``right_lane_reward``, per lane index.
        merging_speed_reward: merge-v0's ``merging_speed_reward`` (<= 0).
        ramp_target_speed: the merging vehicle's target speed [m/s] (merge-v0 sets 30), > 0.
    """

    high_speed_reward: float = 0.2
    right_lane_reward: float = 0.1
    merging_speed_reward: float = -0.5
    ramp_target_speed: float = 30.0

    def __post_init__(self) -> None:
        super().__post_init__()
        if not self.merging_speed_reward <= 0:
            raise ValueError(f"merging_speed_reward must be <= 0, got {self.merging_speed_reward}")
        if not self.ramp_target_speed > 0:
            raise ValueError(f"ramp_target_speed must be > 0, got {self.ramp_target_speed}")

    def reward(
        self, obs: torch.Tensor, action: torch.Tensor, next_obs: torch.Tensor
    ) -> torch.Tensor:
        rows = next_obs.unflatten(-1, (-1, len(KINEMATICS_FEATURES)))  # [..., V, 5]
        scale = next_obs.new_tensor(
            [1.0, *(KINEMATICS_RANGE[k][1] for k in ("x", "y", "vx", "vy"))]
        )
        rows = rows * scale  # metres and m/s; row 0 absolute, the others relative to it
        own, others = rows[..., 0, :], rows[..., 1:, :]
        lane = (own[..., 2] / LANE_WIDTH).round().clamp(min=0.0)
        scaled = (own[..., 3] - self.speed_low) / (self.speed_high - self.speed_low)
        y = own[..., 2:3] + others[..., 2]  # [..., V - 1] the neighbours' y [m]
        speed = torch.hypot(own[..., 3:4] + others[..., 3], own[..., 4:5] + others[..., 4])
        merging = (others[..., 0] > 0.5) & ((y - MERGE_LANE_Y).abs() < LANE_WIDTH / 2)
        slowdown = ((self.ramp_target_speed - speed) / self.ramp_target_speed * merging).sum(-1)
        crash = self.crash(obs, action, next_obs).to(scaled.dtype)
        raw = (
            self.collision_reward * crash
            + self.right_lane_reward * lane
            + self.high_speed_reward * scaled
            + self.merging_speed_reward * slowdown
        )
        low = self.collision_reward + self.merging_speed_reward
        high = self.high_speed_reward + self.right_lane_reward
        return (raw - low) / (high - low)


# ------------------------------------------------------------------------ registration
SCENARIOS: dict[str, tuple[type[HighwayScenarioParallelEnv], str, dict[str, Any]]] = {
    "highway-intersection": (
        HighwayIntersectionParallelEnv,
        "mapets_rl/HighwayIntersection-v0",
        {
            "controlled_vehicles": 2,
            "initial_vehicle_count": 5,
            "spawn_probability": 0.3,
            "other_vehicles_type": f"{__name__}.IntersectionIDMVehicle",
            **_multi_agent(
                {
                    **MultiAgentIntersectionEnv.default_config()["observation"][
                        "observation_config"
                    ],
                    "vehicles_count": 5,
                },
                {**LONGITUDINAL_META, "target_speeds": [0, 4.5, 9]},
            ),
        },
    ),
    "highway-roundabout": (
        HighwayRoundaboutParallelEnv,
        "mapets_rl/HighwayRoundabout-v0",
        {
            "controlled_vehicles": 2,
            "simulation_frequency": 5,
            **_multi_agent(
                {**RoundaboutEnv.default_config()["observation"], "vehicles_count": 5},
                {**META, "target_speeds": [0, 8, 16]},
            ),
        },
    ),
    "highway-merge": (
        HighwayMergeParallelEnv,
        "mapets_rl/HighwayMerge-v0",
        {"controlled_vehicles": 2, "simulation_frequency": 5, **_multi_agent(_kinematics(4), META)},
    ),
    "highway-multi": (
        HighwayMultiParallelEnv,
        "mapets_rl/HighwayMulti-v0",
        {
            "controlled_vehicles": 3,
            "vehicles_count": 6,
            "lanes_count": 3,
            "duration": 10,
            "simulation_frequency": 5,
            "right_lane_reward": 0.0,
            **_multi_agent(_kinematics(4), META),
        },
    ),
}
"""Scenario name -> its ``ParallelEnv`` class, its gymnasium id (the raw highway-env env with
the scenario's config; ``mapets_rl.envs.GYM_IDS``) and what it changes from the env's
defaults."""

PLANNER_REWARDS: dict[str, type[HighwayPlannerReward]] = {
    "highway-multi": HighwayPlannerReward,
    "highway-merge": HighwayMergePlannerReward,
}
"""The scenarios MA-PETS plans on (straight lanes, continuous longitudinal actions) and their
planner rewards."""

# the generalised scenes at highway-env's defaults (the scenarios' ids, with their changes, are
# registered by mapets_rl.envs with the other built-in scenarios')
for _id, _cls in (
    (HighwayRoundaboutParallelEnv.env_id, MultiAgentRoundaboutEnv),
    (HighwayMergeParallelEnv.env_id, MultiAgentMergeEnv),
):
    if _id not in gymnasium.registry:
        gymnasium.register(_id, entry_point=f"{__name__}:{_cls.__name__}")

for _name, (_cls, _gym_id, _changes) in SCENARIOS.items():
    register_builtin(
        _name,
        functools.partial(make_env, _name),
        _cls,
        _gym_id,
        _changes,
        PLANNER_REWARDS.get(_name),
    )
