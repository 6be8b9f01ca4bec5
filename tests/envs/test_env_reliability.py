"""Scenario physics that users notice: vehicles never roll backwards."""

from __future__ import annotations

import numpy as np

from mapets_rl.envs import FigureEightEnv, FreewayEnv
from mapets_rl.envs.freeway import ES


def _min_speed_over_episode(env, actions) -> float:
    lowest = np.inf
    for action in actions:
        _, _, terminated, truncated, _ = env.step(action)
        lowest = min(lowest, *(v.speed for v in env.road.vehicles))
        if terminated or truncated:
            break
    return lowest


def test_figure_eight_vehicles_never_roll_backwards() -> None:
    # bang-bang target speeds make CAVs and the humans behind them brake to a standstill
    env = FigureEightEnv({"horizon": 120})
    env.reset(seed=0)
    rng = np.random.default_rng(0)
    actions = (
        np.where(rng.random((8, 1)) < 0.5, 0.0, 13.89).astype(np.float32) for _ in range(120)
    )
    assert _min_speed_over_episode(env, actions) >= 0.0


def test_freeway_emergency_stop_ends_at_zero_speed() -> None:
    env = FreewayEnv({"n_vehicles": 12, "cav_ratio": 0.5})
    env.reset(seed=0)
    actions = [np.full(6, ES)] * 40
    assert _min_speed_over_episode(env, actions) >= 0.0
    assert min(cav.speed for cav in env.cavs) == 0.0  # the CAVs did stop
