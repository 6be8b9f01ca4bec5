"""Video frames of both scenarios: CAVs and human drivers in their own colours, crashes marked
where they happened, a legend and a step counter; on the freeway a camera on the CAVs' mean
position (rendered off screen)."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

from mapets_rl.envs import FigureEightParallelEnv, FreewayParallelEnv, scenario_config
from mapets_rl.envs.rendering import (
    CAV_COLOR,
    CRASH_COLOR,
    HV_COLOR,
    LEGEND_BACKGROUND,
    LEGEND_ORIGIN,
    STEP_COUNTER_MARGIN,
    SWATCH,
)

pygame = pytest.importorskip("pygame")


@pytest.fixture
def crashed_freeway(monkeypatch):
    """A 6-vehicle freeway (3 CAVs) whose rearmost CAV is hit in the first step by a standing
    human driver put 2 m ahead of it; returns the raw env and the frame after that step."""
    monkeypatch.setenv("SDL_VIDEODRIVER", os.environ.get("SDL_VIDEODRIVER", "offscreen"))
    parallel = FreewayParallelEnv(
        n_vehicles=6, cav_ratio=0.5, render_mode="rgb_array", horizon=4, spawn_length=100.0
    )
    env = parallel.env
    parallel.reset(seed=0)
    cav = env.cavs[0]
    hv = next(v for v in env.road.vehicles if all(v is not c for c in env.cavs))
    hv.lane_index = hv.target_lane_index = cav.lane_index
    hv.lane = cav.lane
    hv.position = cav.position + np.array([2.0, 0.0])
    hv.speed = 0.0
    parallel.step_joint(env.scripted_action())
    try:
        frame = env.render()
    except pygame.error as err:  # pragma: no cover - depends on the SDL build
        pytest.skip(f"pygame cannot render off screen here: {err}")
    return env, frame


def _near(frame: np.ndarray, pixel: tuple[int, int], color: tuple[int, int, int], r: int = 3):
    """Whether ``color`` occurs within ``r`` pixels of ``pixel`` (x, y)."""
    x, y = pixel
    patch = frame[max(y - r, 0) : y + r + 1, max(x - r, 0) : x + r + 1]
    return bool((patch == np.array(color, dtype=np.uint8)).all(-1).any())


def test_cavs_and_human_drivers_have_their_own_colours(crashed_freeway) -> None:
    env, frame = crashed_freeway
    assert frame.shape == (200, 900, 3) and frame.dtype == np.uint8
    surface = env.viewer.sim_surface
    cav_ids = {id(c) for c in env.cavs}
    seen = {"cav": 0, "hv": 0}
    for vehicle in env.road.vehicles:
        x, y = surface.pos2pix(*vehicle.position)
        if not (0 <= x < 900 and 0 <= y < 200):
            continue
        is_cav = id(vehicle) in cav_ids
        assert tuple(frame[y, x]) == (CAV_COLOR if is_cav else HV_COLOR)
        seen["cav" if is_cav else "hv"] += 1
    assert seen["cav"] >= 1 and seen["hv"] >= 1


def test_crashed_vehicles_stay_marked(crashed_freeway) -> None:
    env, frame = crashed_freeway
    assert not env.alive[0] and len(env.crash_sites) == 2  # the CAV and the human driver
    assert sorted(env.crash_sites.is_cav) == [False, True]
    surface = env.viewer.sim_surface
    red = (frame == np.array(CRASH_COLOR, dtype=np.uint8)).all(-1)
    red[: LEGEND_ORIGIN[1] + 3 * (SWATCH + 4) + 4, : LEGEND_ORIGIN[0] + 150] = False  # legend
    for position in env.crash_sites.positions:
        x, y = surface.pos2pix(*position)
        assert 0 <= x < 900 and 0 <= y < 200
        assert _near(frame, (x, y), CRASH_COLOR, r=12)
        red[max(y - 12, 0) : y + 13, max(x - 12, 0) : x + 13] = False
    assert red.sum() == 0  # nothing but the crash sites is drawn in the marker colour
    assert all(not v.crashed for v in env.road.vehicles)  # they left the road, marks stay
    # a new episode starts without marks
    env.reset(seed=1)
    assert len(env.crash_sites) == 0


def test_camera_follows_the_cavs_and_legend_names_the_colours(crashed_freeway) -> None:
    env, frame = crashed_freeway
    surface = env.viewer.sim_surface
    for _ in range(2):
        centre = surface.pos2pix(*env.view_centre)
        assert abs(centre[0] - 450) <= 1 and abs(centre[1] - 100) <= 1
        alive = [c.position for i, c in enumerate(env.cavs) if env.alive[i]]
        assert np.allclose(env.view_centre, np.mean(alive, axis=0))
        env.step(env.scripted_action())
        frame = env.render()
    x0, y0 = LEGEND_ORIGIN
    row = SWATCH + 4
    for k, color in enumerate((CAV_COLOR, HV_COLOR, CRASH_COLOR)):
        middle = (x0 + 4 + SWATCH // 2, y0 + 4 + k * row + SWATCH // 2)
        assert tuple(frame[middle[1], middle[0]]) == color


# --------------------------------------------------------------------------- figure-eight
EGO_YELLOW = (200, 200, 0)
"""highway-env's colour of a controlled vehicle without a colour of its own."""


