"""Figure-eight scenario (MA-PETS paper, Wen et al., sec. VI: SMARTS unprotected intersection).

CAVs (learning agents) and human-driven vehicles (IDM/MOBIL with a first-come-first-served
crossing rule) share a ~480 m figure-eight loop whose two straights cross at one unsignalised
intersection. Each step lasts 0.1 s.

CAV observation, ``observation="paper"`` (7): ``(v, x, y, v_ahead, v_behind, gap_ahead,
gap_behind)``; speeds in m/s, position in metres, gaps bumper-to-bumper along the lane in
``[0, 75]`` m (75 and neighbour speed 0 when nobody is within 75 m). ``observation="crossing"``
(10, the default; a deviation from the paper, whose CAVs cannot see traffic on the crossing
branch) appends ``(d_cross, d_conflict, v_conflict)``: the CAV's signed route distance to the
next crossing point it has not cleared, and the signed distance to that point and the speed of
the first vehicle on the other branch that has not cleared it (both in ``[-5, 75]`` m; 75 and
speed 0 when nobody is within 75 m). A vehicle has cleared the crossing once its centre is 5 m
past the crossing point.

On two lanes (``lanes=2``) ``observation="crossing"`` has 15 features (a further deviation: the
paper's CAVs cannot see the other lane, so a lane change, theirs or a human's, is a jump no model
can predict): the 10 above, then ``(lane, v_ahead_other, v_behind_other, gap_ahead_other,
gap_behind_other)``. ``lane`` is the CAV's lateral position in lane widths (0 = centre of the inner
lane 0, 1 = centre of lane 1; it moves continuously through a lane change, so the model can
learn when the CAV's lane switches), the other four are the leader and follower of the CAV in
the lane it is not on, measured and clipped like the own-lane gaps. ``observation="paper"`` stays
the paper's 7 features on two lanes.

``info["neighbour_cav"]`` ``[I, K]`` says which CAV (its agent index; ``-1``: a human driver or
nobody) each observed vehicle is, in the order of :func:`neighbour_speed_columns` (leader,
follower, then the conflicting vehicle, then the other lane's leader and follower): what a CAV
needs to read a neighbour's broadcast plan (MA-PETS ``comm.share_plans``).

``info["neighbour_changed"]`` ``[I]`` flags the CAVs whose observed neighbours changed identity in
this step (a new leader or follower, one removed after a crash, a vehicle entering or leaving the
75 m range, a new conflicting vehicle or crossing, and on two lanes a new leader or follower in
the other lane): their gap features jump, which no dynamics model of the CAV's own motion can
predict. (Keeping the changes that only move an observed vehicle between the own and the other
lane's slots was measured and rejected: their jumps of up to 70 m raise the gap-ahead error of an
exact own-motion model on the kept transitions from 0.06 to 2.7 m per step, and flagging every
change keeps 93% of the transitions once CAVs no longer weave; ``docs/results/mapets.md``.)

CAV action: target speed in ``[0, 13.89]`` m/s, plus on two lanes a lane-change flag in
``[0, 1]`` (> 0.5 requests a change to the other lane; a request starts a change only while
the CAV is settled within 0.5 m of its lane's centre, so a flag held through a change does not
turn it back). Reward (paper eq. 26):
``r = v + v_ahead + v_behind + beta`` with ``beta = -10`` on collision.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Mapping
from typing import Any

import numpy as np
import torch
from gymnasium import spaces
from highway_env.envs.common.action import ActionType

from mapets_rl.config import check
from mapets_rl.envs.figure_eight_road import FigureEightGeometry
from mapets_rl.envs.planner_reward import PlannerReward
from mapets_rl.envs.road import SortedNeighbourRoad
from mapets_rl.envs.traffic import AgentObservation, MultiAgentTrafficEnv, require
from mapets_rl.envs.validation import (
    PHYSICAL_MAX_SPEED,
    is_integer,
    require_number,
    require_range,
)
from mapets_rl.envs.vehicles import HumanVehicle, TargetSpeedVehicle, clip, idm_acceleration
from mapets_rl.metrics import agility, safety

MAX_LENGTH = 20_000.0
"""The longest figure-eight loop [m] (the default is 480 m): the initial vehicle slots are laid
out along it, so a typo such as ``length=1e15`` would ask for petabytes."""
MAX_SPEED = 13.89
"""Speed limit of the figure-eight [m/s] (50 km/h)."""
GAP_RANGE = 75.0
"""Sensing range of the gap observations [m]."""
OBS_DIM = 7
"""Size of the paper's observation (``observation="paper"``)."""
CROSSING_OBS_DIM = 10
"""Size of the observation with the crossing features (``observation="crossing"``, one lane)."""
TWO_LANE_OBS_DIM = 15
"""Size of ``observation="crossing"`` on two lanes: the crossing features + lane + other lane."""
OBSERVATIONS = {"paper": OBS_DIM, "crossing": CROSSING_OBS_DIM}
"""Observation options of the figure-eight and their sizes on one lane."""
OBSERVATION_SIZES = (OBS_DIM, CROSSING_OBS_DIM, TWO_LANE_OBS_DIM)
"""Every size a figure-eight observation can have (one or two lanes)."""
LANE_CHANGE_THRESHOLD = 0.5
"""A lane-change flag above this requests a change to the other lane."""
SETTLED_LANE_POSITION = TargetSpeedVehicle.SETTLED / 4.0
"""The lane position (in lane widths of 4 m) within which a CAV may start a lane change."""
CROSSING_CLEAR = 5.0
"""A vehicle whose centre is this far past a crossing point [m] has cleared the crossing."""
COLLISION_REWARD = -10.0


