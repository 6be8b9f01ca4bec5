"""The lanes of ``freeway`` and ``freeway-merge`` as tensors, for the batched simulator.

The lanes are highway-env ``StraightLane`` s (the ones :class:`~mapets_rl.envs.FreewayEnv` and
:class:`~mapets_rl.envs.FreewayMergeEnv` build), numbered in the order in which highway-env's
``RoadNetwork.get_closest_lane_index`` visits them, so that ``argmin`` over lanes picks the same
lane on a tie:

- ``0 .. lanes - 1``: the mainline lanes ``("0", "1", k)`` (0 the leftmost, at ``y = 4 k``);
- ``lanes``: the acceleration lane ``("0", "1", lanes)`` (``freeway-merge`` only);
- ``lanes + 1``: the slanted ramp lane ``("r", "0", 0)`` (``freeway-merge`` only).

Every lane also has a *table* (the neighbour-search lane of
:class:`~mapets_rl.envs.road.SortedNeighbourRoad`: the mainline lane's own number, and
``lanes`` for both ramp lanes, which are searched as one) and a *segment* (``("0", "1")`` or
``("r", "0")``), on which highway-env's lane-change rules depend.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from highway_env.road.lane import AbstractLane, StraightLane

LANE_WIDTH = StraightLane.DEFAULT_WIDTH
"""Lane width [m] (highway-env ``AbstractLane.DEFAULT_WIDTH``)."""
VEHICLE_LENGTH = AbstractLane.VEHICLE_LENGTH
"""The vehicle length highway-env's lanes assume in ``after_end`` / ``is_reachable_from`` [m]."""

MAINLINE, RAMP_SEGMENT = 0, 1
"""Segment ids: ``("0", "1")`` (mainline and acceleration lane) and ``("r", "0")`` (ramp)."""


