"""The freeway-merge camera stays on the merge area (issue 52): the merge point and the
acceleration lane are in every frame of an episode, on both backends (the freeway's camera on
the CAVs had left the ramp behind by step 21)."""

from __future__ import annotations

import os

import numpy as np
import pytest
from highway_env.road.lane import StraightLane

from mapets_rl.envs import FreewayMergeParallelEnv, make_env
from mapets_rl.envs.freeway_merge import MERGE_VIEW_POINT

pytest.importorskip("pygame")
STEPS = 25
CONFIG = {"n_vehicles": 8, "cav_ratio": 0.5, "horizon": STEPS, "spawn_length": 200.0}


def _in_frame(surface, frame: np.ndarray, x: float, y: float) -> bool:
    col, row = surface.pos2pix(x, y)
    return 0 <= col < frame.shape[1] and 0 <= row < frame.shape[0]


def _merge_in_view(env, frame: np.ndarray) -> None:
    """The acceleration lane's start and the merge point (its end) are in the frame, the merge
    point at :data:`MERGE_VIEW_POINT` of its width."""
    surface = env.viewer.sim_surface
    y = env.config["lanes"] * StraightLane.DEFAULT_WIDTH  # the acceleration lane's centre
    assert _in_frame(surface, frame, env.config["merge_start"], y)
    assert _in_frame(surface, frame, env.merge_end, y)
    col, _ = surface.pos2pix(env.merge_end, y)
    assert abs(col - MERGE_VIEW_POINT * frame.shape[1]) <= 1


def test_the_merge_stays_in_view_for_the_whole_episode(monkeypatch) -> None:
    monkeypatch.setenv("SDL_VIDEODRIVER", os.environ.get("SDL_VIDEODRIVER", "offscreen"))
    parallel = FreewayMergeParallelEnv(render_mode="rgb_array", **CONFIG)
    env = parallel.env
    parallel.reset(seed=0)
    for step in range(STEPS):
        frame = env.render()
        _merge_in_view(env, frame)
        if step == 21:  # the CAVs have driven far past the merge: the view stayed
            cavs = [c.position[0] for i, c in enumerate(env.cavs) if env.alive[i]]
            assert not cavs or min(cavs) > env.merge_end
        parallel.step_joint(env.scripted_action())


def test_the_torch_backend_frames_the_merge_too(monkeypatch) -> None:
    monkeypatch.setenv("SDL_VIDEODRIVER", os.environ.get("SDL_VIDEODRIVER", "offscreen"))
    env = make_env("freeway-merge", backend="torch", render_mode="rgb_array", **CONFIG)
    env.reset()
    frame = env.render()
    _merge_in_view(env._viewer_env, frame)
    env.close()