class FigureEightRoad(SortedNeighbourRoad):
    """The figure-eight road with a first-come-first-served rule at the crossing.

    Each simulation step every vehicle within ``approach`` metres before the conflict zone of
    its branch (``zone_half`` metres either side of the crossing point) is queued by the step at
    which it arrived (ties: nearer first). A queued vehicle must stop before the zone while a
    vehicle of the other branch is inside the zone or is queued ahead of it.
    """

    def __init__(
        self,
        geometry: FigureEightGeometry,
        zone_half: float = 7.0,
        approach: float = 40.0,
        stock_neighbour_search: bool = False,
        np_random: np.random.Generator | None = None,
    ) -> None:
        super().__init__(
            geometry.network,
            coordinate=geometry.coordinate,
            period=geometry.length,
            n_lanes=geometry.lanes,
            stock_neighbour_search=stock_neighbour_search,
            np_random=np_random,
        )
        self.geometry = geometry
        self.zone_half = zone_half
        self.approach = approach
        self.clock = 0
        self._arrival: dict[tuple[int, int], int] = {}
        self._stop: dict[int, float] = {}

    def candidate_lanes(self, lane_index: tuple) -> list[tuple]:
        """Lanes a vehicle on ``lane_index`` can be on after one simulation step."""
        return self.geometry.next_segment_lanes(lane_index)

    def refresh(self) -> None:
        """Neighbour tables (even in stock-search mode: the crossing rule needs coordinates)."""
        super().refresh()
        self.clock += 1
        self._update_crossing()

    def act(self) -> None:
        self.refresh()
        for vehicle in self.vehicles:
            vehicle.act()

    def _update_crossing(self) -> None:
        z, d, period = self.zone_half, self.approach, self.period
        occupied = [False, False]
        queued: list[tuple[tuple[int, float], int, int, float]] = []
        arrivals: dict[tuple[int, int], int] = {}
        for vehicle in self.vehicles:
            s = self._coord[id(vehicle)]
            for branch, crossing in enumerate(self.geometry.crossing_coordinates):
                r = (s - crossing + period / 2) % period - period / 2
                if -z <= r <= z:
                    occupied[branch] = True
                elif -z - d <= r < -z:
                    key = (id(vehicle), branch)
                    arrivals[key] = self._arrival.get(key, self.clock)
                    queued.append(((arrivals[key], -r), branch, id(vehicle), r))
        self._arrival = arrivals
        first = [min((q[0] for q in queued if q[1] == b), default=None) for b in (0, 1)]
        self._stop = {}
        for priority, branch, vid, r in queued:
            other = 1 - branch
            if occupied[other] or (first[other] is not None and first[other] < priority):
                # Virtual standing car 5 m inside the zone: the front bumper stops before it.
                self._stop[vid] = -r - z + 5.0

    def stop_distance(self, vehicle: object) -> float | None:
        """Distance [m] to the virtual obstacle ``vehicle`` must stop for, ``None`` if free."""
        return self._stop.get(id(vehicle))


