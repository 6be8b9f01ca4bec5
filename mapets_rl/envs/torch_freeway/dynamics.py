"""highway-env's driver models and physics as tensor functions over a batch of roads.

Every function takes tensors of one shape ``[...]`` (roads, vehicles, queries) and computes what
the highway-env method it names computes for one vehicle, with the same constants (read from
highway-env's classes, so they cannot drift from the reference):

- :func:`idm_acceleration`: ``IDMVehicle.acceleration`` with ``desired_gap(projected=True)``;
- :func:`steering_control`: ``ControlledVehicle.steering_control`` (the lateral controller whose
  gains set how long a lane change takes);
- :func:`integrate`: ``Vehicle.step`` (kinematic bicycle model) with ``clip_actions`` and our
  ``RouteVehicleMixin.step`` floor (speeds never go below 0 within a step);
- :func:`lane_neighbours`: the leader / follower search of
  :class:`~mapets_rl.envs.road.SortedNeighbourRoad` (one sort per road, then running minima);
- :func:`rectangle_collisions`: ``RoadObject._is_colliding`` (the spherical pre-check, then the
  separating-axis test of ``utils.are_polygons_intersecting`` with the displacement of one
  simulation step).
"""

from __future__ import annotations

import math

import torch
from highway_env.vehicle.behavior import IDMVehicle
from highway_env.vehicle.controller import ControlledVehicle
from highway_env.vehicle.kinematics import Vehicle

from mapets_rl.envs.torch_freeway.geometry import wrap_to_pi

COMFORT_ACC_MAX = IDMVehicle.COMFORT_ACC_MAX  # 3 m/s^2
COMFORT_ACC_MIN = IDMVehicle.COMFORT_ACC_MIN  # -5 m/s^2
DISTANCE_WANTED = IDMVehicle.DISTANCE_WANTED  # 5 m + vehicle length
TIME_WANTED = IDMVehicle.TIME_WANTED  # 1.5 s
SQRT_AB = math.sqrt(-COMFORT_ACC_MAX * COMFORT_ACC_MIN)
KP_LATERAL = ControlledVehicle.KP_LATERAL  # 1 / 0.6 s
KP_HEADING = ControlledVehicle.KP_HEADING  # 1 / 0.2 s
TAU_PURSUIT = ControlledVehicle.TAU_PURSUIT  # straight lanes: the future heading is the lane's
MAX_STEERING_ANGLE = ControlledVehicle.MAX_STEERING_ANGLE  # pi / 3
LENGTH = Vehicle.LENGTH  # 5 m
WIDTH = Vehicle.WIDTH  # 2 m
NOT_ZERO_EPS = 1e-2  # highway-env utils.not_zero


def not_zero(value: torch.Tensor, eps: float = NOT_ZERO_EPS) -> torch.Tensor:
    """highway-env ``utils.not_zero``: ``value`` if ``|value| > eps``, else ``+-eps`` by sign."""
    small = torch.where(value >= 0, eps, -eps).to(value.dtype)
    return torch.where(value.abs() > eps, value, small)


def idm_acceleration(
    speed: torch.Tensor,
    target_speed: torch.Tensor,
    heading: torch.Tensor,
    delta: torch.Tensor,
    speed_limit: float,
    has_front: torch.Tensor,
    gap: torch.Tensor,
    front_speed: torch.Tensor,
    front_heading: torch.Tensor,
) -> torch.Tensor:
    """IDM acceleration [m/s^2] of an ego vehicle (highway-env ``IDMVehicle.acceleration``).

    Args:
        speed, target_speed, heading: the ego's speed [m/s], desired speed [m/s] (clipped to
            ``[0, speed_limit]`` as highway-env clips it to its lane's limit) and heading [rad].
        delta: the exponent of the *deciding* vehicle (highway-env evaluates another vehicle's
            acceleration with its own ``DELTA``).
        has_front: whether there is a vehicle (or obstacle) ahead.
        gap: centre-to-centre distance to it along the road [m] (``lane_distance_to``).
        front_speed, front_heading: its speed [m/s] and heading [rad].
    """
    target = target_speed.clamp(0.0, speed_limit)
    ratio = speed.clamp(min=0.0) / not_zero(target).abs()
    acceleration = COMFORT_ACC_MAX * (1.0 - ratio.pow(delta))
    cos, sin = torch.cos(heading), torch.sin(heading)
    dv = (speed * cos - front_speed * torch.cos(front_heading)) * cos + (
        speed * sin - front_speed * torch.sin(front_heading)
    ) * sin
    desired = DISTANCE_WANTED + speed * TIME_WANTED + speed * dv / (2 * SQRT_AB)
    term = desired / not_zero(gap)
    return acceleration - torch.where(has_front, COMFORT_ACC_MAX * term * term, 0.0)


