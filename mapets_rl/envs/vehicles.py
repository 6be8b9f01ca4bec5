"""Vehicles of the traffic scenarios, built on highway-env's vehicle classes.

- ``RouteVehicleMixin``: longitudinal distances along the road's route coordinate (correct across
  segment boundaries and around a loop), lane tracking restricted to the current and next
  segment when the road provides them (stock tracking tests every lane of the network and, at
  the figure-eight crossing, must rely on the heading penalty alone), and speeds bounded below
  by ``MIN_SPEED = 0`` within every integration step (stock highway-env clips the acceleration
  only once the speed is already below the minimum, so braking vehicles roll backwards).
- ``FastIDMVehicle``: highway-env's IDM/MOBIL driver whose per-step control (IDM acceleration,
  desired gap, steering, kinematics) is plain float math: the stock methods apply NumPy ufuncs
  (``np.clip``, ``np.arcsin``, ``np.dot`` on 2-vectors) to scalars, whose call overhead was ~14%
  of an env step. The overrides compute the same expressions in the same order and give the same
  numbers (``tests/envs/test_envs.py`` compares them with the stock methods).
- ``HumanVehicle``: highway-env IDM/MOBIL driver that additionally obeys a crossing rule (it
  brakes for a virtual stop line when the road says it must yield).
- ``TargetSpeedVehicle``: a CAV whose action is a target speed (plus an optional lane change),
  tracked by a proportional controller with physically bounded acceleration.
"""

from __future__ import annotations

import contextlib
import math
from collections.abc import Iterator

import numpy as np
from highway_env import utils
from highway_env.road.lane import CircularLane, StraightLane
from highway_env.road.road import LaneIndex
from highway_env.vehicle.behavior import IDMVehicle
from highway_env.vehicle.controller import ControlledVehicle
from highway_env.vehicle.kinematics import Vehicle

from mapets_rl.envs.lanes import FastCircularLane, FastStraightLane

ACC_MIN = -6.0
"""Maximum braking of every vehicle [m/s^2] (highway-env's IDM ``ACC_MAX`` is 6)."""
ACC_MAX = 3.0
"""Maximum acceleration of a CAV [m/s^2] (IDM comfortable acceleration)."""


def clip(value: float, low: float, high: float) -> float:
    """``np.clip`` for one float (NaN stays NaN): ``min(max(value, low), high)``."""
    return min(max(value, low), high)


def idm_acceleration(
    speed: float,
    target_speed: float,
    distance: float | None = None,
    front_speed: float = 0.0,
    params: type[IDMVehicle] | IDMVehicle = IDMVehicle,
) -> float:
    """Intelligent Driver Model acceleration [m/s^2], as in ``IDMVehicle.acceleration``.

    Args:
        speed: own speed [m/s].
        target_speed: desired free-road speed [m/s].
        distance: centre-to-centre distance to the obstacle ahead [m], ``None`` if free road.
        front_speed: speed of the obstacle ahead [m/s] (0 for a standing one).
        params: object or class carrying the IDM constants (``COMFORT_ACC_MAX``, ``DELTA``, ...).
    """
    v = max(speed, 0.0)
    acceleration = params.COMFORT_ACC_MAX * (
        1.0 - (v / abs(utils.not_zero(target_speed))) ** params.DELTA
    )
    if distance is not None:
        ab = -params.COMFORT_ACC_MAX * params.COMFORT_ACC_MIN
        desired = (
            params.DISTANCE_WANTED
            + v * params.TIME_WANTED
            + v * (v - front_speed) / (2 * math.sqrt(ab))
        )
        acceleration -= (
            params.COMFORT_ACC_MAX * (desired / utils.not_zero(max(distance, 1e-3))) ** 2
        )
    return float(acceleration)


def idm_stop_acceleration(vehicle: IDMVehicle, distance: float) -> float:
    """IDM acceleration of ``vehicle`` towards a standing obstacle ``distance`` metres ahead."""
    return idm_acceleration(vehicle.speed, vehicle.target_speed, distance, 0.0, vehicle)