class TargetSpeedAction(ActionType):
    """Continuous per-CAV action: target speed (+ lane-change flag on two lanes).

    Action array ``[I, 1]`` (``[I, 2]`` on two lanes) with bounds ``[0, max_speed]`` (and
    ``[0, 1]`` for the flag). Out-of-bound, wrong-shaped or non-finite actions raise ValueError.
    """

    def __init__(self, env: FigureEightEnv, **kwargs: Any) -> None:
        super().__init__(env)
        n, lanes = env.config["n_cavs"], env.config["lanes"]
        high = [env.config["max_speed"]] + ([1.0] if lanes == 2 else [])
        self.low = np.zeros((n, len(high)), dtype=np.float32)
        self.high = np.tile(np.array(high, dtype=np.float32), (n, 1))

    def space(self) -> spaces.Box:
        return spaces.Box(self.low, self.high, dtype=np.float32)

    @property
    def vehicle_class(self) -> type:
        return TargetSpeedVehicle

    def validate(self, action: Any) -> None:
        """Raise ValueError unless ``action`` has shape ``[I, act_dim]`` and is within bounds."""
        action = np.asarray(action, dtype=np.float64)
        require(
            action.shape == self.low.shape,
            f"action must have shape {self.low.shape} (n_cavs, act_dim), got {action.shape}",
        )
        require(bool(np.isfinite(action).all()), "action must be finite (got NaN or inf)")
        tol = 1e-4
        if not ((action >= self.low - tol) & (action <= self.high + tol)).all():
            flag = " and the lane-change flag in [0, 1]" if self.low.shape[1] == 2 else ""
            raise ValueError(
                f"action out of bounds: target speed must be in [0, {self.high[0, 0]:.2f}] m/s"
                f"{flag}, got min {action.min(0)} max {action.max(0)}"
            )

    def act(self, action: np.ndarray) -> None:
        action = np.clip(np.asarray(action, dtype=np.float64), self.low, self.high)
        env = self.env
        for i, cav in enumerate(env.cavs):
            if not env.alive[i]:
                continue
            cav.target_speed = float(action[i, 0])
            if action.shape[1] == 2 and action[i, 1] > LANE_CHANGE_THRESHOLD:
                _from, _to, lane = cav.lane_index
                cav.request_lane_change((_from, _to, 1 - lane))