def steering_control(
    lateral: torch.Tensor, lane_heading: torch.Tensor, heading: torch.Tensor, speed: torch.Tensor
) -> torch.Tensor:
    """Steering angle [rad] that follows a straight lane's centre (highway-env
    ``ControlledVehicle.steering_control``), from the lateral offset [m] on that lane, the
    lane's heading, and the vehicle's heading [rad] and speed [m/s].

    Computed in float64 whatever the inputs' dtype: at a standstill the controller saturates at
    ``asin(1)``, which float32 rounds above pi / 2, so that ``tan`` flips sign and the vehicle
    would steer the wrong way (measured: ramp vehicles that stop before the merge point then
    stay stuck more often)."""
    dtype = lateral.dtype
    lateral, lane_heading = lateral.double(), lane_heading.double()
    heading, speed_nz = heading.double(), not_zero(speed.double())
    heading_command = torch.asin((-KP_LATERAL * lateral / speed_nz).clamp(-1.0, 1.0))
    heading_ref = lane_heading + heading_command.clamp(-math.pi / 4, math.pi / 4)
    heading_rate = KP_HEADING * wrap_to_pi(heading_ref - heading)
    slip = torch.asin((LENGTH / 2 / speed_nz * heading_rate).clamp(-1.0, 1.0))
    steering = torch.atan(2 * torch.tan(slip))
    return steering.clamp(-MAX_STEERING_ANGLE, MAX_STEERING_ANGLE).to(dtype)


def integrate(
    x: torch.Tensor,
    y: torch.Tensor,
    heading: torch.Tensor,
    speed: torch.Tensor,
    steering: torch.Tensor,
    acceleration: torch.Tensor,
    crashed: torch.Tensor,
    max_speed: float,
    dt: float,
) -> tuple[torch.Tensor, ...]:
    """One simulation step of the kinematic bicycle model (highway-env ``Vehicle.step``).

    The commanded ``acceleration`` is first limited as ``RouteVehicleMixin.step`` limits it
    (no speed below 0 at the end of the step), then ``Vehicle.clip_actions`` applies (a crashed
    vehicle steers 0 and brakes by its speed; none exceeds ``max_speed``).

    Returns ``(x, y, heading, speed, steering, acceleration)`` after the step, the last two the
    commands actually applied (highway-env stores them in ``vehicle.action``).
    """
    floor = -speed / dt
    acceleration = torch.where(~crashed & (acceleration < floor), floor, acceleration)
    steering = torch.where(crashed, 0.0, steering)
    acceleration = torch.where(crashed, -speed, acceleration)
    acceleration = torch.where(
        speed > max_speed,
        torch.minimum(acceleration, max_speed - speed),
        torch.where(speed < 0, torch.maximum(acceleration, -speed), acceleration),
    )
    beta = torch.atan(0.5 * torch.tan(steering))
    angle = heading + beta
    x = x + speed * torch.cos(angle) * dt
    y = y + speed * torch.sin(angle) * dt
    heading = heading + speed * torch.sin(beta) / (LENGTH / 2) * dt
    speed = speed + acceleration * dt
    return x, y, heading, speed, steering, acceleration


def lane_neighbours(
    x: torch.Tensor, table: torch.Tensor, present: torch.Tensor, n_tables: int
) -> tuple[torch.Tensor, torch.Tensor]:
    """Leader and follower of every body in the lane tables left of, equal to and right of its
    own (highway-env ``Road.neighbour_vehicles`` as :class:`SortedNeighbourRoad` answers it).

    One sort of each road's bodies by ``x``, then for every table the next and previous body
    of that table at each sorted position (reverse / forward running minimum and maximum), so
    the search costs ``O(N log N + N T)`` per road with no per-query binary search. As in
    highway-env, the leader is the first body strictly ahead and the follower the last body at
    or behind ``x`` other than the body itself.

    Args:
        x: ``[B, N]`` route coordinates [m].
        table: ``[B, N]`` neighbour-search lane of each body (``0 .. n_tables - 1``).
        present: ``[B, N]`` bodies on the road (the others are never neighbours).
        n_tables: number of tables ``T``.

    Returns:
        ``(front, rear)``, each ``[B, N, 3]`` body indices (``-1``: none) for the tables
        ``table - 1``, ``table``, ``table + 1``.
    """
    rows, n = x.shape
    device = x.device
    pos = torch.arange(n, device=device)
    sorted_x, order = torch.sort(torch.where(present, x, math.inf), dim=1, stable=True)
    rank = torch.empty_like(order).scatter_(1, order, pos.expand(rows, n))
    sorted_table = torch.where(present.gather(1, order), table.gather(1, order), -1)
    # the last sorted position of each group of equal x (searchsorted's side="right")
    group_end = torch.ones(rows, n, dtype=torch.bool, device=device)
    group_end[:, :-1] = sorted_x[:, 1:] != sorted_x[:, :-1]
    upper = torch.where(group_end, pos, n).flip(1).cummin(1).values.flip(1)
    tables = torch.arange(n_tables, device=device).view(1, -1, 1)
    member = sorted_table.unsqueeze(1) == tables  # [B, T, N]
    after = torch.where(member, pos, n).flip(2).cummin(2).values.flip(2)
    before = torch.where(member, pos, -1).cummax(2).values
    # padded so that position n reads "none" ahead and position -1 reads "none" behind
    after = torch.cat([after, torch.full_like(after[..., :1], n)], dim=2)  # [B, T, N + 1]
    before = torch.cat([torch.full_like(before[..., :1], -1), before], dim=2)  # index p + 1
    own = table.unsqueeze(-1) + torch.tensor([-1, 0, 1], device=device)  # [B, N, 3]
    valid = (own >= 0) & (own < n_tables) & present.unsqueeze(-1)
    lane = own.clamp(0, n_tables - 1)
    self_rank = rank.unsqueeze(-1).expand(rows, n, 3)
    top = upper.gather(1, rank).unsqueeze(-1).expand(rows, n, 3)
    width = n + 1
    front_pos = after.reshape(rows, -1).gather(1, (lane * width + top + 1).reshape(rows, -1))
    rear_pos = before.reshape(rows, -1).gather(1, (lane * width + top + 1).reshape(rows, -1))
    front_pos, rear_pos = front_pos.view(rows, n, 3), rear_pos.view(rows, n, 3)
    is_self = rear_pos == self_rank  # only in the own table: the one behind it instead
    earlier = before.reshape(rows, -1).gather(1, (lane * width + self_rank).reshape(rows, -1))
    rear_pos = torch.where(is_self, earlier.view(rows, n, 3), rear_pos)

    def body(position: torch.Tensor) -> torch.Tensor:
        flat = position.clamp(0, n - 1).reshape(rows, -1)
        return order.gather(1, flat).view(rows, n, 3)

    front = torch.where(valid & (front_pos < n), body(front_pos), -1)
    rear = torch.where(valid & (rear_pos >= 0), body(rear_pos), -1)
    return front, rear


