"""One simulation step of every road: highway-env's ``Road.act`` then ``Road.step``, in tensors.

:class:`RoadPhysics` holds what does not change during an episode (the lanes, the bodies'
sizes, the constants of the config) and :meth:`RoadPhysics.substep` advances the bodies of all
roads by one simulation step: every driving vehicle decides (``follow_road``, MOBIL and its
abort rule, the lateral controller, IDM in its current and target lanes, or the emergency stop
of a CAV under ES), every vehicle moves (kinematic bicycle model, lane assignment), and
rectangles that touch crash. The step is a pure function of a dict of ``[B, N]`` tensors (no
data-dependent shapes), so :class:`~mapets_rl.envs.torch_freeway.simulator.BatchedFreeway` can
hand it to ``torch.compile``, which fuses its few hundred elementwise ops into a few loops.

Where it departs from highway-env (measured in ``docs/results/scenarios.md``):

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
    idm_acceleration,
    integrate,
    lane_neighbours,
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
        self.body_diagonal = torch.sqrt(self.body_length**2 + self.body_width**2)
        self.dense = {
            "decide": self.decide,
            "control_and_move": self.control_and_move,
            "near_pairs": self.near_pairs,
        }
        """The dense parts of :meth:`substep`, by name (``BatchedFreeway`` may compile them)."""

    # --- neighbour search ----------------------------------------------------------------------
    def neighbours(self, b: Bodies) -> tuple[torch.Tensor, torch.Tensor]:
        """Leader and follower ``[B, N, 3]`` of every body in the lane tables left of, equal to
        and right of its own (``-1``: none), for the bodies on the road now."""
        return lane_neighbours(
            b["x"], self.geometry.table[b["lane"]], b["present"], self.geometry.n_tables
        )

    @staticmethod
    def gather(value: torch.Tensor, index: torch.Tensor) -> torch.Tensor:
        """``value [B, N]`` at body indices ``index [B, ...]`` (``-1`` reads body 0)."""
        flat = index.clamp(min=0).reshape(index.shape[0], -1)
        return value.gather(1, flat).view(index.shape)

    def idm(
        self, b: Bodies, ego: torch.Tensor, front: torch.Tensor, delta: torch.Tensor
    ) -> torch.Tensor:
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
        self, b: Bodies, front: torch.Tensor, rear: torch.Tensor
    ) -> tuple[Bodies, torch.Tensor, torch.Tensor]:
        """One simulation step of every road from bodies ``b`` and their neighbours
        ``(front, rear)`` (:meth:`neighbours`); returns the new bodies and neighbours.

        The dense parts (every vehicle's decision inputs, its control and motion, the
        collision pre-check) run through ``self.dense`` (the same functions, compiled where
        :class:`~mapets_rl.envs.torch_freeway.simulator.BatchedFreeway` compiles them); MOBIL,
        the abort rule and the exact collision test run on the few vehicles that need them."""
        decision = self.dense["decide"](b, front, rear)
        target = decision["target"]
        deciding = decision["deciding"].nonzero(as_tuple=True)
        if deciding[0].numel():
            target = self.mobil(b, front, rear, target, decision["self_a"], deciding)
        aborting = decision["aborting"].nonzero(as_tuple=True)
        if aborting[0].numel():
            target = self.abort(b, target, aborting)
        b = self.dense["control_and_move"](b, decision, target, front)
        front, rear = self.neighbours(b)
        b = self.collide(b, front, rear)
        return b, front, rear

    def decide(self, b: Bodies, front: torch.Tensor, rear: torch.Tensor) -> Bodies:
        """What every vehicle's decision starts from (highway-env ``IDMVehicle.act`` up to
        MOBIL): ``follow_road`` (at the end of the ramp the acceleration lane becomes the
        target), who may change lanes (humans, and merge CAVs on the ramp, not under ES), who is
        changing lanes within a segment (``aborting``: the abort rule applies), who decides on
        a lane change now (``deciding``: the lane-change timer passed), and the IDM
        acceleration in the current lane (``self_a``)."""
        geo = self.geometry
        lane, cav = b["lane"], b["cav"]
        acting = b["present"] & ~b["crashed"] & ~self.is_obstacle
        stop = cav & (b["decision"] == ES)
        own_table = geo.table[lane]
        s_target, _ = geo.local_coordinates(b["x"], b["y"], b["target"])
        after_end = s_target > geo.length[b["target"]] - VEHICLE_LENGTH / 2
        target = torch.where(acting & after_end, geo.next_lane[b["target"]], b["target"])
        lane_changer = (~cav | (own_table == geo.ramp_table)) if self.merge else ~cav
        enabled = acting & ~stop & lane_changer
        changing = lane != target
        deciding = enabled & ~changing & (b["timer"] > LANE_CHANGE_DELAY)
        ego = self.body_index.expand_as(lane)
        return {
            "target": target,
            "acting": acting,
            "stop": stop,
            "aborting": enabled & changing & (geo.segment[lane] == geo.segment[target]),
            "deciding": deciding,
            "timer": torch.where(deciding, 0.0, b["timer"]),
            "self_a": self.idm(b, ego, front[..., 1], b["delta"]),
        }

    def mobil(
        self,
        b: Bodies,
        front: torch.Tensor,
        rear: torch.Tensor,
        target: torch.Tensor,
        self_a: torch.Tensor,
        who: tuple[torch.Tensor, torch.Tensor],
    ) -> torch.Tensor:
        """MOBIL (highway-env ``IDMVehicle.mobil``, politeness 0) for the vehicles ``who``
        (road and body indices ``[E]``): left, then right (right wins when both pass); the
        side lane must be reachable, the vehicle moving, the new follower's imposed braking at
        most ``LANE_CHANGE_MAX_BRAKING_IMPOSED`` and the own gain at least
        ``LANE_CHANGE_MIN_ACC_GAIN``. Returns the targets ``[B, N]``."""
        geo = self.geometry
        road, ego = who
        sub = {key: value[road] for key, value in b.items()}  # [E, N]
        lane = sub["lane"].gather(1, ego.unsqueeze(1))  # [E, 1]
        x, y = sub["x"].gather(1, ego.unsqueeze(1)), sub["y"].gather(1, ego.unsqueeze(1))
        speed = sub["speed"].gather(1, ego.unsqueeze(1))
        delta = sub["delta"].gather(1, ego.unsqueeze(1))
        me = ego.unsqueeze(1)
        chosen = target[road, ego]
        for column, query in ((0, 0), (1, 2)):  # left, then right
            side = geo.side[lane, column]
            candidate = side.clamp(min=0)
            s, r = geo.local_coordinates(x, y, candidate)
            reachable = (side >= 0) & ~geo.forbidden[candidate] & (r.abs() <= 2 * LANE_WIDTH)
            reachable &= (s >= 0) & (s < geo.length[candidate] + VEHICLE_LENGTH)
            new_front = front[road, ego, query].unsqueeze(1)
            new_rear = rear[road, ego, query].unsqueeze(1)
            imposed = self.idm(sub, new_rear, me, delta)
            gain = self.idm(sub, me, new_front, delta) - self_a[road, ego].unsqueeze(1)
            go = reachable & (speed.abs() >= 1) & (imposed >= -MAX_BRAKING_IMPOSED)
            go &= gain >= MIN_ACC_GAIN
            chosen = torch.where(go.squeeze(1), side.squeeze(1), chosen)
        target = target.clone()
        target[road, ego] = chosen
        return target

    def abort(
        self, b: Bodies, after: torch.Tensor, who: tuple[torch.Tensor, torch.Tensor]
    ) -> torch.Tensor:
        """highway-env's abort of a lane change (``IDMVehicle.change_lane_policy``) for the
        vehicles ``who`` (``[E]`` road and body indices, changing lanes within a segment): the
        change is given up when another vehicle not yet in the target lane but heading for it
        is ahead within the desired gap. highway-env lets the vehicles act one after the other,
        so a vehicle sees the targets of the vehicles before it as they are ``after`` their
        decision in this simulation step, and those after it as they were before (``b``).
        Returns the targets ``[B, N]``."""
        road, ego = who
        x, speed, heading = b["x"][road], b["speed"][road], b["heading"][road]  # [E, N]
        goal = after[road, ego].unsqueeze(-1)
        earlier = self.body_index.unsqueeze(0) < ego.unsqueeze(-1)
        other_goal = torch.where(earlier, after[road], b["target"][road])
        others = b["present"][road] & ~self.is_obstacle
        others &= self.body_index.unsqueeze(0) != ego.unsqueeze(-1)
        others &= (b["lane"][road] != goal) & (other_goal == goal)
        own_x, own_speed = x.gather(1, ego.unsqueeze(-1)), speed.gather(1, ego.unsqueeze(-1))
        own_heading = heading.gather(1, ego.unsqueeze(-1))
        cos, sin = torch.cos(own_heading), torch.sin(own_heading)
        dv = (own_speed * cos - speed * torch.cos(heading)) * cos + (
            own_speed * sin - speed * torch.sin(heading)
        ) * sin
        desired = DISTANCE_WANTED + own_speed * TIME_WANTED + own_speed * dv / (2 * SQRT_AB)
        gap = x - own_x
        blocked = (others & (gap > 0) & (gap < desired)).any(1)
        target = after.clone()
        target[road, ego] = torch.where(blocked, b["lane"][road, ego], after[road, ego])
        return target

    def control_and_move(
        self, b: Bodies, decision: Bodies, target: torch.Tensor, front: torch.Tensor
    ) -> Bodies:
        """Lateral control towards the target lane, IDM in the current and target lanes (the
        lower while changing lanes), or the emergency stop; then one step of the kinematics
        (a pending impact applied and the vehicle marked crashed) and the lane assignment."""
        geo = self.geometry
        lane, speed = b["lane"], b["speed"]
        acting, self_a = decision["acting"], decision["self_a"]
        _, lateral = geo.local_coordinates(b["x"], b["y"], target)
        steer = steering_control(lateral, geo.heading[target], b["heading"], speed)
        column = (geo.table[target] - geo.table[lane] + 1).clamp(0, 2).unsqueeze(-1)
        ego = self.body_index.expand_as(lane)
        target_a = self.idm(b, ego, front.gather(-1, column).squeeze(-1), b["delta"])
        acc = torch.where(lane != target, torch.minimum(self_a, target_a), self_a)
        acc = acc.clamp(-ACC_MAX, ACC_MAX)
        acc = torch.where(decision["stop"], torch.where(speed > 0, ACC_MIN, 0.0), acc)
        acc = torch.where(acting, acc, b["acc"])
        steer = torch.where(acting, steer, b["steer"])
        moving = b["present"] & ~self.is_obstacle
        x, y, heading, speed, steer, acc = integrate(
            b["x"], b["y"], b["heading"], speed, steer, acc, b["crashed"],
            self.speed_limit, self.dt,
        )  # fmt: skip
        impact = b["has_impact"] & moving
        x = x + torch.where(impact, b["impact_x"], 0.0)
        y = y + torch.where(impact, b["impact_y"], 0.0)
        updates = {
            "x": x,
            "y": y,
            "heading": heading,
            "speed": speed,
            "steer": steer,
            "acc": acc,
            "timer": decision["timer"] + self.dt,
            "lane": geo.closest_lane(x, y, heading),
        }
        out = {**b, **{k: torch.where(moving, v, b[k]) for k, v in updates.items()}}
        out["target"] = target
        out["crashed"] = b["crashed"] | impact
        out["has_impact"] = b["has_impact"] & ~moving
        return out

    def near_pairs(
        self, b: Bodies, front: torch.Tensor, rear: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """The candidate pairs of the collision test: each vehicle with its leader in its lane
        and its leaders and followers in the lanes beside it, as ``(lo, hi)`` body indices
        ``[B, N, 5]`` (``lo < hi``, the order in which highway-env visits a pair) and whether
        they pass highway-env's spherical pre-check (``RoadObject._is_colliding``)."""
        partner = torch.stack(
            [front[..., 1], front[..., 0], rear[..., 0], front[..., 2], rear[..., 2]], dim=-1
        )
        rows, n = partner.shape[:2]
        ego = self.body_index.view(1, n, 1).expand(rows, n, 5)
        valid = (partner >= 0) & (b["present"] & ~self.is_obstacle).unsqueeze(-1)
        partner = torch.where(valid, partner, ego)
        lo, hi = torch.minimum(ego, partner), torch.maximum(ego, partner)
        g = self.gather
        dx, dy = g(b["x"], hi) - g(b["x"], lo), g(b["y"], hi) - g(b["y"], lo)
        reach = (self.body_diagonal[lo] + self.body_diagonal[hi]) / 2 + g(b["speed"], lo) * self.dt
        return lo, hi, valid & (dx * dx + dy * dy <= reach * reach)

    def collide(self, b: Bodies, front: torch.Tensor, rear: torch.Tensor) -> Bodies:
        """Rectangle collisions among the bodies of every road (highway-env ``Road.step``'s
        pairwise ``handle_collisions``): the separating-axis test on the pairs that pass the
        pre-check of :meth:`near_pairs`; touching bodies crash, and a pair about to touch
        within a step leaves each the impact highway-env applies in the next step (each body
        keeps the one of the last pair highway-env visits: pairs ``(i, j)``, ``i < j``, row by
        row; an obstacle pushes the vehicle by the whole translation)."""
        lo, hi, near = self.dense["near_pairs"](b, front, rear)
        road, row, column = near.nonzero(as_tuple=True)
        if road.numel() == 0:
            return b
        lo, hi = lo[road, row, column], hi[road, row, column]
        length, width = self.body_length, self.body_width

        def at(key: str, index: torch.Tensor) -> torch.Tensor:
            return b[key][road, index]

        hit, will, tx, ty = rectangle_collisions(
            at("x", lo), at("y", lo), at("heading", lo), at("speed", lo), length[lo], width[lo],
            at("x", hi), at("y", hi), at("heading", hi), at("speed", hi), length[hi], width[hi],
            self.dt,
        )  # fmt: skip
        crashed = b["crashed"].clone()
        crashed[road[hit], lo[hit]] = True
        crashed[road[hit], hi[hit]] = True
        crashed &= ~self.is_obstacle
        out = {**b, "crashed": crashed}
        if not bool(will.any()):
            return out
        road, lo, hi, tx, ty = road[will], lo[will], hi[will], tx[will], ty[will]
        n = self.body_index.numel()
        obstacle_hi = self.is_obstacle[hi]
        # visit order of the pairs touching each body: its pairs as the lower index come last
        rows = torch.cat([road, road[~obstacle_hi]])
        body = torch.cat([lo, hi[~obstacle_hi]])
        rank = torch.cat([n + hi, lo[~obstacle_hi]])
        lower_share = torch.where(obstacle_hi, 1.0, 0.5).to(tx.dtype)
        upper_share = torch.full((int((~obstacle_hi).sum()),), -0.5, dtype=tx.dtype)
        scale = torch.cat([lower_share, upper_share.to(tx.device)])
        dx = torch.cat([tx, tx[~obstacle_hi]]) * scale
        dy = torch.cat([ty, ty[~obstacle_hi]]) * scale
        slot = rows * n + body
        order = torch.argsort(slot * (2 * n + 1) + rank, stable=True)
        slot, dx, dy = slot[order], dx[order], dy[order]
        last = torch.ones_like(slot, dtype=torch.bool)
        last[:-1] = slot[1:] != slot[:-1]
        impact_x, impact_y = b["impact_x"].clone(), b["impact_y"].clone()
        has_impact = b["has_impact"].clone()
        impact_x.view(-1)[slot[last]] = dx[last]
        impact_y.view(-1)[slot[last]] = dy[last]
        has_impact.view(-1)[slot[last]] = True
        out.update(impact_x=impact_x, impact_y=impact_y, has_impact=has_impact)
        return out