class RouteVehicleMixin:
    """Route-coordinate distances and segment-local lane tracking (see module docstring)."""

    road: object
    MIN_SPEED = 0.0

    def step(self, dt: float) -> None:
        """Integrate one step of ``dt`` seconds with the braking limited so that the speed
        ends at ``MIN_SPEED`` or above (vehicles never roll backwards)."""
        floor = (self.MIN_SPEED - self.speed) / dt
        if not self.crashed and self.action["acceleration"] < floor:
            self.action["acceleration"] = floor
        self.integrate(dt)

    def integrate(self, dt: float) -> None:
        """``Vehicle.step`` (kinematic bicycle model, then lane tracking) in float math."""
        self.clip_actions()
        beta = math.atan(1 / 2 * math.tan(self.action["steering"]))
        speed, angle = self.speed, self.heading + beta
        self.position += (speed * math.cos(angle) * dt, speed * math.sin(angle) * dt)
        if self.impact is not None:
            self.position += self.impact
            self.crashed = True
            self.impact = None
        self.heading += speed * math.sin(beta) / (self.LENGTH / 2) * dt
        self.speed += self.action["acceleration"] * dt
        self.on_state_update()

    def steering_control(self, target_lane_index: LaneIndex) -> float:
        """``ControlledVehicle.steering_control`` in float math: steering angle [rad] that
        follows the centre of lane ``target_lane_index``."""
        target_lane = self.road.network.get_lane(target_lane_index)
        longitudinal, lateral = target_lane.local_coordinates(self.position)
        future_heading = target_lane.heading_at(longitudinal + self.speed * self.TAU_PURSUIT)
        lateral_speed_command = -self.KP_LATERAL * lateral
        heading_command = math.asin(clip(lateral_speed_command / utils.not_zero(self.speed), -1, 1))
        heading_ref = future_heading + clip(heading_command, -math.pi / 4, math.pi / 4)
        heading_rate_command = self.KP_HEADING * utils.wrap_to_pi(heading_ref - self.heading)
        slip_angle = math.asin(
            clip(self.LENGTH / 2 / utils.not_zero(self.speed) * heading_rate_command, -1, 1)
        )
        steering_angle = math.atan(2 * math.tan(slip_angle))
        return float(clip(steering_angle, -self.MAX_STEERING_ANGLE, self.MAX_STEERING_ANGLE))

    def lane_distance_to(self, other: Vehicle, lane: object = None) -> float:
        if other is None:
            return np.nan
        return self.road.longitudinal_distance(self, other)

    def on_state_update(self) -> None:
        candidates = getattr(self.road, "candidate_lanes", None)
        stock = getattr(self.road, "stock_neighbour_search", True)
        if candidates is None or self.lane_index is None or stock:
            super().on_state_update()
            return
        # Search the candidate lanes only once the vehicle leaves the middle of its lane.
        s, lateral = self.lane.local_coordinates(self.position)
        if not (0.0 <= s <= self.lane.length and abs(lateral) <= 0.25 * self.lane.width_at(s)):
            indexes = candidates(self.lane_index)
            network = self.road.network
            distances = [
                network.get_lane(index).distance_with_heading(self.position, self.heading)
                for index in indexes
            ]
            self.lane_index = indexes[int(np.argmin(distances))]
            self.lane = network.get_lane(self.lane_index)
        if self.road.record_history:
            self.history.appendleft(self.create_from(self))


class FastIDMVehicle(RouteVehicleMixin, IDMVehicle):
    """highway-env's ``IDMVehicle`` (IDM + MOBIL) with its per-step control in float math."""

    def integrate(self, dt: float) -> None:
        """``IDMVehicle.step``: advance the lane-change timer, then the kinematics."""
        self.timer += dt
        super().integrate(dt)

    def act(self, action: dict | str | None = None) -> None:
        """``IDMVehicle.act``: MOBIL lane decision, lane-following steering, IDM acceleration
        (the lower of the current and the target lane's while changing lanes)."""
        if self.crashed:
            return
        self.follow_road()
        if self.enable_lane_change:
            self.change_lane_policy()
        steering = clip(
            self.steering_control(self.target_lane_index),
            -self.MAX_STEERING_ANGLE,
            self.MAX_STEERING_ANGLE,
        )
        front_vehicle, rear_vehicle = self.road.neighbour_vehicles(self, self.lane_index)
        acceleration = self.acceleration(self, front_vehicle, rear_vehicle)
        if self.lane_index != self.target_lane_index:
            front_vehicle, rear_vehicle = self.road.neighbour_vehicles(self, self.target_lane_index)
            acceleration = min(acceleration, self.acceleration(self, front_vehicle, rear_vehicle))
        acceleration = clip(acceleration, -self.ACC_MAX, self.ACC_MAX)
        Vehicle.act(self, {"steering": steering, "acceleration": acceleration})

    def acceleration(
        self,
        ego_vehicle: ControlledVehicle,
        front_vehicle: Vehicle | None = None,
        rear_vehicle: Vehicle | None = None,
    ) -> float:
        """``IDMVehicle.acceleration``: IDM acceleration [m/s^2] of ``ego_vehicle``."""
        if not ego_vehicle or not isinstance(ego_vehicle, Vehicle):
            return 0
        ego_target_speed = getattr(ego_vehicle, "target_speed", 0)
        if ego_vehicle.lane and ego_vehicle.lane.speed_limit is not None:
            ego_target_speed = clip(ego_target_speed, 0, ego_vehicle.lane.speed_limit)
        ratio = max(ego_vehicle.speed, 0) / abs(utils.not_zero(ego_target_speed))
        acceleration = self.COMFORT_ACC_MAX * (1 - ratio**self.DELTA)
        if front_vehicle:
            d = ego_vehicle.lane_distance_to(front_vehicle)
            gap = self.desired_gap(ego_vehicle, front_vehicle) / utils.not_zero(d)
            acceleration -= self.COMFORT_ACC_MAX * (gap * gap)
        return acceleration

    def desired_gap(
        self, ego_vehicle: Vehicle, front_vehicle: Vehicle | None = None, projected: bool = True
    ) -> float:
        """``IDMVehicle.desired_gap``: IDM desired distance [m] to ``front_vehicle``."""
        ab = -self.COMFORT_ACC_MAX * self.COMFORT_ACC_MIN
        speed = ego_vehicle.speed
        if projected:
            cos, sin = math.cos(ego_vehicle.heading), math.sin(ego_vehicle.heading)
            front_speed = front_vehicle.speed
            dv = (speed * cos - front_speed * math.cos(front_vehicle.heading)) * cos + (
                speed * sin - front_speed * math.sin(front_vehicle.heading)
            ) * sin
        else:
            dv = speed - front_vehicle.speed
        return self.DISTANCE_WANTED + speed * self.TIME_WANTED + speed * dv / (2 * math.sqrt(ab))