def rectangle_collisions(
    ax: torch.Tensor,
    ay: torch.Tensor,
    a_heading: torch.Tensor,
    a_speed: torch.Tensor,
    a_length: torch.Tensor,
    a_width: torch.Tensor,
    bx: torch.Tensor,
    by: torch.Tensor,
    b_heading: torch.Tensor,
    b_speed: torch.Tensor,
    b_length: torch.Tensor,
    b_width: torch.Tensor,
    dt: float,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """highway-env ``a._is_colliding(b, dt)`` for pairs of rectangles ``[...]``.

    The spherical pre-check (centre distance against the half diagonals plus ``a``'s travel),
    then the separating-axis test on the four edge normals of ``a`` and ``b``
    (``utils.are_polygons_intersecting``; opposite edges give the same distance, so two axes per
    rectangle suffice, visited in highway-env's order so that ties pick the same axis), with
    ``a``'s interval swept by the relative displacement ``(v_a - v_b) dt``.

    Returns ``(intersecting, will_intersect, translation_x, translation_y)``: overlapping now;
    overlapping within ``dt`` at constant velocity; the minimum translation that separates them
    (the impact highway-env applies in the next step).
    """
    diag_a = torch.sqrt(a_length**2 + a_width**2)
    diag_b = torch.sqrt(b_length**2 + b_width**2)
    cx, cy = ax - bx, ay - by
    near = torch.sqrt(cx * cx + cy * cy) <= (diag_a + diag_b) / 2 + a_speed * dt
    ca, sa = torch.cos(a_heading), torch.sin(a_heading)
    cb, sb = torch.cos(b_heading), torch.sin(b_heading)
    disp_x = (a_speed * ca - b_speed * cb) * dt
    disp_y = (a_speed * sa - b_speed * sb) * dt
    intersecting = near.clone()
    will = near.clone()
    best = torch.full_like(ax, math.inf)
    tx = torch.zeros_like(ax)
    ty = torch.zeros_like(ax)
    # edge normals in highway-env's order: a's first two edges, then b's (-u, then w)
    for nx, ny in ((-ca, -sa), (-sa, ca), (-cb, -sb), (-sb, cb)):
        half_a = a_length / 2 * (ca * nx + sa * ny).abs() + a_width / 2 * (-sa * nx + ca * ny).abs()
        half_b = b_length / 2 * (cb * nx + sb * ny).abs() + b_width / 2 * (-sb * nx + cb * ny).abs()
        centre_a = ax * nx + ay * ny
        centre_b = bx * nx + by * ny
        min_a, max_a = centre_a - half_a, centre_a + half_a
        min_b, max_b = centre_b - half_b, centre_b + half_b
        gap = torch.where(min_a < min_b, min_b - max_a, min_a - max_b)
        intersecting = intersecting & (gap <= 0)
        sweep = nx * disp_x + ny * disp_y
        min_a = torch.where(sweep < 0, min_a + sweep, min_a)
        max_a = torch.where(sweep < 0, max_a, max_a + sweep)
        distance = torch.where(min_a < min_b, min_b - max_a, min_a - max_b)
        will = will & (distance <= 0)
        better = distance.abs() < best
        best = torch.where(better, distance.abs(), best)
        sign = torch.where(cx * nx + cy * ny > 0, 1.0, -1.0).to(ax.dtype)
        tx = torch.where(better, sign * nx, tx)
        ty = torch.where(better, sign * ny, ty)
    return intersecting, will, best * tx, best * ty
