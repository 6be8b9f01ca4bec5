"""A known-physics dynamics model of a figure-eight CAV: the planner's oracle for diagnosis.

:class:`FigureEightKinematicModel` predicts the next observation of a CAV exactly for its own
motion (the speed controller of :class:`~mapets_rl.envs.vehicles.TargetSpeedVehicle`, one 0.1 s
step) under the assumption that every other vehicle keeps its speed. It is what a perfect
learned model of the CAV's own dynamics could at best know, so planning with it separates the
planner's (and the collision predicate's) errors from the learned ensemble's: a crash under this
model is a crash the planner chose or could not foresee (a human's braking or lane change), not
a model error. It does not model lane changes (the lane position and the other lane stay as they
are; the planner's termination refuses changes into short gaps) nor the position ``(x, y)``,
which the reward does not read.
"""

from __future__ import annotations

import torch

from mapets_rl.envs.figure_eight import (
    CROSSING_OBS_DIM,
    GAP_RANGE,
    OBSERVATION_SIZES,
    TWO_LANE_OBS_DIM,
)
from mapets_rl.envs.vehicles import ACC_MAX, ACC_MIN, TargetSpeedVehicle

__all__ = ["FigureEightKinematicModel"]


class FigureEightKinematicModel:
    """Exact own-speed dynamics, constant-speed neighbours (a :class:`DynamicsModel`).

    Own speed: ``v' = v + a dt`` with ``a = KP_A (u - v)`` clipped to ``[ACC_MIN, ACC_MAX]`` and
    to ``>= -v / dt`` (no rolling backwards); the CAV advances ``v dt`` (the kinematic model
    moves by the speed at the start of the step). Neighbours and the conflicting vehicle advance
    ``v_other dt``; gaps and crossing distances change by the difference, and a feature at the
    75 m "nobody in range" value stays there. Predictions are deterministic: log-variance
    ``logvar`` (default -30) for every feature.

    Args:
        n_agents: ``I``.
        obs_dim: 7, 10 or 15 (the figure-eight's observation sizes).
        action_dim: 1 (target speed) or 2 (+ lane-change flag, ignored).
        dt: step length [s] (the figure-eight's 0.1 s).
        logvar: the predicted log-variance.
    """

    ensemble_size = 1

    def __init__(
        self,
        n_agents: int,
        obs_dim: int,
        action_dim: int,
        dt: float = 0.1,
        logvar: float = -30.0,
    ) -> None:
        if obs_dim not in OBSERVATION_SIZES:
            raise ValueError(f"obs_dim must be one of {list(OBSERVATION_SIZES)}, got {obs_dim}")
        if action_dim not in (1, 2):
            raise ValueError(f"action_dim must be 1 or 2, got {action_dim}")
        if not dt > 0:
            raise ValueError(f"dt must be > 0 seconds, got {dt}")
        self.n_agents, self.obs_dim, self.action_dim = int(n_agents), obs_dim, action_dim
        self.dt, self.logvar = float(dt), float(logvar)

    def predict(
        self, obs: torch.Tensor, action: torch.Tensor, dtype: torch.dtype = torch.float32
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Delta mean and log-variance ``[I, B, N, S]`` from ``obs [I, B, N, S]`` and
        ``action [I, B, N, A]``."""
        dt = self.dt
        v = obs[..., 0]
        acc = (TargetSpeedVehicle.KP_A * (action[..., 0] - v)).clamp(ACC_MIN, ACC_MAX)
        acc = torch.maximum(acc, -v / dt)
        delta = torch.zeros_like(obs)
        delta[..., 0] = acc * dt
        travelled = v * dt

        def approach(gap: torch.Tensor, closing: torch.Tensor) -> torch.Tensor:
            """Change of a gap that shrinks by ``closing``, 0 where nobody is in range."""
            new = (gap - closing).clamp(0.0, GAP_RANGE)
            return torch.where(gap >= GAP_RANGE, torch.zeros_like(gap), new - gap)

        delta[..., 5] = approach(obs[..., 5], travelled - obs[..., 3] * dt)
        delta[..., 6] = approach(obs[..., 6], obs[..., 4] * dt - travelled)
        if self.obs_dim >= CROSSING_OBS_DIM:
            for column, speed in ((7, v), (8, obs[..., 9])):
                d = obs[..., column]
                delta[..., column] = torch.where(d >= GAP_RANGE, torch.zeros_like(d), -speed * dt)
        if self.obs_dim == TWO_LANE_OBS_DIM:
            delta[..., 13] = approach(obs[..., 13], travelled - obs[..., 11] * dt)
            delta[..., 14] = approach(obs[..., 14], obs[..., 12] * dt - travelled)
        return delta.to(dtype), torch.full_like(delta, self.logvar, dtype=dtype)
