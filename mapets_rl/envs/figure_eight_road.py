"""Geometry of the figure-eight loop (MA-PETS paper, SMARTS unprotected intersection).

Two circular lobes of radius ``R`` centred at ``(+-c, 0)`` with ``c = sqrt(2) R`` are joined by two
straights along the diagonals ``y = x`` and ``y = -x``; the straights cross at right angles at the
origin, the one unsignalised intersection. Travel order (node names in the ``RoadNetwork``)::

    a -> b   straight 1, from (-c/2, -c/2) to (c/2, c/2), crossing the origin at its middle
    b -> c -> d   right lobe, 270 degrees clockwise, split in two 135-degree arcs
    d -> e   straight 2, from (c/2, -c/2) to (-c/2, c/2), crossing the origin at its middle
    e -> f -> a   left lobe, 270 degrees counter-clockwise, split in two 135-degree arcs

Arcs longer than 180 degrees are split because ``CircularLane.local_coordinates`` wraps angles to
+-pi. The reference line has length ``R (4 + 3 pi)``; lane ``k`` of ``L`` lanes is its parallel
offset by ``(k - (L-1)/2) * width`` to the left of travel. A figure-eight turns by +270 degrees on
one lobe and -270 degrees on the other, so every offset lane has exactly the reference length.
"""

from __future__ import annotations

import math

import numpy as np
from highway_env.road.lane import AbstractLane, LineType
from highway_env.road.road import LaneIndex, RoadNetwork

from mapets_rl.envs.lanes import FastCircularLane, FastStraightLane

SEGMENTS: tuple[tuple[str, str], ...] = (
    ("a", "b"),
    ("b", "c"),
    ("c", "d"),
    ("d", "e"),
    ("e", "f"),
    ("f", "a"),
)
"""Road segments in travel order."""


class FigureEightGeometry:
    """The figure-eight road network and its route coordinate.

    Args:
        length: total loop length [m] (paper: about 480 m).
        lanes: number of parallel lanes, 1 or 2.
        lane_width: lane width [m].

    Attributes:
        radius: lobe radius of the reference line [m].
        crossing_coordinates: route coordinates [m] of the intersection on straight 1 and on
            straight 2 (the two *branches* that conflict).
    """

    def __init__(self, length: float = 480.0, lanes: int = 1, lane_width: float = 4.0) -> None:
        self.length = float(length)
        self.lanes = int(lanes)
        self.lane_width = float(lane_width)
        self.radius = self.length / (4.0 + 3.0 * math.pi)
        r = self.radius
        straight = 2.0 * r
        arc = 0.75 * math.pi * r
        self.segment_lengths = np.array([straight, arc, arc, straight, arc, arc])
        self.segment_offsets = np.concatenate([[0.0], np.cumsum(self.segment_lengths)[:-1]])
        self.crossing_coordinates = np.array([r, self.segment_offsets[3] + r])
        self._segment_index = {seg: k for k, seg in enumerate(SEGMENTS)}
        self.network = self._build_network()

    def lateral_offset(self, lane: int) -> float:
        """Lateral offset of lane ``lane`` from the reference line, positive to the left [m]."""
        return (lane - (self.lanes - 1) / 2.0) * self.lane_width

    def _line_types(self, lane: int) -> tuple[str, str]:
        left = LineType.CONTINUOUS if lane == self.lanes - 1 else LineType.STRIPED
        right = LineType.CONTINUOUS if lane == 0 else LineType.NONE
        return right, left

    def _straight(
        self, start: tuple[float, float], end: tuple[float, float], lane: int
    ) -> FastStraightLane:
        direction = np.subtract(end, start) / np.linalg.norm(np.subtract(end, start))
        left = np.array([-direction[1], direction[0]]) * self.lateral_offset(lane)
        return FastStraightLane(
            np.add(start, left),
            np.add(end, left),
            line_types=self._line_types(lane),
            width=self.lane_width,
        )

    def _arc(
        self, center: tuple[float, float], start: float, end: float, lane: int
    ) -> FastCircularLane:
        clockwise = end > start  # highway-env calls increasing angle "clockwise"
        direction = 1.0 if clockwise else -1.0
        return FastCircularLane(
            center,
            self.radius - self.lateral_offset(lane) * direction,
            math.radians(start),
            math.radians(end),
            clockwise=clockwise,
            width=self.lane_width,
            line_types=self._line_types(lane),
        )

    def _build_network(self) -> RoadNetwork:
        c = math.sqrt(2.0) * self.radius
        h = c / 2.0
        net = RoadNetwork()
        for lane in range(self.lanes):
            lanes: dict[tuple[str, str], AbstractLane] = {
                ("a", "b"): self._straight((-h, -h), (h, h), lane),
                ("b", "c"): self._arc((c, 0.0), 135.0, 0.0, lane),
                ("c", "d"): self._arc((c, 0.0), 0.0, -135.0, lane),
                ("d", "e"): self._straight((h, -h), (-h, h), lane),
                ("e", "f"): self._arc((-c, 0.0), 45.0, 180.0, lane),
                ("f", "a"): self._arc((-c, 0.0), 180.0, 315.0, lane),
            }
            for (start, end), lane_obj in lanes.items():
                net.add_lane(start, end, lane_obj)
        return net

    def coordinate(self, lane_index: LaneIndex, position: np.ndarray) -> float:
        """Route coordinate [m] of ``position`` on lane ``lane_index``, in ``[0, length)``.

        Arc length along the reference line: the lane's longitudinal coordinate rescaled to the
        reference segment length, plus the segment's offset along the loop.
        """
        k = self._segment_index[(lane_index[0], lane_index[1])]
        lane = self.network.get_lane(lane_index)
        s = lane.local_coordinates(position)[0] * self.segment_lengths[k] / lane.length
        return float((self.segment_offsets[k] + s) % self.length)

    def lane_at(self, coordinate: float, lane: int) -> tuple[LaneIndex, float]:
        """Lane index and lane-local longitudinal position of route coordinate ``coordinate``."""
        coordinate = coordinate % self.length
        k = int(np.searchsorted(self.segment_offsets, coordinate, side="right") - 1)
        index = (*SEGMENTS[k], lane)
        lane_obj = self.network.get_lane(index)
        s = (coordinate - self.segment_offsets[k]) * lane_obj.length / self.segment_lengths[k]
        return index, s

    def next_segment_lanes(self, lane_index: LaneIndex) -> list[LaneIndex]:
        """All lanes of the current and of the next segment (candidates for lane tracking)."""
        k = self._segment_index[(lane_index[0], lane_index[1])]
        nxt = SEGMENTS[(k + 1) % len(SEGMENTS)]
        return [(*seg, lane) for seg in (SEGMENTS[k], nxt) for lane in range(self.lanes)]
