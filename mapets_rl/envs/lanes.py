"""highway-env lanes whose per-call geometry is plain float math.

``StraightLane.local_coordinates`` and ``CircularLane.local_coordinates`` / ``heading_at`` are
called several times per vehicle and simulation step (steering control, lane tracking, route
coordinates). The stock versions run NumPy ufuncs on two-element arrays and NumPy scalars, whose
per-call overhead dominates; these subclasses compute the same expressions, in the same order,
with Python floats and ``math`` (the results are the same numbers, see ``tests/envs/test_envs.py``).
"""

from __future__ import annotations

import math

import numpy as np
from highway_env import utils
from highway_env.road.lane import CircularLane, StraightLane


class FastStraightLane(StraightLane):
    """``StraightLane`` with float-math ``local_coordinates``."""

    def __init__(self, *args: object, **kwargs: object) -> None:
        super().__init__(*args, **kwargs)
        self._start_xy = (float(self.start[0]), float(self.start[1]))
        self._direction_xy = (float(self.direction[0]), float(self.direction[1]))
        self._lateral_xy = (float(self.direction_lateral[0]), float(self.direction_lateral[1]))

    def local_coordinates(self, position: np.ndarray) -> tuple[float, float]:
        """``(longitudinal, lateral)`` [m] of the ``[2]`` world ``position`` on this lane."""
        x, y = position.tolist()
        dx, dy = x - self._start_xy[0], y - self._start_xy[1]
        return (
            dx * self._direction_xy[0] + dy * self._direction_xy[1],
            dx * self._lateral_xy[0] + dy * self._lateral_xy[1],
        )


class FastCircularLane(CircularLane):
    """``CircularLane`` with float-math ``local_coordinates`` and ``heading_at``."""

    def __init__(self, *args: object, **kwargs: object) -> None:
        super().__init__(*args, **kwargs)
        self._center_xy = (float(self.center[0]), float(self.center[1]))

    def heading_at(self, longitudinal: float) -> float:
        """Heading [rad] of the lane at ``longitudinal`` [m]."""
        phi = self.direction * longitudinal / self.radius + self.start_phase
        return phi + math.pi / 2 * self.direction

    def local_coordinates(self, position: np.ndarray) -> tuple[float, float]:
        """``(longitudinal, lateral)`` [m] of the ``[2]`` world ``position`` on this lane."""
        x, y = position.tolist()
        dx, dy = x - self._center_xy[0], y - self._center_xy[1]
        phi = math.atan2(dy, dx)
        phi = self.start_phase + utils.wrap_to_pi(phi - self.start_phase)
        r = math.sqrt(dx * dx + dy * dy)
        return (
            self.direction * (phi - self.start_phase) * self.radius,
            self.direction * (self.radius - r),
        )