class FigureEightEnv(MultiAgentTrafficEnv):
    """Figure-eight loop with ``n_cavs`` CAVs and a random number of human-driven vehicles.

    Config keys (with defaults): ``n_cavs=8``, ``n_hvs=(8, 20)`` (inclusive range drawn per
    episode, or an int), ``lanes=1`` (1 or 2), ``length=480.0`` m, ``horizon=200`` steps,
    ``policy_frequency=10`` Hz, ``simulation_frequency=10`` Hz, ``max_speed=13.89`` m/s,
    ``initial_speed=(4.0, 8.0)`` m/s, ``hv_target_speed=(10.0, 13.89)`` m/s,
    ``min_spacing=12.0`` m (initial bumper-to-bumper spacing >= 7 m), ``collision_reward=-10``,
    ``observation="crossing"`` (``"paper"``: the paper's 7 features; see the module docstring),
    ``stock_neighbour_search=False`` (True uses highway-env's stock search; benchmark reference).
    """

    _observed_ids: np.ndarray | None = None
    _previous_ids: np.ndarray | None = None

    @property
    def obs_dim(self) -> int:
        """Observation size of the configured ``observation`` option and lanes (7, 10 or 15)."""
        return observation_size(self.config["observation"], self.config["lanes"])

    @classmethod
    def default_config(cls) -> dict:
        config = super().default_config()
        config.update(
            {
                "n_cavs": 8,
                "n_hvs": (8, 20),
                "lanes": 1,
                "length": 480.0,
                "horizon": 200,
                "max_speed": MAX_SPEED,
                "initial_speed": (4.0, 8.0),
                "hv_target_speed": (10.0, MAX_SPEED),
                "min_spacing": 12.0,
                "collision_reward": COLLISION_REWARD,
                "observation": "crossing",
                "screen_width": 640,
                "screen_height": 400,
                "scaling": 3.2,
                "centering_position": [0.5, 0.5],
            }
        )
        return config

    @classmethod
    def validate_config(cls, config: dict) -> None:
        super().validate_config(config)
        require(
            is_integer(config["lanes"]) and config["lanes"] in (1, 2),
            f"lanes must be 1 or 2, got {config['lanes']!r}",
        )
        require(
            config["observation"] in OBSERVATIONS,
            f"observation must be one of {sorted(OBSERVATIONS)}, got {config['observation']!r}",
        )
        require_number(config, "length", low=0.0, low_open=True, high=MAX_LENGTH, unit="m")
        require_number(
            config, "max_speed", low=0.0, low_open=True, high=PHYSICAL_MAX_SPEED, unit="m/s"
        )
        require_range(config, "initial_speed", low=0.0, high=config["max_speed"], unit="m/s")
        require_range(config, "hv_target_speed", low=0.0, high=config["max_speed"], unit="m/s")
        require_number(config, "min_spacing", low=7.0, unit="m")
        n_hvs = config["n_hvs"]
        require(
            (is_integer(n_hvs) and n_hvs >= 0)
            or (
                isinstance(n_hvs, list | tuple)
                and len(n_hvs) == 2
                and all(is_integer(n) for n in n_hvs)
                and 0 <= n_hvs[0] <= n_hvs[1]
            ),
            f"n_hvs must be an int >= 0 or a range (lo, hi) of ints with 0 <= lo <= hi, got "
            f"{n_hvs!r}",
        )
        lo, hi = cls.hv_range(n_hvs)
        capacity = cls.capacity(config)
        require(
            config["n_cavs"] + hi <= capacity,
            f"n_cavs + max n_hvs = {config['n_cavs'] + hi} vehicles do not fit on a "
            f"{config['lanes']}-lane loop of {config['length']} m at min_spacing="
            f"{config['min_spacing']} m: n_cavs + n_hvs must be <= {capacity}",
        )

    @staticmethod
    def hv_range(n_hvs: int | tuple[int, int]) -> tuple[int, int]:
        """``(lo, hi)`` of the human-driven vehicle count."""
        if isinstance(n_hvs, int | np.integer):
            return int(n_hvs), int(n_hvs)
        lo, hi = n_hvs
        return int(lo), int(hi)

    @staticmethod
    def spawn_slots(geometry: FigureEightGeometry, spacing: float) -> np.ndarray:
        """Route coordinates where vehicles may start: evenly spaced, clear of the crossing."""
        slots = np.arange(0.0, geometry.length - spacing / 2, spacing)
        r = (slots[:, None] - geometry.crossing_coordinates[None, :]) % geometry.length
        r = np.minimum(r, geometry.length - r)
        return slots[(r > 20.0).all(axis=1)]

    @classmethod
    def capacity(cls, config: dict) -> int:
        """Number of vehicles that fit at ``min_spacing`` on all lanes."""
        geometry = FigureEightGeometry(config["length"], config["lanes"])
        return len(cls.spawn_slots(geometry, config["min_spacing"])) * config["lanes"]

    def define_spaces(self) -> None:
        self.observation_type = AgentObservation(self, self.obs_dim)
        self.action_type = TargetSpeedAction(self)
        self.observation_space = self.observation_type.space()
        self.action_space = self.action_type.space()

    def _make_road(self) -> FigureEightRoad:
        if getattr(self, "_geometry_key", None) != (self.config["length"], self.config["lanes"]):
            self.geometry = FigureEightGeometry(self.config["length"], self.config["lanes"])
            self._geometry_key = (self.config["length"], self.config["lanes"])
        return FigureEightRoad(
            self.geometry,
            stock_neighbour_search=self.config["stock_neighbour_search"],
            np_random=self.np_random,
        )

    def _spawn_vehicles(self) -> list[TargetSpeedVehicle]:
        cfg, rng, geometry = self.config, self.np_random, self.geometry
        lo, hi = self.hv_range(cfg["n_hvs"])
        n_hvs = int(rng.integers(lo, hi + 1))
        n_cavs = cfg["n_cavs"]
        slots = [
            (s, lane)
            for lane in range(cfg["lanes"])
            for s in self.spawn_slots(geometry, cfg["min_spacing"])
        ]
        chosen = rng.choice(len(slots), size=n_cavs + n_hvs, replace=False)
        is_cav = self._draw_cavs(n_cavs + n_hvs)
        cavs = []
        for k, slot in enumerate(chosen):
            s, lane = slots[slot]
            lane_index, longitudinal = geometry.lane_at(s, lane)
            speed = float(rng.uniform(*cfg["initial_speed"]))
            if is_cav[k]:
                cavs.append(
                    self._place_vehicle(
                        TargetSpeedVehicle,
                        lane_index,
                        longitudinal,
                        speed,
                        cfg["max_speed"],
                        target_speed=speed,
                    )
                )
            else:
                self._place_vehicle(
                    HumanVehicle,
                    lane_index,
                    longitudinal,
                    speed,
                    cfg["max_speed"],
                    target_speed=float(rng.uniform(*cfg["hv_target_speed"])),
                    enable_lane_change=cfg["lanes"] > 1,
                ).randomize_behavior()
        return cavs

    def _reset(self) -> None:
        super()._reset()
        self._observed_ids = None
        self._previous_ids = None

    def _neighbour_features(
        self, cav: TargetSpeedVehicle, lane_index: tuple | None = None
    ) -> tuple[tuple[float, float, float, float], tuple[int, int]]:
        """``(v_ahead, v_behind, gap_ahead, gap_behind)`` and the ids (``-1``: nobody in range)
        of the leader and follower of ``cav`` in lane ``lane_index`` (default: its own)."""
        front, rear = self.road.neighbour_vehicles(cav, lane_index)
        out, ids = [], []
        for other, sign in ((front, 1.0), (rear, -1.0)):
            gap = GAP_RANGE + 1.0
            if other is not None:
                distance = sign * self.road.longitudinal_distance(cav, other)
                if distance < 0:  # stock search may return cars behind as "front"
                    distance += self.road.period
                gap = distance - 0.5 * (cav.LENGTH + other.LENGTH)
            if gap > GAP_RANGE:
                out.append((0.0, GAP_RANGE))
                ids.append(-1)
            else:
                out.append((float(other.speed), float(clip(gap, 0.0, GAP_RANGE))))
                ids.append(id(other))
        (v_ahead, gap_ahead), (v_behind, gap_behind) = out
        return (v_ahead, v_behind, gap_ahead, gap_behind), (ids[0], ids[1])

    def _crossing_features(
        self, coords: np.ndarray, speeds: np.ndarray, index: int
    ) -> tuple[tuple[float, float, float], tuple[int, int]]:
        """``(d_cross, d_conflict, v_conflict)`` of vehicle ``index`` of the road and the ids of
        its crossing branch and conflicting vehicle (``-1``: nobody within 75 m).

        Args:
            coords: ``[V]`` route coordinates of the road's vehicles [m].
            speeds: ``[V]`` their speeds [m/s].
            index: the CAV's index among the road's vehicles.
        """
        period, crossings = self.road.period, self.geometry.crossing_coordinates
        ahead = (crossings - coords[index] + CROSSING_CLEAR) % period - CROSSING_CLEAR  # [2]
        branch = int(np.argmin(ahead))
        d_cross = float(min(ahead[branch], GAP_RANGE))
        others = (crossings[1 - branch] - coords + CROSSING_CLEAR) % period - CROSSING_CLEAR
        others[index] = np.inf
        nearest = int(np.argmin(others))
        if others[nearest] > GAP_RANGE:
            return (d_cross, GAP_RANGE, 0.0), (branch, -1)
        vehicle = id(self.road.vehicles[nearest])
        return (d_cross, float(others[nearest]), float(speeds[nearest])), (branch, vehicle)

    def _lane_features(
        self, cav: TargetSpeedVehicle
    ) -> tuple[tuple[float, float, float, float, float], tuple[int, int]]:
        """``(lane, v_ahead_other, v_behind_other, gap_ahead_other, gap_behind_other)`` of
        ``cav`` on two lanes and the ids of its leader and follower in the other lane."""
        _from, _to, lane = cav.lane_index
        _s, lateral = cav.lane.local_coordinates(cav.position)
        position = lane + lateral / self.geometry.lane_width
        features, ids = self._neighbour_features(cav, (_from, _to, 1 - lane))
        return (position, *features), ids

    def observe_agents(self) -> np.ndarray:
        """Per-CAV observations ``[I, obs_dim]`` (zero rows for crashed CAVs).

        Also records the observed vehicles' ids ``[I, K]`` (``-1``: nobody) for
        ``neighbour_changed``: columns leader, follower, then with the crossing features the
        crossing branch and the conflicting vehicle, then on two lanes the other lane's leader
        and follower.
        """
        crossing = self.config["observation"] == "crossing"
        two_lanes = self.obs_dim == TWO_LANE_OBS_DIM
        obs = np.zeros((len(self.cavs), self.obs_dim), dtype=np.float32)
        ids = np.full((len(self.cavs), 2 + 2 * crossing + 2 * two_lanes), -1, dtype=np.int64)
        if crossing:
            vehicles = self.road.vehicles
            coords = np.array([self.road.route_coordinate(v) for v in vehicles])
            speeds = np.array([v.speed for v in vehicles])
            road_index = {id(v): k for k, v in enumerate(vehicles)}
        for i, cav in enumerate(self.cavs):
            if self.alive[i]:
                features, ids[i, :2] = self._neighbour_features(cav)
                row = [cav.speed, *cav.position, *features]
                if crossing:
                    cross, ids[i, 2:4] = self._crossing_features(
                        coords, speeds, road_index[id(cav)]
                    )
                    row.extend(cross)
                if two_lanes:
                    lane, ids[i, 4:] = self._lane_features(cav)
                    row.extend(lane)
                obs[i] = row
        self._observed_ids = ids
        return obs

    def _info(self, obs: np.ndarray, action: Any = None) -> dict:
        """Adds ``neighbour_changed`` ``[I]``: observed neighbours changed identity (see the
        module docstring); ``False`` at reset and for CAVs that are no longer driving."""
        info = super()._info(obs, action)
        current, previous = self._observed_ids, self._previous_ids
        changed = np.zeros(len(self.cavs), dtype=bool)
        if previous is not None and current is not None:
            changed = (current != previous).any(axis=1) & self.alive
        self._previous_ids = current
        info["neighbour_changed"] = changed
        info["neighbour_cav"] = self._neighbour_cavs(current)
        return info

    def _neighbour_cavs(self, ids: np.ndarray | None) -> np.ndarray:
        """``[I, K]`` agent index of the CAV in each observed vehicle slot (``-1``: a human
        driver, nobody in range, or a CAV that no longer drives); see the module docstring."""
        slots = NEIGHBOUR_SLOTS[self.obs_dim]
        out = np.full((len(self.cavs), len(slots)), -1, dtype=np.int64)
        if ids is None:
            return out
        index = {id(cav): i for i, cav in enumerate(self.cavs) if self.alive[i]}
        for k, (column, _speed) in enumerate(slots):
            out[:, k] = [index.get(int(v), -1) for v in ids[:, column]]
        return out

    def agent_rewards(self, obs: np.ndarray, action: Any) -> np.ndarray:
        """Paper eq. (26) on the observation ``obs``, ``beta`` for CAVs that crashed this step."""
        rewards = obs[:, 0] + obs[:, 3] + obs[:, 4]
        rewards = rewards + self.config["collision_reward"] * self._crashed_now
        return (rewards * (self.alive | self._crashed_now)).astype(np.float32)

    def episode_metrics(self) -> dict[str, float]:
        """Agility and safety (paper eqs. 27-28) and mean speed of the episode so far."""
        distances = np.stack(self._episode_distances, axis=0) if self._episode_distances else None
        horizon = self.config["horizon"]
        steps = max(len(self._episode_distances), 1)
        collision_steps = np.where(self.alive, horizon, self.collision_step - 1)
        return {
            "agility": float(agility(distances, collision_steps)) if distances is not None else 0.0,
            "safety": float(safety(collision_steps, horizon)),
            "collisions": int((~self.alive).sum()),
            "mean_speed": float(
                np.stack(self._episode_distances).sum() / steps / self.dt / len(self.cavs)
            )
            if distances is not None
            else 0.0,
        }

    # --- scripted policy ---------------------------------------------------------------------
    def scripted_action(self) -> np.ndarray:
        """A crash-free scripted CAV action ``[I, act_dim]``: IDM + the crossing rule.

        Each CAV drives like a human-driven vehicle (IDM towards ``max_speed`` and first come,
        first served at the crossing) and outputs the target speed that makes its speed
        controller produce that acceleration. Never changes lanes.
        """
        action = np.zeros(self.action_space.shape, dtype=np.float32)
        for i, cav in enumerate(self.cavs):
            if not self.alive[i]:
                continue
            front, _ = self.road.neighbour_vehicles(cav)
            distance = self.road.longitudinal_distance(cav, front) if front else None
            if distance is not None and distance < 0:
                distance += self.road.period
            acc = idm_acceleration(
                cav.speed,
                self.config["max_speed"],
                distance,
                front.speed if front else 0.0,
            )
            stop = self.road.stop_distance(cav)
            if stop is not None:
                acc = min(acc, idm_acceleration(cav.speed, self.config["max_speed"], stop))
            target = cav.speed + acc / cav.KP_A
            action[i, 0] = clip(target, 0.0, self.config["max_speed"])
        return action