def _render(env) -> np.ndarray:
    try:
        return env.render()
    except pygame.error as err:  # pragma: no cover - depends on the SDL build
        pytest.skip(f"pygame cannot render off screen here: {err}")


@pytest.fixture
def crashed_figure_eight(monkeypatch):
    """A figure-eight with 3 CAVs and 3 human drivers whose first CAV is hit in the first step
    by a standing human driver put 2 m ahead of it on its lane; returns the raw env and the
    frames after reset and after that step."""
    monkeypatch.setenv("SDL_VIDEODRIVER", os.environ.get("SDL_VIDEODRIVER", "offscreen"))
    parallel = FigureEightParallelEnv(n_cavs=3, n_hvs=3, render_mode="rgb_array", horizon=6)
    env = parallel.env
    parallel.reset(seed=0)
    first = _render(env)
    cav = env.cavs[0]
    hv = next(v for v in env.road.vehicles if all(v is not c for c in env.cavs))
    s, _ = cav.lane.local_coordinates(cav.position)
    hv.lane_index = hv.target_lane_index = cav.lane_index
    hv.lane = cav.lane
    hv.position = cav.lane.position(s + 2.0, 0.0)
    hv.heading = cav.lane.heading_at(s + 2.0)
    hv.speed = hv.target_speed = 0.0
    parallel.step_joint(env.scripted_action())
    return env, first, _render(env)


