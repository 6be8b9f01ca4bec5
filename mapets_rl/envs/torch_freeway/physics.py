"""One simulation step of every road: highway-env's ``Road.act`` then ``Road.step``, in tensors.

:class:`RoadPhysics` holds what does not change during an episode (the lanes, the bodies'
sizes, the constants of the config) and :meth:`RoadPhysics.substep` advances the bodies of all
roads by one simulation step: every driving vehicle decides (``follow_road``, MOBIL and its
abort rule, the lateral controller, IDM in its current and target lanes, or the emergency stop
of a CAV under ES), every vehicle moves (kinematic bicycle model, lane assignment), and
rectangles that touch crash. The step is a pure function of a dict of ``[B, N]`` tensors (no
data-dependent shapes), so :class:`~mapets_rl.envs.torch_freeway.simulator.BatchedFreeway` can
hand it to ``torch.compile``, which fuses its few hundred elementwise ops into a few loops.

Where it departs from highway-env (measured in ``benchmarks/RESULTS.md``):

- highway-env's vehicles act one after the other; a vehicle's abort of a lane change reads the
  targets of the vehicles before it *after* their decision in the same step and those after it
  *before* theirs. Reproduced, except that the earlier vehicles' own aborts in that step are
  not seen (a second-order effect).
- collisions are tested for each vehicle against its leader in its lane and the leaders and
  followers in the lanes beside it, not against every body on the road: two bodies further
  apart cannot touch (lanes are 4 m wide, vehicles 2 m).
- on the slanted ramp lane, torch's vectorised ``sin``/``cos`` differ from libm's in the last
  bit; these differences can grow over an episode where a decision sits on a threshold.
"""

from __future__ import annotations

import torch
from highway_env.vehicle.behavior import IDMVehicle
from highway_env.vehicle.objects import Obstacle

from mapets_rl.envs.freeway import ES
from mapets_rl.envs.torch_freeway.dynamics import (
    DISTANCE_WANTED,
    LENGTH,
    SQRT_AB,
    TIME_WANTED,
    WIDTH,
    NeighbourTables,
    idm_acceleration,
    integrate,
    rectangle_collisions,
    steering_control,
)
from mapets_rl.envs.torch_freeway.geometry import LANE_WIDTH, VEHICLE_LENGTH, FreewayGeometry
from mapets_rl.envs.vehicles import ACC_MIN

ACC_MAX = IDMVehicle.ACC_MAX
"""Largest |acceleration| of an IDM driver [m/s^2] (highway-env ``IDMVehicle.ACC_MAX``)."""
LANE_CHANGE_DELAY = IDMVehicle.LANE_CHANGE_DELAY
MIN_ACC_GAIN = IDMVehicle.LANE_CHANGE_MIN_ACC_GAIN
MAX_BRAKING_IMPOSED = IDMVehicle.LANE_CHANGE_MAX_BRAKING_IMPOSED
if IDMVehicle.POLITENESS != 0:  # MOBIL's follower terms are dropped below because they weigh 0
    raise ImportError("the batched freeway assumes highway-env's MOBIL politeness of 0")

Bodies = dict[str, torch.Tensor]
"""The bodies of all roads: ``[B, N]`` tensors by name (see ``BatchedFreeway``)."""