@dataclass(frozen=True)
class FreewayGeometry:
    """The lanes of one scenario config as ``[L]`` tensors (``L`` lanes, see module docstring).

    Attributes:
        lanes: mainline lanes.
        merge: whether the road has the on-ramp (``freeway-merge``).
        start_x, start_y: lane start points [m].
        dir_x, dir_y: unit direction vectors.
        heading: lane headings [rad].
        length: lane lengths [m].
        forbidden: lanes no vehicle changes into (the ramp lanes).
        table: neighbour-search lane of each lane.
        number: the lane's number within its segment (highway-env ``lane_index[2]``).
        segment: the lane's segment id.
        side: ``[L, 2]`` the lane to the left / right in the same segment, ``-1`` if none.
        next_lane: the lane a vehicle follows once it reaches the end of this one
            (highway-env ``follow_road``: the ramp leads onto the acceleration lane, every other
            lane to itself).
        merge_start, merge_end: x of the acceleration lane's start and end [m] (0 without a
            ramp).
        n_tables: neighbour-search lanes (``lanes`` or ``lanes + 1``).
    """

    lanes: int
    merge: bool
    start_x: torch.Tensor
    start_y: torch.Tensor
    dir_x: torch.Tensor
    dir_y: torch.Tensor
    heading: torch.Tensor
    length: torch.Tensor
    forbidden: torch.Tensor
    table: torch.Tensor
    number: torch.Tensor
    segment: torch.Tensor
    side: torch.Tensor
    next_lane: torch.Tensor
    merge_start: float
    merge_end: float
    n_tables: int

    @classmethod
    def from_config(
        cls, config: dict, merge: bool, device: torch.device, dtype: torch.dtype
    ) -> FreewayGeometry:
        """The lanes of a validated ``FreewayEnv`` / ``FreewayMergeEnv`` ``config``."""
        lanes = int(config["lanes"])
        road_length = float(config["road_length"])
        starts = [(0.0, k * LANE_WIDTH) for k in range(lanes)]
        ends = [(road_length, k * LANE_WIDTH) for k in range(lanes)]
        forbidden = [False] * lanes
        table = list(range(lanes))
        number = list(range(lanes))
        segment = [MAINLINE] * lanes
        merge_start = merge_end = 0.0
        if merge:
            merge_start = float(config["merge_start"])
            merge_end = merge_start + float(config["merge_length"])
            y = lanes * LANE_WIDTH
            starts += [(merge_start, y), (merge_start - float(config["ramp_length"]),
                                          y + float(config["ramp_offset"]))]  # fmt: skip
            ends += [(merge_end, y), (merge_start, y)]
            forbidden += [True, True]
            table += [lanes, lanes]
            number += [lanes, 0]
            segment += [MAINLINE, RAMP_SEGMENT]
        n = len(starts)
        side = []
        for k in range(n):
            same = [j for j in range(n) if segment[j] == segment[k]]
            left = [j for j in same if number[j] == number[k] - 1]
            right = [j for j in same if number[j] == number[k] + 1]
            side.append((left[0] if left else -1, right[0] if right else -1))
        next_lane = list(range(n))
        if merge:
            next_lane[lanes + 1] = lanes

        def tensor(values: list, kind: torch.dtype = dtype) -> torch.Tensor:
            return torch.tensor(values, dtype=kind, device=device)

        # highway-env's own lanes give the directions, lengths and headings, to the last bit
        stock = [StraightLane(a, b) for a, b in zip(starts, ends, strict=True)]
        return cls(
            lanes=lanes,
            merge=merge,
            start_x=tensor([lane.start[0] for lane in stock]),
            start_y=tensor([lane.start[1] for lane in stock]),
            dir_x=tensor([lane.direction[0] for lane in stock]),
            dir_y=tensor([lane.direction[1] for lane in stock]),
            heading=tensor([lane.heading for lane in stock]),
            length=tensor([lane.length for lane in stock]),
            forbidden=tensor(forbidden, torch.bool),
            table=tensor(table, torch.long),
            number=tensor(number, torch.long),
            segment=tensor(segment, torch.long),
            side=tensor(side, torch.long),
            next_lane=tensor(next_lane, torch.long),
            merge_start=merge_start,
            merge_end=merge_end,
            n_tables=lanes + 1 if merge else lanes,
        )

    @property
    def n_lanes(self) -> int:
        """Lanes ``L`` (mainline, acceleration and ramp lanes)."""
        return int(self.length.numel())

    @property
    def ramp_table(self) -> int:
        """Neighbour-search lane of the ramp (``lanes``; one past the mainline without one)."""
        return self.lanes

    def local_coordinates(
        self, x: torch.Tensor, y: torch.Tensor, lane: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """``(longitudinal, lateral)`` [m] of points ``(x, y)`` on lanes ``lane`` (all the same
        shape): highway-env ``StraightLane.local_coordinates``."""
        dx = x - self.start_x[lane]
        dy = y - self.start_y[lane]
        ux, uy = self.dir_x[lane], self.dir_y[lane]
        return dx * ux + dy * uy, dy * ux - dx * uy

    def closest_lane(self, x: torch.Tensor, y: torch.Tensor, heading: torch.Tensor) -> torch.Tensor:
        """highway-env ``RoadNetwork.get_closest_lane_index(position, heading)``: the lane that
        minimises ``|lateral| + distance beyond the lane's ends + |heading difference|``
        (first lane on a tie), for points ``[...]`` -> lane ids ``[...]``."""
        dx = x.unsqueeze(-1) - self.start_x
        dy = y.unsqueeze(-1) - self.start_y
        s = dx * self.dir_x + dy * self.dir_y
        r = dy * self.dir_x - dx * self.dir_y
        angle = wrap_to_pi(heading.unsqueeze(-1) - self.heading).abs()
        distance = r.abs() + (s - self.length).clamp(min=0) + (-s).clamp(min=0) + angle
        return distance.argmin(-1)


def wrap_to_pi(angle: torch.Tensor) -> torch.Tensor:
    """highway-env ``utils.wrap_to_pi``: ``((angle + pi) mod 2 pi) - pi`` (floor modulo)."""
    return torch.remainder(angle + math.pi, 2 * math.pi) - math.pi
