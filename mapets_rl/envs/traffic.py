"""Common machinery of the multi-agent traffic scenarios (a highway-env ``AbstractEnv``).

Stock multi-agent highway-env returns one scalar reward and ends the episode on
``controlled_vehicles[0]``. ``MultiAgentTrafficEnv`` keeps per-CAV bookkeeping instead: each
CAV has its own observation row, reward, termination on collision and travelled distance.
Crashed vehicles (CAVs and human-driven alike) leave the road at the end of the step in which
they crashed; a crashed CAV stays in the arrays with a zero observation row and ``alive=False``.

The gymnasium interface is array-valued: observation ``[I, obs_dim]``, action ``[I, act_dim]``
(or ``[I]`` discrete), scalar reward = mean of the per-CAV rewards, and the per-CAV signals in
``info`` (``agent_rewards``, ``agent_terminated``, ``positions``, ``distance``, ``speed``,
``collided``, ``alive``). At the end of an episode ``info["episode"]`` holds the episode metrics.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from gymnasium import spaces
from highway_env.envs.common.abstract import AbstractEnv
from highway_env.envs.common.graphics import EnvViewer
from highway_env.envs.common.observation import ObservationType
from highway_env.vehicle.kinematics import Vehicle

from mapets_rl.envs.rendering import (
    CrashSites,
    decorate_frame,
    draw_step_counter,
    paint_vehicles,
)
from mapets_rl.envs.road import SortedNeighbourRoad
from mapets_rl.envs.validation import is_integer, require_number, require_rendering

MAX_SIMULATION_FREQUENCY = 1000
"""The highest ``simulation_frequency`` a scenario accepts [Hz]: 100 times the scenarios'
10 Hz, 1000 simulation steps per second of traffic (a policy step costs as many)."""


def require(condition: bool, message: str) -> None:
    """Raise ``ValueError(message)`` unless ``condition`` holds."""
    if not condition:
        raise ValueError(message)


class AgentObservation(ObservationType):
    """Adapter that lets highway-env's ``AbstractEnv`` ask the scenario for observations."""

    def __init__(self, env: MultiAgentTrafficEnv, obs_dim: int) -> None:
        super().__init__(env)
        self.obs_dim = obs_dim

    def space(self) -> spaces.Space:
        n = self.env.config["n_cavs"]
        return spaces.Box(-np.inf, np.inf, shape=(n, self.obs_dim), dtype=np.float32)

    def observe(self) -> np.ndarray:
        return self.env.observe_agents()


class _Origin:
    """A fixed point for the viewer to centre on (the scene, not the first CAV)."""

    def __init__(self, position: np.ndarray) -> None:
        self.position = position


SCENARIO_SET_KEYS = frozenset(
    {"action", "observation", "other_vehicles_type", "manual_control"}
    | {"neighbour_vehicles_connected_lanes"}
)
"""highway-env config keys our scenarios set themselves (their action and observation types,
their vehicle classes): accepted from a user they were silently ignored."""