class RoadPhysics:
    """The fixed part of ``B`` roads of ``N`` bodies (the last one the obstacle on
    ``freeway-merge``) and their simulation step.

    Args:
        geometry: the lanes.
        n_vehicles: vehicles per road (bodies ``0 .. n_vehicles - 1``).
        n_bodies: ``n_vehicles`` plus the obstacle, if any.
        speed_limit: every lane's limit and every vehicle's ``MAX_SPEED`` [m/s].
        dt: simulation step [s].
    """

    def __init__(
        self,
        geometry: FreewayGeometry,
        n_vehicles: int,
        n_bodies: int,
        speed_limit: float,
        dt: float,
    ) -> None:
        self.geometry = geometry
        self.speed_limit = speed_limit
        self.dt = dt
        self.merge = geometry.merge
        device, dtype = geometry.length.device, geometry.length.dtype
        self.body_index = torch.arange(n_bodies, device=device)
        self.is_obstacle = self.body_index >= n_vehicles
        self.body_length = torch.where(self.is_obstacle, Obstacle.LENGTH, LENGTH).to(dtype)
        self.body_width = torch.where(self.is_obstacle, Obstacle.WIDTH, WIDTH).to(dtype)
        self.sides = torch.tensor([-1, 0, 1], device=device)

    # --- neighbour search ----------------------------------------------------------------------
    def tables(self, b: Bodies) -> NeighbourTables:
        """The sorted lane tables of every road's bodies on the road now."""
        return NeighbourTables.build(self.geometry.table[b["lane"]], b["x"], b["present"])

    def neighbours(self, b: Bodies, tables: NeighbourTables) -> tuple[torch.Tensor, torch.Tensor]:
        """Leader and follower ``[B, N, 3]`` of every body in the lane tables left of, equal to
        and right of its own (``-1``: none)."""
        own = self.geometry.table[b["lane"]]
        rows, n = own.shape
        query = (own.unsqueeze(-1) + self.sides).reshape(rows, -1)
        x = b["x"].unsqueeze(-1).expand(rows, n, 3).reshape(rows, -1)
        body = self.body_index.view(1, n, 1).expand(rows, n, 3).reshape(rows, -1)
        front, rear = tables.search(query, x, body)
        return front.view(rows, n, 3), rear.view(rows, n, 3)

    @staticmethod
    def gather(value: torch.Tensor, index: torch.Tensor) -> torch.Tensor:
        """``value [B, N]`` at body indices ``index [B, ...]`` (``-1`` reads body 0)."""
        flat = index.clamp(min=0).reshape(index.shape[0], -1)
        return value.gather(1, flat).view(index.shape)

    def idm(self, b: Bodies, ego: torch.Tensor, front: torch.Tensor, delta: torch.Tensor):
        """IDM acceleration ``[B, ...]`` of bodies ``ego`` behind bodies ``front`` (``-1``:
        none), with the deciding vehicles' exponent ``delta``; 0 where ``ego`` is none or the
        obstacle."""
        gather = self.gather
        has_front = front >= 0
        acc = idm_acceleration(
            gather(b["speed"], ego),
            gather(b["target_speed"], ego),
            gather(b["heading"], ego),
            delta,
            self.speed_limit,
            has_front,
            gather(b["x"], front) - gather(b["x"], ego),
            torch.where(has_front, gather(b["speed"], front), 0.0),
            torch.where(has_front, gather(b["heading"], front), 0.0),
        )
        is_vehicle = (ego >= 0) & ~self.is_obstacle[ego.clamp(min=0)]
        return torch.where(is_vehicle, acc, 0.0)

    # --- the step ------------------------------------------------------------------------------
    def substep(
        self, b: Bodies, key: torch.Tensor, order: torch.Tensor
    ) -> tuple[Bodies, torch.Tensor, torch.Tensor]:
        """One simulation step of every road from bodies ``b`` and their lane tables
        ``(key, order)`` (:class:`NeighbourTables`); returns the new bodies and tables."""
        b = self.act(b, NeighbourTables(key, order))
        b = self.move(b)
        tables = self.tables(b)
        b = self.collide(b, tables)
        return b, tables.key, tables.order

    def act(self, b: Bodies, tables: NeighbourTables) -> Bodies:
        """Every driving vehicle decides its lane and its commands (highway-env
        ``IDMVehicle.act`` for humans and for CAVs under KL / CL / CR; the emergency stop of
        ``LaneDecisionVehicle.act`` under ES)."""
        geo = self.geometry
        x, y, heading, speed = b["x"], b["y"], b["heading"], b["speed"]
        lane, before, cav = b["lane"], b["target"], b["cav"]
        acting = b["present"] & ~b["crashed"] & ~self.is_obstacle
        stop = cav & (b["decision"] == ES)
        own_table = geo.table[lane]
        front, rear = self.neighbours(b, tables)
        ego = self.body_index.expand_as(lane)
        delta = b["delta"]
        # follow_road: at the end of the ramp, the acceleration lane becomes the target
        s_target, _ = geo.local_coordinates(x, y, before)
        after_end = s_target > geo.length[before] - VEHICLE_LENGTH / 2
        target = torch.where(acting & after_end, geo.next_lane[before], before)
        # MOBIL for humans and for merge CAVs on the ramp (not under ES)
        lane_changer = (~cav | (own_table == geo.ramp_table)) if self.merge else ~cav
        enabled = acting & ~stop & lane_changer
        changing = lane != target
        aborting = enabled & changing & (geo.segment[lane] == geo.segment[target])
        deciding = enabled & ~changing & (b["timer"] > LANE_CHANGE_DELAY)
        self_a = self.idm(b, ego, front[..., 1], delta)
        for column, query in ((0, 0), (1, 2)):  # left, then right (right wins if both)
            side = geo.side[lane, column]
            candidate = side.clamp(min=0)
            s, r = geo.local_coordinates(x, y, candidate)
            reachable = (side >= 0) & ~geo.forbidden[candidate] & (r.abs() <= 2 * LANE_WIDTH)
            reachable &= (s >= 0) & (s < geo.length[candidate] + VEHICLE_LENGTH)
            imposed = self.idm(b, rear[..., query], ego, delta)
            gain = self.idm(b, ego, front[..., query], delta) - self_a
            mobil = (imposed >= -MAX_BRAKING_IMPOSED) & (gain >= MIN_ACC_GAIN)
            target = torch.where(deciding & reachable & (speed.abs() >= 1) & mobil, side, target)
        target = torch.where(self.blocked_change(b, aborting, before, target), lane, target)
        # lateral control towards the target lane, IDM in the current and target lanes
        _, lateral = geo.local_coordinates(x, y, target)
        steer = steering_control(lateral, geo.heading[target], heading, speed)
        column = (geo.table[target] - own_table + 1).clamp(0, 2).unsqueeze(-1)
        target_a = self.idm(b, ego, front.gather(-1, column).squeeze(-1), delta)
        acc = torch.where(lane != target, torch.minimum(self_a, target_a), self_a)
        acc = acc.clamp(-ACC_MAX, ACC_MAX)
        acc = torch.where(stop, torch.where(speed > 0, ACC_MIN, 0.0), acc)
        return {
            **b,
            "target": target,
            "timer": torch.where(deciding, 0.0, b["timer"]),
            "acc": torch.where(acting, acc, b["acc"]),
            "steer": torch.where(acting, steer, b["steer"]),
        }

    def blocked_change(
        self, b: Bodies, aborting: torch.Tensor, before: torch.Tensor, after: torch.Tensor
    ) -> torch.Tensor:
        """highway-env's abort of a lane change (``IDMVehicle.change_lane_policy``): for the
        vehicles ``aborting [B, N]`` (changing lanes within a segment), whether another vehicle
        not yet in the target lane but heading for it is ahead within the desired gap.

        highway-env lets the vehicles act one after the other, so a vehicle sees the targets of
        the vehicles before it as they are ``after`` their decision in this simulation step and
        those after it as they were ``before``. Pairs ``[B, N, N]``."""
        index = self.body_index
        earlier = index.view(1, 1, -1) < index.view(1, -1, 1)  # [1, ego, other]
        goal = after.unsqueeze(-1)
        other_goal = torch.where(earlier, after.unsqueeze(1), before.unsqueeze(1))
        others = (b["present"] & ~self.is_obstacle).unsqueeze(1) & ~torch.eye(
            index.numel(), dtype=torch.bool, device=index.device
        )
        others = others & (b["lane"].unsqueeze(1) != goal) & (other_goal == goal)
        speed, heading = b["speed"], b["heading"]
        own_speed, own_heading = speed.unsqueeze(-1), heading.unsqueeze(-1)
        cos, sin = torch.cos(own_heading), torch.sin(own_heading)
        other_speed, other_heading = speed.unsqueeze(1), heading.unsqueeze(1)
        dv = (own_speed * cos - other_speed * torch.cos(other_heading)) * cos + (
            own_speed * sin - other_speed * torch.sin(other_heading)
        ) * sin
        desired = DISTANCE_WANTED + own_speed * TIME_WANTED + own_speed * dv / (2 * SQRT_AB)
        gap = b["x"].unsqueeze(1) - b["x"].unsqueeze(-1)
        return aborting & (others & (gap > 0) & (gap < desired)).any(-1)

    def move(self, b: Bodies) -> Bodies:
        """One simulation step of every vehicle's kinematics (a pending impact applied and the
        vehicle marked crashed), then its lane assignment."""
        moving = b["present"] & ~self.is_obstacle
        x, y, heading, speed, steer, acc = integrate(
            b["x"], b["y"], b["heading"], b["speed"], b["steer"], b["acc"], b["crashed"],
            self.speed_limit, self.dt,
        )  # fmt: skip
        impact = b["has_impact"] & moving
        x = x + torch.where(impact, b["impact_x"], 0.0)
        y = y + torch.where(impact, b["impact_y"], 0.0)
        lane = self.geometry.closest_lane(x, y, heading)
        updates = {
            "x": x,
            "y": y,
            "heading": heading,
            "speed": speed,
            "steer": steer,
            "acc": acc,
            "timer": b["timer"] + self.dt,
            "lane": lane,
        }
        out = {**b, **{k: torch.where(moving, v, b[k]) for k, v in updates.items()}}
        out["crashed"] = b["crashed"] | impact
        out["has_impact"] = b["has_impact"] & ~moving
        return out

    def collide(self, b: Bodies, tables: NeighbourTables) -> Bodies:
        """Rectangle collisions among the bodies of every road (highway-env ``Road.step``'s
        pairwise ``handle_collisions``), tested for each vehicle against its leader in its lane
        and its leaders and followers in the lanes beside it."""
        front, rear = self.neighbours(b, tables)
        partner = torch.stack(
            [front[..., 1], front[..., 0], rear[..., 0], front[..., 2], rear[..., 2]], dim=-1
        )
        rows, n = partner.shape[:2]
        ego = self.body_index.view(1, n, 1).expand(rows, n, 5)
        valid = (partner >= 0) & (b["present"] & ~self.is_obstacle).unsqueeze(-1)
        partner = torch.where(valid, partner, ego)
        lo, hi = torch.minimum(ego, partner), torch.maximum(ego, partner)
        g = self.gather
        hit, will, tx, ty = rectangle_collisions(
            g(b["x"], lo), g(b["y"], lo), g(b["heading"], lo), g(b["speed"], lo),
            self.body_length[lo], self.body_width[lo],
            g(b["x"], hi), g(b["y"], hi), g(b["heading"], hi), g(b["speed"], hi),
            self.body_length[hi], self.body_width[hi],
            self.dt,
        )  # fmt: skip
        hit = hit & valid
        will = will & valid
        flat = (rows, -1)
        dtype = b["x"].dtype
        crash = torch.zeros(rows, n, dtype=dtype, device=lo.device)
        crash = crash.scatter_reduce(1, lo.reshape(flat), hit.to(dtype).reshape(flat), "amax")
        crash = crash.scatter_reduce(1, hi.reshape(flat), hit.to(dtype).reshape(flat), "amax")
        # impacts: each body keeps the one of the last pair highway-env visits (pairs (i, j),
        # i < j, row by row); an obstacle pushes the vehicle by the whole translation
        obstacle_hi = self.is_obstacle[hi]
        half = torch.where(obstacle_hi, 1.0, 0.5).to(dtype)
        key_lo = torch.where(will, (n + hi).to(dtype), -1.0)
        key_hi = torch.where(will & ~obstacle_hi, lo.to(dtype), -1.0)
        best = torch.full((rows, n), -1.0, dtype=dtype, device=lo.device)
        best = best.scatter_reduce(1, lo.reshape(flat), key_lo.reshape(flat), "amax")
        best = best.scatter_reduce(1, hi.reshape(flat), key_hi.reshape(flat), "amax")
        pad = torch.zeros(rows, 1, dtype=dtype, device=lo.device)
        impact_x = torch.cat([b["impact_x"], pad], dim=1)  # column n takes the dropped writes
        impact_y = torch.cat([b["impact_y"], pad], dim=1)
        for index, key, scale in ((lo, key_lo, half), (hi, key_hi, -0.5)):
            chosen = (key >= 0) & (key == self.gather(best, index))
            dest = torch.where(chosen, index, n).reshape(flat)
            impact_x = impact_x.scatter(1, dest, (scale * tx).reshape(flat))
            impact_y = impact_y.scatter(1, dest, (scale * ty).reshape(flat))
        return {
            **b,
            "crashed": b["crashed"] | ((crash > 0) & ~self.is_obstacle),
            "impact_x": impact_x[:, :n],
            "impact_y": impact_y[:, :n],
            "has_impact": b["has_impact"] | ((best >= 0) & ~self.is_obstacle),
        }