NEIGHBOUR_SLOTS = {
    OBS_DIM: ((0, 3), (1, 4)),
    CROSSING_OBS_DIM: ((0, 3), (1, 4), (3, 9)),
    TWO_LANE_OBS_DIM: ((0, 3), (1, 4), (3, 9), (4, 11), (5, 12)),
}
"""Per observation size, the observed vehicles in the order of ``info["neighbour_cav"]``: the
column of each one's id among ``observe_agents``' ids and the observation column of its speed
(leader, follower, with the crossing features the conflicting vehicle, on two lanes the other
lane's leader and follower)."""


def neighbour_speed_columns(obs_dim: int) -> tuple[int, ...]:
    """The observation columns holding the speeds of the observed vehicles, in the order of
    ``info["neighbour_cav"]``: ``v_ahead``, ``v_behind``, with the crossing features
    ``v_conflict``, on two lanes ``v_ahead_other`` and ``v_behind_other``."""
    if obs_dim not in OBSERVATION_SIZES:
        raise ValueError(f"obs_dim must be one of {list(OBSERVATION_SIZES)}, got {obs_dim}")
    return tuple(speed for _id, speed in NEIGHBOUR_SLOTS[obs_dim])


def observation_size(observation: str, lanes: int) -> int:
    """Size of the figure-eight's observation option ``observation`` on ``lanes`` lanes."""
    if observation == "crossing" and lanes == 2:
        return TWO_LANE_OBS_DIM
    return OBSERVATIONS[observation]


