"""Roads whose neighbour search is one sorted pass per simulation step.

highway-env's stock ``Road.neighbour_vehicles`` scans every vehicle for every query, projects it
onto the ego's current lane segment only, and on the figure-eight mistakes cars on the crossing
branch for leaders. Here every vehicle gets one scalar *route coordinate* per simulation step
(arc length along the reference line of the route), vehicles are sorted once per lane, and
leaders/followers are read off the sorted arrays. Longitudinal distances use the same coordinate,
so IDM gaps are correct across lane-segment boundaries and around a closed loop.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from highway_env.road.road import LaneIndex, Road, RoadNetwork
from highway_env.vehicle.kinematics import Vehicle


class SortedNeighbourRoad(Road):
    """A highway-env ``Road`` with cached, sorted per-lane neighbour tables.

    Args:
        network: the lanes.
        coordinate: maps ``(lane_index, position)`` to the route coordinate in metres.
        period: length of a closed route (coordinates wrap modulo ``period``), ``None`` for an
            open road.
        n_lanes: number of parallel lanes (lane ids ``0 .. n_lanes - 1``).
        lane_id: maps a lane index to its lane id in ``0 .. n_lanes - 1`` (default: the
            index's last element); lanes of different road segments that share an id are
            searched as one lane (e.g. an on-ramp and the acceleration lane it leads to).
        stock_neighbour_search: use highway-env's stock searches for who is near whom:
            ``Road.neighbour_vehicles`` (leaders/followers), ``get_closest_lane_index`` over
            every lane (lane assignment) and the all-pairs collision loop of ``Road.step``.
            The reference of ``benchmarks/env_throughput.py``.
        np_random: random generator for vehicle behaviour.
    """

    def __init__(
        self,
        network: RoadNetwork,
        coordinate: Callable[[LaneIndex, np.ndarray], float],
        period: float | None,
        n_lanes: int,
        stock_neighbour_search: bool = False,
        np_random: np.random.Generator | None = None,
        lane_id: Callable[[LaneIndex], int] | None = None,
    ) -> None:
        super().__init__(network=network, np_random=np_random)
        self.coordinate = coordinate
        self.period = period
        self.n_lanes = n_lanes
        self.stock_neighbour_search = stock_neighbour_search
        self.lane_id = lane_id or (lambda lane_index: lane_index[2])
        self._coord: dict[int, float] = {}
        self._lane_coords: list[np.ndarray] = []
        self._lane_vehicles: list[list[Vehicle]] = []

    def refresh(self) -> None:
        """Recompute every vehicle's route coordinate and the sorted per-lane tables.

        Road objects (e.g. the obstacle that ends an acceleration lane) are in the tables too,
        so that IDM and MOBIL see them as standing leaders, as in highway-env's stock search."""
        vehicles = self.vehicles + self.objects if self.objects else self.vehicles
        lane_id = self.lane_id
        coords = np.fromiter(
            (self.coordinate(v.lane_index, v.position) for v in vehicles),
            dtype=float,
            count=len(vehicles),
        )
        lanes = np.fromiter(
            (lane_id(v.lane_index) for v in vehicles), dtype=int, count=len(vehicles)
        )
        self._coord = {id(v): c for v, c in zip(vehicles, coords, strict=True)}
        self._lane_coords, self._lane_vehicles = [], []
        for lane in range(self.n_lanes):
            idx = np.flatnonzero(lanes == lane)
            order = idx[np.argsort(coords[idx], kind="stable")]
            self._lane_coords.append(coords[order])
            self._lane_vehicles.append([vehicles[i] for i in order])

    def route_coordinate(self, vehicle: Vehicle) -> float:
        """Route coordinate of ``vehicle`` [m] (cached for the current simulation step)."""
        coord = self._coord.get(id(vehicle))
        if coord is None:
            coord = self.coordinate(vehicle.lane_index, vehicle.position)
        return coord

    def longitudinal_distance(self, ego: Vehicle, other: Vehicle) -> float:
        """Signed distance from ``ego`` to ``other`` along the route [m]; wraps on a loop."""
        delta = self.route_coordinate(other) - self.route_coordinate(ego)
        if self.period is not None:
            delta = (delta + self.period / 2) % self.period - self.period / 2
        return delta

    def act(self) -> None:
        """Refresh the neighbour tables, then let every vehicle decide (once per sim step)."""
        if not self.stock_neighbour_search:
            self.refresh()
        super().act()

    def step(self, dt: float) -> None:
        """Step the dynamics, then test for collisions only among pairs that are close.

        The stock ``Road.step`` calls ``handle_collisions`` on all n(n-1)/2 pairs; a vectorised
        distance pre-check keeps highway-env's exact polygon test for the few candidate pairs.
        """
        if self.stock_neighbour_search:
            super().step(dt)
            return
        for vehicle in self.vehicles:
            vehicle.step(dt)
        bodies = self.vehicles + self.objects if self.objects else self.vehicles
        n = len(bodies)
        if n < 2:
            return
        pos = np.array([v.position for v in bodies])
        reach = np.array([v.diagonal / 2 + abs(v.speed) * dt for v in bodies])
        dist = np.linalg.norm(pos[:, None, :] - pos[None, :, :], axis=-1)
        close = dist <= reach[:, None] + reach[None, :]
        for i, j in zip(*np.nonzero(np.triu(close, k=1)), strict=True):
            bodies[i].handle_collisions(bodies[j], dt)  # i < j: a vehicle meets any body

    def neighbour_vehicles(
        self, vehicle: Vehicle, lane_index: LaneIndex | None = None
    ) -> tuple[Vehicle | None, Vehicle | None]:
        """Leader and follower of ``vehicle`` in lane ``lane_index`` (default: its own lane)."""
        if self.stock_neighbour_search:
            return super().neighbour_vehicles(vehicle, lane_index)
        lane_index = lane_index or vehicle.lane_index
        if not lane_index:
            return None, None
        table = self.lane_id(lane_index)
        coords = self._lane_coords[table]
        lane_vehicles = self._lane_vehicles[table]
        n = len(lane_vehicles)
        pos = int(coords.searchsorted(self.route_coordinate(vehicle), side="right"))
        ahead, behind = pos, pos - 1
        if 0 <= behind < n and lane_vehicles[behind] is vehicle:
            behind -= 1
        if self.period is None:
            front = lane_vehicles[ahead] if ahead < n else None
            rear = lane_vehicles[behind] if behind >= 0 else None
            return front, rear
        front, rear = (
            lane_vehicles[ahead % n] if n else None,
            lane_vehicles[behind % n] if n else None,
        )
        return (
            None if front is vehicle else front,
            None if rear is vehicle else rear,
        )