class HumanVehicle(FastIDMVehicle):
    """A human-driven vehicle: highway-env IDM + MOBIL, plus a crossing rule.

    The road (``stop_distance(vehicle)``) tells each vehicle, once per simulation step, the
    distance to the stop line it must not pass (``None`` when it has right of way); the vehicle
    then brakes as IDM would for a standing car there.
    """

    ACC_MAX = -ACC_MIN

    def act(self, action: dict | str | None = None) -> None:
        if self.crashed:
            return
        super().act()
        stop_distance = getattr(self.road, "stop_distance", None)
        distance = stop_distance(self) if stop_distance is not None else None
        if distance is not None:
            acceleration = min(self.action["acceleration"], idm_stop_acceleration(self, distance))
            self.action["acceleration"] = max(acceleration, -self.ACC_MAX)


class TargetSpeedVehicle(RouteVehicleMixin, ControlledVehicle):
    """A connected autonomous vehicle driven by a target speed (and lane-change requests).

    Every simulation step it follows its lane (highway-env steering control) and accelerates by
    ``KP_A * (target_speed - speed)`` clipped to ``[ACC_MIN, ACC_MAX]``; the stock
    ``ControlledVehicle.speed_control`` has no such physical bound.
    """

    ACC_MIN = ACC_MIN
    ACC_MAX = ACC_MAX

    def act(self, action: dict | str | None = None) -> None:
        if self.crashed:
            return
        self.follow_road()
        acceleration = self.KP_A * (self.target_speed - self.speed)
        steering = float(self.steering_control(self.target_lane_index))
        limit = self.MAX_STEERING_ANGLE
        Vehicle.act(
            self,
            {
                "steering": min(max(steering, -limit), limit),
                "acceleration": min(max(float(acceleration), self.ACC_MIN), self.ACC_MAX),
            },
        )

    SETTLED = 0.5
    """A lane change can start only within this many metres of the lane's centre [m]."""

    def request_lane_change(self, lane_index: LaneIndex) -> None:
        """Start a lane change to ``lane_index`` unless one is under way: the vehicle must be
        on its target lane and within ``SETTLED`` metres of its centre (once its lane index
        has switched halfway through a change, a request does not turn it back)."""
        if self.lane_index != self.target_lane_index:
            return
        _s, lateral = self.lane.local_coordinates(self.position)
        if abs(lateral) <= self.SETTLED:
            self.target_lane_index = lane_index


STOCK_METHODS: tuple[tuple[type, str, object], ...] = (
    (RouteVehicleMixin, "steering_control", ControlledVehicle.steering_control),
    (RouteVehicleMixin, "integrate", Vehicle.step),
    (FastIDMVehicle, "integrate", IDMVehicle.step),
    (FastIDMVehicle, "act", IDMVehicle.act),
    (FastIDMVehicle, "acceleration", IDMVehicle.acceleration),
    (FastIDMVehicle, "desired_gap", IDMVehicle.desired_gap),
    (FastStraightLane, "local_coordinates", StraightLane.local_coordinates),
    (FastCircularLane, "local_coordinates", CircularLane.local_coordinates),
    (FastCircularLane, "heading_at", CircularLane.heading_at),
)
"""(class, method name, the highway-env method our float-math override replaces)."""


@contextlib.contextmanager
def stock_control() -> Iterator[None]:
    """Inside the block, highway-env's own methods replace the float-math overrides (the
    reference of ``tests/envs/test_envs.py`` and ``benchmarks/env_throughput.py``); not
    thread-safe."""
    saved = [(cls, name, cls.__dict__[name]) for cls, name, _ in STOCK_METHODS]
    try:
        for cls, name, stock in STOCK_METHODS:
            setattr(cls, name, stock)
        yield
    finally:
        for cls, name, ours in saved:
            setattr(cls, name, ours)