def figure_eight_observation_bounds(
    env_config: Mapping[str, Any] | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Per-feature bounds ``(low, high)``, each ``[7]``, ``[10]`` or ``[15]``, of the
    figure-eight's observation under ``env_config`` (the env's defaults for keys not given: pass
    a scenario's own defaults too, e.g. ``lanes=2`` for ``figure-eight-multilane``): speeds in
    ``[0, v_max]`` with ``v_max`` the larger of ``max_speed`` and the human drivers' top target
    speed, the position inside the loop's bounding box (lobe radius plus the lanes' width), gaps
    in ``[0, 75]`` m, crossing distances in ``[-5, 75]`` m, the lane position in ``[-0.5, 1.5]``
    lane widths. Tile coding (:class:`~mapets_rl.modules.TileCoder`) covers this box."""
    config = {**FigureEightEnv.default_config(), **dict(env_config or {})}
    hv = config["hv_target_speed"]
    v_max = float(max(config["max_speed"], *(hv if isinstance(hv, (tuple, list)) else [hv])))
    geometry = FigureEightGeometry(config["length"], config["lanes"])
    margin = geometry.radius + config["lanes"] * geometry.lane_width
    x_max = math.sqrt(2.0) * geometry.radius + margin
    low = [0.0, -x_max, -margin, 0.0, 0.0, 0.0, 0.0]
    high = [v_max, x_max, margin, v_max, v_max, GAP_RANGE, GAP_RANGE]
    if config["observation"] == "crossing":
        low += [-CROSSING_CLEAR, -CROSSING_CLEAR, 0.0]
        high += [GAP_RANGE, GAP_RANGE, v_max]
    if observation_size(config["observation"], config["lanes"]) == TWO_LANE_OBS_DIM:
        low += [-0.5, 0.0, 0.0, 0.0, 0.0]
        high += [1.5, v_max, v_max, GAP_RANGE, GAP_RANGE]
    return np.array(low, dtype=np.float32), np.array(high, dtype=np.float32)


@dataclasses.dataclass(frozen=True)
class FigureEightPlannerReward(PlannerReward):
    """The figure-eight scenarios' planner reward (paper eq. 26) and predicted collision, the
    margins and penalty they use declared once (the registry's ``planner_reward`` of
    ``figure-eight`` and ``figure-eight-multilane``; MA-PETS' ``planner_reward`` section).

    A collision is predicted when the (predicted) gap ahead falls below ``collision_gap``
    metres or closes while below ``collision_gap + headway * v`` (``v`` the CAV's predicted
    speed; a CAV inside that margin that opens the gap, e.g. after a cut-in, is not stopped),
    or, with the crossing features (10 or 15 features), when the CAV and the first
    conflicting vehicle of the other branch are both within ``crossing_gap`` metres of the
    crossing point and neither has cleared it (``> -5`` m), or, with the two-lane features (15),
    when the action requests a lane change (flag ``> 0.5``) while the gap ahead or behind in the
    other lane is below ``lane_change_gap`` metres plus what that gap closes in
    ``lane_change_time`` seconds at the current speed difference (a lane change takes about
    2 s, in which the CAV shares both lanes; tested only while the CAV is settled in its lane,
    the only time a request starts a change). The gap behind in the own lane is not tested: a
    CAV cannot avoid a follower by speeding into its leader. The margins let a 0.1 s step
    resolve an approach (a CAV at 13.89 m/s covers 1.4 m per step).

    Attributes:
        collision_gap: margin on the gap ahead [m] (>= 0).
        crossing_gap: half-width of the conflict zone around the crossing point [m] (>= 0).
        headway: time headway added to the margin ahead [s] (in [0, 10]; 0: the fixed margin
            of earlier versions). 0.5 s keeps the room to react to a braking leader that a
            constant-speed prediction does not see (``benchmarks/multilane_diagnosis.py``).
        lane_change_gap: margin on the other lane's gaps ahead and behind for a lane change
            [m] (>= 0).
        lane_change_time: seconds of closing speed added to the lane-change margins (in
            [0, 10]; 0: a fixed margin): ``max(0, v - v_ahead)`` ahead, ``max(0, v_behind -
            v)`` behind. 1 s: on the two-lane figure-eight's diagnosis
            (``benchmarks/multilane_diagnosis.py``) it cut the oracle planner's crashes from
            2.0 to 0.7 per episode (6 seeds) and a trained MA-PETS planner's from 4.0 to 2.0
            (3 seeds).
        collision_reward: the reward ``beta`` of a predicted collision (paper eq. 26: -10;
            <= 0). A predicted collision also ends the particle's trajectory (no reward after
            it, :attr:`termination_fn`), so the paper's -10 suffices.
        brake_when_lost: a CAV whose gap ahead already fails the gap test (:meth:`lost`)
            brakes (target speed 0) and keeps its lane instead of the planner's action
            (:attr:`fallback`; default off, the paper's planner). From there every plan is
            predicted to crash at its first step (that step's closing does not depend on the
            action), so all plans score alike and the planner's choice is arbitrary; on two
            lanes such choices (accelerating into the leader, changing lanes into 0-2 m gaps)
            were most of the lane-change crashes below the 0.5 s headway
            (``docs/results/history.md``, "What the lane-change crashes are").
    """

    collision_gap: float = dataclasses.field(default=2.0, metadata={"unit": "m"})
    crossing_gap: float = dataclasses.field(default=6.0, metadata={"unit": "m"})
    headway: float = dataclasses.field(default=0.5, metadata={"unit": "s"})
    lane_change_gap: float = dataclasses.field(default=8.0, metadata={"unit": "m"})
    lane_change_time: float = dataclasses.field(default=1.0, metadata={"unit": "s"})
    collision_reward: float = COLLISION_REWARD
    brake_when_lost: bool = False

    def __post_init__(self) -> None:
        super().__post_init__()
        for name in ("collision_gap", "crossing_gap", "lane_change_gap"):
            check(getattr(self, name) >= 0, name, ">= 0 metres", getattr(self, name))
        for name in ("headway", "lane_change_time"):
            check(0 <= getattr(self, name) <= 10, name, "in [0, 10] seconds", getattr(self, name))
        check(self.collision_reward <= 0, "collision_reward", "<= 0", self.collision_reward)

    def collision(
        self, obs: torch.Tensor, action: torch.Tensor | None, next_obs: torch.Tensor
    ) -> torch.Tensor:
        """Predicted collision of a figure-eight CAV, vectorised (the planner's termination).

        Args:
            obs: ``[..., 7, 10 or 15]`` current observation (read for the lane-change test
                only).
            action: ``[..., act_dim]`` action (its lane-change flag, ``act_dim = 2``, is read
                with the two-lane observation), or None.
            next_obs: ``[..., 7, 10 or 15]`` (predicted) next observation.

        Returns:
            ``[...]`` bool.
        """
        gap = next_obs[..., 5]
        collided = self.gap_fails(gap, next_obs[..., 0], gap < obs[..., 5])
        if next_obs.shape[-1] in (CROSSING_OBS_DIM, TWO_LANE_OBS_DIM):
            near = next_obs[..., 7:9]
            inside = (near < self.crossing_gap) & (near > -CROSSING_CLEAR)
            collided = collided | inside.all(-1)
        if obs.shape[-1] == TWO_LANE_OBS_DIM and action is not None and action.shape[-1] == 2:
            settled = (obs[..., 10] - obs[..., 10].round()).abs() <= SETTLED_LANE_POSITION
            changing = (action[..., 1] > LANE_CHANGE_THRESHOLD) & settled
            closing = torch.stack([obs[..., 0] - obs[..., 11], obs[..., 12] - obs[..., 0]], -1)
            margin = self.lane_change_gap + self.lane_change_time * closing.clamp_min(0.0)
            short = (obs[..., 13:15] < margin).any(-1)
            collided = collided | (changing & short)
        return collided

    def reward(
        self, obs: torch.Tensor, action: torch.Tensor | None, next_obs: torch.Tensor
    ) -> torch.Tensor:
        """Known figure-eight reward for planning (paper eq. 26), vectorised:
        ``r = v' + v_ahead' + v_behind' + beta`` on the (predicted) next observation, with
        ``beta = collision_reward`` where :meth:`collision` predicts a collision (shapes as
        there; returns ``[...]`` rewards)."""
        speed_terms = next_obs[..., 0] + next_obs[..., 3] + next_obs[..., 4]
        collided = self.collision(obs, action, next_obs)
        return speed_terms + self.collision_reward * collided.to(speed_terms.dtype)

    @property
    def termination_fn(
        self,
    ) -> Callable[[torch.Tensor, torch.Tensor, torch.Tensor], torch.Tensor]:
        """:meth:`collision`: a predicted crash ends the particle's trajectory."""
        return self.collision

    def gap_fails(
        self, gap: torch.Tensor, speed: torch.Tensor, closing: torch.Tensor
    ) -> torch.Tensor:
        """The gap test of :meth:`collision`, ``[...]`` bool: ``gap`` ahead below
        ``collision_gap``, or below ``collision_gap + headway * speed`` while ``closing``."""
        margin = self.collision_gap + self.headway * speed
        return (gap < self.collision_gap) | ((gap < margin) & closing)

    def lost(self, obs: torch.Tensor) -> torch.Tensor:
        """``[...]`` bool: the gap ahead of ``obs [..., S]`` already fails the gap test
        (:meth:`gap_fails`, closing: faster than the leader): every plan is predicted to crash
        at its first step."""
        return self.gap_fails(obs[..., 5], obs[..., 0], obs[..., 0] > obs[..., 3])

    def brake_if_lost(self, obs: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        """``action [..., A]`` with the rows of :meth:`lost` CAVs set to 0: target speed 0 and,
        on two lanes, no lane-change request."""
        return torch.where(self.lost(obs).unsqueeze(-1), torch.zeros_like(action), action)

    @property
    def fallback(self) -> Callable[[torch.Tensor, torch.Tensor], torch.Tensor] | None:
        """:meth:`brake_if_lost` with ``brake_when_lost``, else ``None``."""
        return self.brake_if_lost if self.brake_when_lost else None
