"""Freeway scenario (Shapley reward-reallocation paper, Han et al.; CARLA Town05 freeway).

A straight 3-lane freeway (highway-env ``StraightLane``s) with ``n_vehicles`` vehicles, of which
``round(cav_ratio * n_vehicles)`` are CAVs (learning agents) and the rest highway-env IDM/MOBIL
human drivers. The paper's CARLA Town05 outer loop is replaced by a straight road long enough
for the episode (checked at construction). One step lasts ``1 / policy_frequency`` s (default
1 s); episodes last 40 steps (paper).

CAV action: one of ``KL, CL, CR, ES`` (0..3): keep lane, change left (lane id - 1), change right
(lane id + 1) — longitudinal control is IDM towards ``cav_target_speed`` in all three — and
emergency stop (target speed 0 at maximum braking, ``-6 m/s^2``, for that step).

CAV observation (``OBS_DIM = 22``): own ``(speed, lane, lateral offset, acceleration)``, then
for the six neighbours *front/rear* in the *left/own/right* lane: ``(present, dx, dv)`` with
``dx`` the centre distance along the road clipped to ``+-perception`` metres and ``dv`` the
speed difference (neighbour minus own); absent neighbours read ``(0, +-perception, 0)``.

Reward per CAV (paper eq. 10): ``R_i = w * velocity + comfort`` with comfort (eq. 9) 3 if
``|acc| < Theta`` and KL, 2 if ``|acc| >= Theta`` and KL, 1 for CL/CR (``lane_change_comfort``,
1 by default), 0 for ES; ``|acc|`` is
the mean absolute acceleration over the step. A CAV that collides gets ``collision_reward``
and is terminated. Human drivers' comfort uses KL unless MOBIL changed lane during the step.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from gymnasium import spaces
from highway_env.envs.common.action import ActionType
from highway_env.road.lane import LineType, StraightLane
from highway_env.road.road import RoadNetwork
from highway_env.vehicle.kinematics import Vehicle

from mapets_rl.envs.lanes import FastStraightLane
from mapets_rl.envs.road import SortedNeighbourRoad
from mapets_rl.envs.traffic import AgentObservation, MultiAgentTrafficEnv, require
from mapets_rl.envs.validation import (
    PHYSICAL_MAX_SPEED,
    is_integer,
    is_real,
    require_number,
    require_range,
)
from mapets_rl.envs.vehicles import ACC_MIN, FastIDMVehicle, HumanVehicle, clip
from mapets_rl.metrics import average_comfort, average_velocity

KL, CL, CR, ES = 0, 1, 2, 3
MAX_ROAD_LENGTH = 50_000.0
"""Longest road, spawn region and perception range [m] (a 40-step episode at the speed limit
covers 1.3 km; larger values only overflow the lane geometry)."""
ACTION_NAMES = ("KL", "CL", "CR", "ES")
OBS_DIM = 4 + 6 * 3


class LaneDecisionVehicle(FastIDMVehicle):
    """A CAV on the freeway: IDM longitudinal control, lane decisions from its agent."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, enable_lane_change=False, **kwargs)
        self.decision = KL

    def act(self, action: dict | str | None = None) -> None:
        if self.crashed:
            return
        if self.decision != ES:
            super().act()
            return
        self.follow_road()
        Vehicle.act(
            self,
            {
                "steering": clip(
                    self.steering_control(self.target_lane_index),
                    -self.MAX_STEERING_ANGLE,
                    self.MAX_STEERING_ANGLE,
                ),
                "acceleration": ACC_MIN if self.speed > 0 else 0.0,
            },
        )


class LaneDecisionAction(ActionType):
    """Discrete per-CAV action ``[I]`` with values in ``{0: KL, 1: CL, 2: CR, 3: ES}``."""

    def __init__(self, env: FreewayEnv, **kwargs: Any) -> None:
        super().__init__(env)
        self.n = env.config["n_cavs"]

    def space(self) -> spaces.MultiDiscrete:
        return spaces.MultiDiscrete([4] * self.n)

    @property
    def vehicle_class(self) -> type:
        return LaneDecisionVehicle

    def validate(self, action: Any) -> None:
        """Raise ValueError unless ``action`` is ``[I]`` integers in ``0..3``."""
        action = np.asarray(action)
        require(
            action.shape == (self.n,),
            f"action must have shape ({self.n},) (one of KL, CL, CR, ES per CAV), "
            f"got {action.shape}",
        )
        require(
            bool(np.isfinite(action).all())
            and bool((action == np.round(action)).all())
            and bool(((action >= 0) & (action <= 3)).all()),
            f"action values must be integers in [0, 3] (KL, CL, CR, ES), got {action}",
        )

    def act(self, action: np.ndarray) -> None:
        env = self.env
        lanes = env.config["lanes"]
        for i, cav in enumerate(env.cavs):
            if not env.alive[i]:
                continue
            decision = int(action[i])
            cav.decision = decision
            _from, _to, lane = cav.lane_index
            if decision in (CL, CR):
                target = lane - 1 if decision == CL else lane + 1
                if 0 <= target < lanes and cav.lane_index == cav.target_lane_index:
                    cav.target_lane_index = (_from, _to, target)