def _legend_swatches(frame: np.ndarray) -> list[tuple[int, ...]]:
    x0, y0 = LEGEND_ORIGIN
    row = SWATCH + 4
    return [tuple(frame[y0 + 4 + k * row + SWATCH // 2, x0 + 4 + SWATCH // 2]) for k in range(3)]


def _step_counter(frame: np.ndarray) -> np.ndarray:
    """The top-right corner where the step counter is drawn."""
    return frame[: STEP_COUNTER_MARGIN + 24, -(STEP_COUNTER_MARGIN + 90) :]


def test_figure_eight_cavs_are_green_and_the_frame_has_a_legend(crashed_figure_eight) -> None:
    env, first, frame = crashed_figure_eight
    assert frame.shape == (400, 640, 3) and frame.dtype == np.uint8
    surface = env.viewer.sim_surface
    cav_ids = {id(c) for c in env.cavs}
    seen = {"cav": 0, "hv": 0}
    for vehicle in env.road.vehicles:
        x, y = surface.pos2pix(*vehicle.position)
        is_cav = id(vehicle) in cav_ids
        assert tuple(frame[y, x]) == (CAV_COLOR if is_cav else HV_COLOR)
        seen["cav" if is_cav else "hv"] += 1
    assert seen == {"cav": 2, "hv": 2}  # the crashed pair left the road
    for image in (first, frame):
        assert not (image == np.array(EGO_YELLOW, dtype=np.uint8)).all(-1).any()
        assert _legend_swatches(image) == [CAV_COLOR, HV_COLOR, CRASH_COLOR]


def test_figure_eight_crashes_stay_marked(crashed_figure_eight) -> None:
    env, _, frame = crashed_figure_eight
    assert not env.alive[0] and len(env.crash_sites) == 2
    assert sorted(env.crash_sites.is_cav) == [False, True]
    surface = env.viewer.sim_surface
    for position in env.crash_sites.positions:
        assert _near(frame, surface.pos2pix(*position), CRASH_COLOR, r=12)
    env.step(env.scripted_action())
    later = _render(env)
    for position in env.crash_sites.positions:  # still marked a step later
        assert _near(later, surface.pos2pix(*position), CRASH_COLOR, r=12)
    env.reset(seed=1)
    assert len(env.crash_sites) == 0


@pytest.mark.parametrize("scenario", ["figure-eight", "freeway"])
def test_frames_count_the_steps(scenario: str, monkeypatch) -> None:
    monkeypatch.setenv("SDL_VIDEODRIVER", os.environ.get("SDL_VIDEODRIVER", "offscreen"))
    if scenario == "freeway":
        parallel = FreewayParallelEnv(
            n_vehicles=4, cav_ratio=0.5, render_mode="rgb_array", horizon=4, spawn_length=100.0
        )
    else:
        parallel = FigureEightParallelEnv(n_cavs=2, n_hvs=1, render_mode="rgb_array", horizon=4)
    env = parallel.env
    parallel.reset(seed=0)
    counters = [_step_counter(_render(env))]
    for _ in range(2):
        parallel.step_joint(env.scripted_action())
        counters.append(_step_counter(_render(env)))
    for counter in counters:
        corner = counter[STEP_COUNTER_MARGIN + 1, -(STEP_COUNTER_MARGIN + 2)]
        assert tuple(corner) == LEGEND_BACKGROUND  # the counter's box
        assert (counter < 60).all(-1).any()  # its dark text
    assert not np.array_equal(counters[0], counters[1])
    assert not np.array_equal(counters[1], counters[2])
    env.reset(seed=0)
    assert np.array_equal(_step_counter(_render(env)), counters[0])  # step 0 again


def test_the_figure_eight_evaluation_video_carries_colours_legend_and_steps(
    tmp_path: Path,
) -> None:
    import imageio.v2 as imageio

    from mapets_rl.recipes.mappo import MAPPO, MAPPOConfig

    config = MAPPOConfig(
        env="figure-eight",
        env_config={"n_cavs": 2, "n_hvs": 1, "horizon": 3},
        progress=False,
        logger="none",
    )
    MAPPO(config, tmp_path).evaluate(episodes=1, video=True)
    frames = [
        np.asarray(f)[..., :3]
        for f in imageio.mimread(tmp_path / "videos" / "eval_000000000000.gif")
    ]
    assert len(frames) == 3

    def close(a: np.ndarray, color: tuple[int, int, int]) -> np.ndarray:
        return (np.abs(a.astype(int) - np.array(color)) <= 8).all(-1)

    for frame in frames:
        assert close(frame, CAV_COLOR).sum() >= 20  # two green CAVs
        assert not close(frame, EGO_YELLOW).any()
        swatches = _legend_swatches(frame)
        assert all(
            close(np.array([s]), c)[0]
            for s, c in zip(swatches, (CAV_COLOR, HV_COLOR, CRASH_COLOR), strict=True)
        )
    assert not np.array_equal(_step_counter(frames[0]), _step_counter(frames[1]))


class _StepCountingMAPPO:
    """A MAPPO whose evaluation env carries an observation transform (as MA-PETS's tile-coded
    variant does): the GIF's frame rate must still be read from the scenario inside."""

    def observation_transforms(self) -> list:
        from torchrl.envs import StepCounter

        return [StepCounter()]


@pytest.mark.parametrize(
    ("scenario", "backend", "transformed", "period_ms"),
    [
        ("freeway", "highway", False, 1000),
        ("freeway", "torch", False, 1000),
        ("freeway", "highway", True, 1000),
        ("freeway-merge", "highway", False, 1000),
        ("figure-eight", "highway", False, 100),
    ],
)
def test_evaluation_gif_plays_one_frame_per_policy_step(
    scenario: str, backend: str, transformed: bool, period_ms: int, tmp_path: Path
) -> None:
    from PIL import Image

    from mapets_rl.recipes.mappo import MAPPO, MAPPOConfig

    if scenario == "figure-eight":
        env_config = {"n_cavs": 2, "n_hvs": 1, "horizon": 3}
    else:
        env_config = {"n_vehicles": 4, "cav_ratio": 0.5, "horizon": 3, "spawn_length": 100.0}
        if backend == "torch":
            env_config["backend"] = "torch"
    config = MAPPOConfig(env=scenario, env_config=env_config, progress=False, logger="none")
    recipe = type("Transformed", (_StepCountingMAPPO, MAPPO), {}) if transformed else MAPPO
    exp = recipe(config, tmp_path)
    exp.evaluate(episodes=1, video=True)
    # the scenario's own step (freeways 1 s, figure-eight 0.1 s) sets the frame duration
    assert scenario_config(exp._video_env)["policy_frequency"] * period_ms == 1000
    with Image.open(tmp_path / "videos" / "eval_000000000000.gif") as gif:
        assert gif.n_frames == 3
        durations = []
        for index in range(gif.n_frames):
            gif.seek(index)
            durations.append(gif.info["duration"])
    assert durations == [period_ms] * 3