class MultiAgentTrafficEnv(AbstractEnv):
    """Base class: per-CAV rewards, terminations, distances and episode bookkeeping.

    Subclasses implement ``validate_config``, ``_make_road``, ``_spawn_vehicles``,
    ``observe_agents``, ``agent_rewards``, ``define_spaces`` and ``episode_metrics``.
    """

    obs_dim: int
    min_cavs = 1
    view_centre = np.zeros(2)

    def __init__(self, config: dict | None = None, render_mode: str | None = None) -> None:
        config = self.resolved_config(config or {})
        self.cavs: list[Vehicle] = []
        self.alive = np.zeros(0, dtype=bool)
        super().__init__(config, render_mode)

    @classmethod
    def resolved_config(cls, config: dict) -> dict:
        """The full config the scenario runs with: its defaults, the user's ``config`` and what
        :meth:`derived_config` computes from them, validated (ValueError naming an unknown or
        invalid key). The torch backend of the freeways resolves its config here too."""
        accepted = cls.user_keys()
        unknown = sorted(set(config) - set(accepted))
        require(
            not unknown,
            f"unknown config key(s) {unknown} for {cls.__name__}; accepted keys: {accepted}",
        )
        merged = {**cls.default_config(), **config}
        merged.update(cls.derived_config(merged))
        cls.validate_config(merged)
        return merged

    @classmethod
    def user_keys(cls) -> list[str]:
        """The config keys a user may set: the scenario's own and highway-env's rendering and
        timing keys; not highway-env's action, observation and vehicle-class keys that the
        scenario sets itself (:data:`SCENARIO_SET_KEYS`, unless the scenario redefines one,
        as the figure-eight does ``observation``), nor what :meth:`derived_config` computes."""
        own = cls.default_config()
        stock = AbstractEnv.default_config()
        fixed = {k for k in SCENARIO_SET_KEYS if own.get(k) == stock.get(k)}
        derived = cls.derived_config(own)
        return sorted(set(own) - fixed - set(derived))

    @classmethod
    def derived_config(cls, config: dict) -> dict:
        """Keys the scenario computes from others of ``config`` (the full config); a user may
        not set them. None by default."""
        return {}

    @classmethod
    def default_config(cls) -> dict:
        config = super().default_config()
        config.update(
            {
                "n_cavs": 8,
                "horizon": 200,
                "simulation_frequency": 10,
                "policy_frequency": 10,
                "collision_reward": -10.0,
                "stock_neighbour_search": False,
                "offscreen_rendering": True,
            }
        )
        return config

    @classmethod
    def validate_config(cls, config: dict) -> None:
        """Raise ``ValueError`` naming the first invalid key of ``config``."""
        require(
            is_integer(config["n_cavs"]) and config["n_cavs"] >= cls.min_cavs,
            f"n_cavs must be an integer >= {cls.min_cavs}, got {config['n_cavs']!r}",
        )
        require(
            is_integer(config["horizon"]) and config["horizon"] >= 1,
            f"horizon must be an integer >= 1, got {config['horizon']!r}",
        )
        require_number(config, "collision_reward")
        policy, sim = config["policy_frequency"], config["simulation_frequency"]
        require(
            is_integer(policy) and policy >= 1,
            f"policy_frequency must be an integer >= 1 [Hz], got {policy!r}",
        )
        require(
            is_integer(sim) and policy <= sim <= MAX_SIMULATION_FREQUENCY and sim % policy == 0,
            f"simulation_frequency must be a multiple of policy_frequency={policy} in [{policy}, "
            f"{MAX_SIMULATION_FREQUENCY}] [Hz] (otherwise simulated time is silently lost), "
            f"got {sim!r}",
        )
        require_rendering(config)

    # --- scene -------------------------------------------------------------------------------
    def _reset(self) -> None:
        self.road = self._make_road()
        self.cavs = self._spawn_vehicles()
        self.controlled_vehicles = list(self.cavs)
        n = len(self.cavs)
        self.alive = np.ones(n, dtype=bool)
        self.collision_step = np.full(n, self.config["horizon"], dtype=np.int64)
        self.distance_total = np.zeros(n)
        self._distance_step = np.zeros(n)
        self._crashed_now = np.zeros(n, dtype=bool)
        self._episode_distances: list[np.ndarray] = []
        self.crash_sites.clear()
        self.road.refresh()

    def _make_road(self) -> SortedNeighbourRoad:
        raise NotImplementedError

    def _place_vehicle(
        self,
        cls: type[Vehicle],
        lane_index: tuple,
        longitudinal: float,
        speed: float,
        max_speed: float,
        **kwargs: Any,
    ) -> Vehicle:
        """Create a ``cls`` vehicle on ``lane_index`` at ``longitudinal`` and put it on the road."""
        lane = self.road.network.get_lane(lane_index)
        vehicle = cls(
            road=self.road,
            position=lane.position(longitudinal, 0.0),
            heading=lane.heading_at(longitudinal),
            speed=speed,
            target_lane_index=lane_index,
            **kwargs,
        )
        vehicle.lane_index, vehicle.lane = lane_index, lane
        vehicle.MAX_SPEED = max_speed
        self.road.vehicles.append(vehicle)
        return vehicle

    def _draw_cavs(self, n_vehicles: int) -> np.ndarray:
        """Which of ``n_vehicles`` spawned vehicles are CAVs: ``[n_vehicles]`` bool, random."""
        is_cav = np.zeros(n_vehicles, dtype=bool)
        is_cav[self.np_random.choice(n_vehicles, size=self.config["n_cavs"], replace=False)] = True
        return is_cav

    def _spawn_vehicles(self) -> list[Vehicle]:
        raise NotImplementedError

    def observe_agents(self) -> np.ndarray:
        """Per-CAV observations ``[I, obs_dim]`` (zero rows for crashed CAVs)."""
        raise NotImplementedError

    def agent_rewards(self, obs: np.ndarray, action: Any) -> np.ndarray:
        """Per-CAV rewards ``[I]`` for the step just simulated (0 for CAVs already gone).

        ``obs`` is the observation ``[I, obs_dim]`` after the step.
        """
        raise NotImplementedError

    def episode_metrics(self) -> dict[str, float]:
        """Metrics of the episode so far."""
        raise NotImplementedError

    # --- stepping ----------------------------------------------------------------------------
    @property
    def dt(self) -> float:
        """Duration of one environment step [s]."""
        return 1.0 / self.config["policy_frequency"]

    def step(self, action: Any) -> tuple[np.ndarray, float, bool, bool, dict]:
        """Advance all vehicles by one policy step; see the module docstring for the outputs."""
        require(action is not None, "step needs the CAVs' action (got None)")
        try:
            dtype = np.asarray(action).dtype
        except ValueError:  # ragged nested sequences
            dtype = np.dtype(object)
        require(
            dtype.kind in "iuf",
            f"action must be an array of numbers, got a {type(action).__name__} of dtype {dtype}",
        )
        require(
            self.steps_taken < self.config["horizon"] and not self._is_terminated(),
            "the episode is over (truncated at the horizon or every CAV crashed); call reset() "
            "before stepping again",
        )
        self.action_type.validate(action)
        self.time += self.dt
        self._simulate(action)
        self.road.refresh()
        obs = self.observe_agents()
        rewards = self.agent_rewards(obs, action)
        crashed_now = self._crashed_now.copy()
        self.collision_step[crashed_now] = self.steps_taken
        self.alive &= ~crashed_now
        self.road.vehicles = [v for v in self.road.vehicles if not v.crashed]
        self._episode_distances.append(self._distance_step.copy())
        terminated = self._is_terminated()
        truncated = self.steps_taken >= self.config["horizon"]
        info = self._info(obs, action)
        info.update(agent_rewards=rewards, agent_terminated=~self.alive, collided=crashed_now)
        if terminated or truncated:
            info["episode"] = self.episode_metrics()
        return obs, float(rewards.mean()) if rewards.size else 0.0, terminated, truncated, info

    @property
    def steps_taken(self) -> int:
        """Policy steps taken in the current episode."""
        return int(round(self.time * self.config["policy_frequency"]))

    def _simulate(self, action: Any = None) -> None:
        frames = self.config["simulation_frequency"] // self.config["policy_frequency"]
        dt = 1.0 / self.config["simulation_frequency"]
        self._distance_step[:] = 0.0
        self._crashed_now[:] = False
        if action is not None:
            self.action_type.act(action)
        for _ in range(frames):
            self.road.act()
            self.road.step(dt)
            self.steps += 1
            self._on_substep(dt)
        self.distance_total += self._distance_step
        if self.render_mode is not None:  # crashed vehicles leave the road after this step
            self.crash_sites.record(self.road.vehicles, {id(cav) for cav in self.cavs})

    def _on_substep(self, dt: float) -> None:
        """Bookkeeping after each simulation sub-step: distances and new collisions."""
        for i, cav in enumerate(self.cavs):
            if self.alive[i] and not self._crashed_now[i]:
                self._distance_step[i] += cav.speed * dt
                self._crashed_now[i] = cav.crashed

    def _info(self, obs: np.ndarray, action: Any = None) -> dict:
        return {
            "positions": np.array([cav.position for cav in self.cavs], dtype=np.float32),
            "speed": np.array([cav.speed for cav in self.cavs], dtype=np.float32) * self.alive,
            "distance": self._distance_step.astype(np.float32),
            "alive": self.alive.copy(),
        }

    def _is_terminated(self) -> bool:
        return bool(len(self.cavs) > 0 and not self.alive.any())

    def _is_truncated(self) -> bool:
        return self.steps_taken >= self.config["horizon"]

    def _reward(self, action: Any) -> float:
        rewards = self.agent_rewards(self.observe_agents(), action)
        return float(rewards.mean()) if rewards.size else 0.0

    # --- rendering ---------------------------------------------------------------------------
    def render(self) -> np.ndarray | None:
        """An RGB frame ``[H, W, 3]`` (``render_mode="rgb_array"``) centred on
        :attr:`view_centre`: CAVs green and human drivers blue, every crash of the episode
        marked where it happened, a legend naming them and ``step k / H`` (policy steps taken
        of the horizon) in the top-right corner (:mod:`mapets_rl.envs.rendering`)."""
        if self.render_mode is None:
            return super().render()
        paint_vehicles(self.road.vehicles, {id(cav) for cav in self.cavs})
        if self.viewer is None:
            self.viewer = EnvViewer(self)
            self.viewer.observer_vehicle = _Origin(self.view_centre)
        else:
            self.viewer.observer_vehicle.position = self.view_centre
        frame = super().render()
        if frame is None:
            return None
        frame = draw_step_counter(frame, self.steps_taken, self.config["horizon"])
        cavs = int(self.alive.sum())
        counts = {"CAVs": cavs, "human drivers": len(self.road.vehicles) - cavs}
        return decorate_frame(frame, self.viewer.sim_surface, self.crash_sites, counts)

    @property
    def crash_sites(self) -> CrashSites:
        """The crashes of the episode so far, recorded while rendering is on."""
        if "_crash_sites" not in self.__dict__:
            self._crash_sites = CrashSites()
        return self._crash_sites