class FreewayEnv(MultiAgentTrafficEnv):
    """3-lane freeway with mixed CAV / human traffic (see module docstring).

    Config keys (defaults): ``n_vehicles=30``, ``cav_ratio=1.0``, ``lanes=3``, ``horizon=40``,
    ``policy_frequency=1`` Hz, ``simulation_frequency=10`` Hz, ``road_length=3000`` m,
    ``spawn_length=600`` m, ``min_spacing=20`` m, ``initial_speed=(22, 28)`` m/s,
    ``hv_target_speed=(25, 30)`` m/s, ``cav_target_speed=31.0`` m/s, ``speed_limit=31.3`` m/s
    (70 mph), ``velocity_weight=0.1`` (w), ``comfort_threshold=1.5`` m/s^2 (Theta),
    ``lane_change_comfort=1`` (the comfort of a step with a lane change, eq. 9's 1, in [0, 3]
    (the comfort scores' range): below 1 a lane change costs more than the paper's, as in the
    dilemma variant of ``freeway-merge``), ``collision_reward=-10``, ``perception=100`` m,
    ``team_reward=False`` (True: every CAV is paid the mean reward of the CAVs driving that step
    instead of its own, the fully cooperative reward; the system reward, the sum over CAVs, is
    the same), ``shield=False`` (True: a model-predictive shield replaces every decision
    predicted to crash in the next step; the torch backend only, see ``BatchedFreeway.shield``),
    ``shield_horizon=3`` (policy steps the shield looks ahead), ``shield_passes=1`` (1: the
    proposed decisions are checked once; ``n > 1``: the corrected decisions are checked again,
    up to ``n`` passes in all, until a pass replaces nothing, so that no move runs beside a
    replacement it was not checked with).
    """

    obs_dim = OBS_DIM
    min_cavs = 0

    def __init__(self, config: dict | None = None, render_mode: str | None = None) -> None:
        require(
            not (config or {}).get("shield", False),
            "shield=True needs backend='torch' (the check steps a copy of the road, which "
            "highway-env cannot do cheaply)",
        )
        super().__init__(config, render_mode)

    @classmethod
    def derived_config(cls, config: dict) -> dict:
        """``n_cavs = round(cav_ratio * n_vehicles)`` (not set by a user)."""
        require(
            is_real(config["cav_ratio"]) and 0.0 <= config["cav_ratio"] <= 1.0,
            f"cav_ratio must be a number in [0, 1], got {config['cav_ratio']!r}",
        )
        require(
            is_integer(config["n_vehicles"]) and config["n_vehicles"] >= 1,
            f"n_vehicles must be an integer >= 1, got {config['n_vehicles']!r}",
        )
        return {"n_cavs": int(round(config["cav_ratio"] * config["n_vehicles"]))}

    @classmethod
    def default_config(cls) -> dict:
        config = super().default_config()
        config.update(
            {
                "n_vehicles": 30,
                "cav_ratio": 1.0,
                "n_cavs": 30,
                "lanes": 3,
                "horizon": 40,
                "policy_frequency": 1,
                "simulation_frequency": 10,
                "road_length": 3000.0,
                "spawn_length": 600.0,
                "min_spacing": 20.0,
                "initial_speed": (22.0, 28.0),
                "hv_target_speed": (25.0, 30.0),
                "cav_target_speed": 31.0,
                "speed_limit": 31.3,
                "velocity_weight": 0.1,
                "team_reward": False,
                "shield": False,
                "shield_horizon": 3,
                "shield_passes": 1,
                "comfort_threshold": 1.5,
                "lane_change_comfort": 1.0,
                "perception": 100.0,
                "screen_width": 900,
                "screen_height": 200,
                "scaling": 3.0,
                "centering_position": [0.5, 0.5],
            }
        )
        return config

    @classmethod
    def validate_config(cls, config: dict) -> None:
        super().validate_config(config)
        require(
            is_integer(config["lanes"]) and config["lanes"] >= 2,
            f"lanes must be an integer >= 2, got {config['lanes']!r}",
        )
        positive = {
            "speed_limit": "m/s",
            "road_length": "m",
            "spawn_length": "m",
            "perception": "m",
            "comfort_threshold": "m/s^2",
        }
        for key, unit in positive.items():
            require_number(config, key, low=0.0, low_open=True, unit=unit)
        for key in ("road_length", "spawn_length", "perception"):
            require_number(config, key, high=MAX_ROAD_LENGTH, unit="m")
        require_number(config, "speed_limit", high=PHYSICAL_MAX_SPEED, unit="m/s")
        require_number(config, "min_spacing", low=7.0, unit="m")
        require_number(config, "velocity_weight")
        require_number(config, "lane_change_comfort", low=0.0, high=3.0)
        require(
            is_integer(config["shield_horizon"]) and 1 <= config["shield_horizon"] <= 40,
            f"shield_horizon must be an integer in [1, 40], got {config['shield_horizon']!r}",
        )
        require(
            is_integer(config["shield_passes"]) and 1 <= config["shield_passes"] <= 40,
            f"shield_passes must be an integer in [1, 40], got {config['shield_passes']!r}",
        )
        for key in ("team_reward", "shield"):
            require(
                isinstance(config[key], bool), f"{key} must be True or False, got {config[key]!r}"
            )
        defaults = cls.default_config()
        for key in ("shield_horizon", "shield_passes"):
            require(
                config["shield"] or config[key] == defaults[key],
                f"{key}={config[key]!r} needs shield=True (without the shield it changes nothing)",
            )
        require_range(config, "initial_speed", low=0.0, high=config["speed_limit"], unit="m/s")
        cls.validate_target_speeds(config)
        capacity = cls.capacity(config)
        require(
            config["n_vehicles"] <= capacity,
            f"n_vehicles={config['n_vehicles']} do not fit in spawn_length="
            f"{config['spawn_length']} m x {config['lanes']} lanes at min_spacing="
            f"{config['min_spacing']} m: n_vehicles must be <= {capacity}",
        )
        needed = (
            config["spawn_length"]
            + 1.2 * config["speed_limit"] * config["horizon"] / (config["policy_frequency"])
        )
        require(
            config["road_length"] >= needed,
            f"road_length={config['road_length']} m is too short for horizon="
            f"{config['horizon']} steps at {config['speed_limit']} m/s: must be >= {needed:.0f}",
        )

    @classmethod
    def validate_target_speeds(cls, config: dict) -> None:
        """CAVs drive towards ``cav_target_speed``, humans draw theirs from ``hv_target_speed``."""
        limit = config["speed_limit"]
        require_number(config, "cav_target_speed", low=0.0, low_open=True, high=limit, unit="m/s")
        require_range(config, "hv_target_speed", low=0.0, high=limit, unit="m/s")

    @staticmethod
    def capacity(config: dict) -> int:
        """Number of vehicles that fit in the spawn region at ``min_spacing``."""
        return int(config["spawn_length"] // config["min_spacing"]) * config["lanes"]

    def define_spaces(self) -> None:
        self.observation_type = AgentObservation(self, self.obs_dim)
        self.action_type = LaneDecisionAction(self)
        self.observation_space = self.observation_type.space()
        self.action_space = self.action_type.space()

    @property
    def view_centre(self) -> np.ndarray:
        """The camera's centre: the mean position of the CAVs still driving [m]."""
        alive = [cav.position for i, cav in enumerate(self.cavs) if self.alive[i]]
        return np.mean(alive or [v.position for v in self.road.vehicles], axis=0)

    def _make_road(self) -> SortedNeighbourRoad:
        return SortedNeighbourRoad(
            self._make_network(),
            coordinate=lambda lane_index, position: float(position[0]),
            period=None,
            n_lanes=self.lane_tables,
            stock_neighbour_search=self.config["stock_neighbour_search"],
            np_random=self.np_random,
            lane_id=self.lane_id,
        )

    @property
    def lane_tables(self) -> int:
        """Lanes of the road's neighbour search (:class:`SortedNeighbourRoad`)."""
        return self.config["lanes"]

    lane_id = None
    """Lane index -> lane id of the neighbour search (``None``: the index's last element)."""

    def _make_network(self) -> RoadNetwork:
        """The lanes: ``("0", "1", k)`` for ``k = 0 .. lanes - 1`` (0 the leftmost)."""
        cfg = self.config
        width = StraightLane.DEFAULT_WIDTH
        net = RoadNetwork()
        for lane in range(cfg["lanes"]):
            lines = (
                LineType.CONTINUOUS_LINE if lane == 0 else LineType.STRIPED,
                LineType.CONTINUOUS_LINE if lane == cfg["lanes"] - 1 else LineType.NONE,
            )
            net.add_lane(
                "0",
                "1",
                FastStraightLane(
                    [0.0, lane * width],
                    [cfg["road_length"], lane * width],
                    line_types=lines,
                    speed_limit=cfg["speed_limit"],
                ),
            )
        return net

    cav_class: type[LaneDecisionVehicle] = LaneDecisionVehicle
    """The vehicle class of the CAVs."""

    def _spawn_slots(self, n: int | None = None) -> list[tuple[tuple, float]]:
        """``(lane index, longitudinal position [m])`` of ``n`` vehicles (default
        ``n_vehicles``) at the start: random distinct slots ``min_spacing`` apart over
        ``spawn_length`` metres of every lane."""
        cfg = self.config
        per_lane = int(cfg["spawn_length"] // cfg["min_spacing"])
        n = cfg["n_vehicles"] if n is None else n
        slots = self.np_random.choice(per_lane * cfg["lanes"], size=n, replace=False)
        return [
            (("0", "1", int(slot // per_lane)), float((slot % per_lane) * cfg["min_spacing"]))
            for slot in slots
        ]

    def _initial_speed(self, lane_index: tuple) -> float:
        """A start speed [m/s] for a vehicle on ``lane_index``, from ``initial_speed``."""
        return float(self.np_random.uniform(*self.config["initial_speed"]))

    def _target_speed(self, cav: bool) -> float:
        """A target speed [m/s]: ``cav_target_speed`` for a CAV, a draw from
        ``hv_target_speed`` for a human driver."""
        if cav:
            return float(self.config["cav_target_speed"])
        return float(self.np_random.uniform(*self.config["hv_target_speed"]))

    def _spawn_vehicles(self) -> list[Vehicle]:
        cfg = self.config
        slots = self._spawn_slots()
        is_cav = self._draw_cavs(len(slots))
        cavs = []
        for k, (lane_index, x) in enumerate(slots):
            speed = self._initial_speed(lane_index)
            vehicle = self._place_vehicle(
                self.cav_class if is_cav[k] else HumanVehicle,
                lane_index,
                x,
                speed,
                cfg["speed_limit"],
                target_speed=self._target_speed(bool(is_cav[k])),
            )
            if is_cav[k]:
                cavs.append(vehicle)
            else:
                vehicle.randomize_behavior()
        # CAVs in a fixed order along the road, so agent ids are reproducible and meaningful.
        cavs.sort(key=lambda v: (v.position[0], v.lane_index[2]))
        self.vehicles_all = list(self.road.vehicles)
        self._abs_acc = np.zeros(len(self.vehicles_all))
        self._lane_change = np.zeros(len(self.vehicles_all), dtype=bool)
        self._speeds: list[np.ndarray] = []
        self._comforts: list[np.ndarray] = []
        return cavs

    def _simulate(self, action: Any = None) -> None:
        self._abs_acc[:] = 0.0
        self._lane_change[:] = False
        super()._simulate(action)
        frames = self.config["simulation_frequency"] // self.config["policy_frequency"]
        self._abs_acc /= frames
        on_road = {id(v) for v in self.road.vehicles}
        present = np.array([id(v) in on_road for v in self.vehicles_all])
        speeds = np.array([v.speed for v in self.vehicles_all])
        self._speeds.append(np.where(present, speeds, np.nan))
        self._comforts.append(np.where(present, self._vehicle_comfort(), np.nan))

    def _on_substep(self, dt: float) -> None:
        super()._on_substep(dt)
        for k, vehicle in enumerate(self.vehicles_all):
            self._abs_acc[k] += abs(vehicle.action["acceleration"])
            self._lane_change[k] |= vehicle.lane_index != vehicle.target_lane_index

    def _vehicle_comfort(self) -> np.ndarray:
        """Comfort (paper eq. 9) of every vehicle for the step just simulated ``[N]``."""
        smooth = self._abs_acc < self.config["comfort_threshold"]
        comfort = np.where(smooth, 3.0, 2.0)
        changing = self.config["lane_change_comfort"]
        comfort[self._lane_change] = changing
        index = {id(v): k for k, v in enumerate(self.vehicles_all)}
        for cav in self.cavs:
            decision = cav.decision
            if decision in (CL, CR):
                comfort[index[id(cav)]] = changing
            elif decision == ES:
                comfort[index[id(cav)]] = 0.0
        return comfort

    def _neighbours(self, cav: Vehicle) -> np.ndarray:
        rng_ = self.config["perception"]
        feats = np.zeros((6, 3), dtype=np.float32)
        for k, lane_index in enumerate(self._observed_lanes(cav)):
            front, rear = (
                self.road.neighbour_vehicles(cav, lane_index)
                if lane_index is not None
                else (None, None)
            )
            for j, (other, sign) in enumerate(((front, 1.0), (rear, -1.0))):
                row = feats[2 * k + j]
                if not isinstance(other, Vehicle):  # none, or a road object (not a neighbour)
                    other = None
                dx = self.road.longitudinal_distance(cav, other) if other is not None else None
                if dx is None or abs(dx) > rng_:
                    row[:] = (0.0, sign * rng_, 0.0)
                else:
                    row[:] = (1.0, dx, other.speed - cav.speed)
        return feats.ravel()

    def _observed_lanes(self, cav: Vehicle) -> tuple[tuple | None, tuple | None, tuple | None]:
        """The lanes of the left / own / right neighbour blocks of ``cav``'s observation
        (``None`` where there is no such lane)."""
        _from, _to, own = cav.lane_index
        return tuple(
            (_from, _to, lane) if 0 <= lane < self.config["lanes"] else None
            for lane in (own - 1, own, own + 1)
        )

    def observe_agents(self) -> np.ndarray:
        obs = np.zeros((len(self.cavs), self.obs_dim), dtype=np.float32)
        for i, cav in enumerate(self.cavs):
            if not self.alive[i]:
                continue
            lane = self.road.network.get_lane(cav.lane_index)
            lateral = lane.local_coordinates(cav.position)[1]
            own = (cav.speed, cav.lane_index[2], lateral, cav.action["acceleration"])
            obs[i, :4] = own
            obs[i, 4:OBS_DIM] = self._neighbours(cav)
        return obs

    def agent_rewards(self, obs: np.ndarray, action: Any) -> np.ndarray:
        """``w * velocity + comfort`` per CAV (paper eq. 10); ``collision_reward`` on crash."""
        if not self.cavs:
            return np.zeros(0, dtype=np.float32)
        index = {id(v): k for k, v in enumerate(self.vehicles_all)}
        comfort = self._comforts[-1][[index[id(cav)] for cav in self.cavs]]
        speed = np.array([cav.speed for cav in self.cavs])
        rewards = self.config["velocity_weight"] * speed + np.nan_to_num(comfort)
        rewards = np.where(self._crashed_now, self.config["collision_reward"], rewards)
        paid = self.alive | self._crashed_now
        if self.config["team_reward"] and paid.any():
            rewards = np.full_like(rewards, rewards[paid].mean())
        return (rewards * paid).astype(np.float32)

    def _info(self, obs: np.ndarray, action: Any = None) -> dict:
        info = super()._info(obs, action)
        comforts = self._comforts[-1] if getattr(self, "_comforts", None) else None
        info["traffic_velocity"] = (
            float(np.nanmean(self._speeds[-1])) if comforts is not None else 0.0
        )
        info["traffic_comfort"] = float(np.nanmean(comforts)) if comforts is not None else 0.0
        return info

    def scripted_action(self) -> np.ndarray:
        """Keep Lane for every CAV (IDM car following) ``[I]``."""
        return np.full(len(self.cavs), KL, dtype=np.int64)

    def episode_metrics(self) -> dict[str, float]:
        """Average velocity [m/s] and comfort of all vehicles over the episode; CAV return."""
        speeds = np.stack(self._speeds)
        comforts = np.stack(self._comforts)
        present = ~np.isnan(speeds)
        return {
            "average_velocity": average_velocity(speeds[present]),
            "average_comfort": average_comfort(comforts[present]),
            "collisions": int((~self.alive).sum()),
        }
