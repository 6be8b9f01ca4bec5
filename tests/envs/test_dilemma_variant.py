"""The dilemma variant of ``freeway-merge`` (issue 50): with ``ramp_forcing`` off a ramp CAV's
Change Left / Right on the acceleration lane is Keep Lane (it merges only by MOBIL, as a ramp
human does), and ``lane_change_comfort`` is what a lane change earns, the same on both
backends; the variant's settings follow highway-env as the defaults do; the defaults keep
forcing and eq. 9's comfort."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from mapets_rl.envs import FreewayMergeEnv, make_env
from mapets_rl.envs.freeway import CL, CR, KL
from mapets_rl.envs.freeway_merge import BEHAVIOUR_COUNTS
from mapets_rl.envs.torch_freeway.highway_state import load_scene
from mapets_rl.envs.torch_freeway.native import kernel_unavailable, load_kernel
from mapets_rl.envs.torch_freeway.simulator import BatchedFreeway
from mapets_rl.experiment.published import load_published

SCENE = {"merge_start": 800.0, "merge_length": 100.0, "perception": 100.0}
"""Acceleration lane from x = 800 to 900 (y = 12, lane 3)."""
ACCELERATION = ("0", "1", 3)
RIGHT = ("0", "1", 2)
KERNELS = ["native", "torch"]
STACK = load_published("fragments/freeway-merge-dilemma-stack").fields["env_config"]
VARIANT = {
    key: value
    for key, value in STACK.items()
    if key not in ("backend", "num_envs", "shield")  # highway-env steps one road, unshielded
}
"""The dilemma study's scenario settings (its shipped fragment), on one highway-env road."""


def _kernel(kernel: str) -> str:
    if kernel == "native" and load_kernel() is None:
        pytest.skip(f"fused CPU kernel unavailable: {kernel_unavailable()}")
    return kernel


def _scene(placements: list[tuple[tuple, float, float]], **config: object) -> FreewayMergeEnv:
    """A 3-vehicle ``freeway-merge`` of CAVs (``env.cavs`` in ``placements``' order) with every
    vehicle put at ``(lane index, x [m], speed [m/s])``."""
    env = FreewayMergeEnv({"n_vehicles": 3, "cav_ratio": 1.0, "ramp_fraction": 1 / 3,
                           **SCENE, **config})  # fmt: skip
    env.reset(seed=0)
    for vehicle, (lane_index, x, speed) in zip(env.cavs, placements, strict=True):
        lane = env.road.network.get_lane(lane_index)
        vehicle.position = lane.position(x - lane.start[0], 0.0)
        vehicle.heading = lane.heading_at(x - lane.start[0])
        vehicle.lane_index = vehicle.target_lane_index = lane_index
        vehicle.lane, vehicle.speed = lane, speed
    env.road.refresh()
    return env


BESIDE = [(ACCELERATION, 820.0, 20.0), (RIGHT, 818.0, 20.0), (("0", "1", 0), 1500.0, 25.0)]
"""A ramp CAV on the acceleration lane with a CAV of the rightmost lane just beside it: MOBIL
finds no safe gap, a forced Change Left would cut in."""


@pytest.mark.parametrize("kernel", KERNELS)
@pytest.mark.parametrize("forcing", [True, False])
def test_a_change_left_on_the_acceleration_lane_forces_only_with_ramp_forcing(
    forcing: bool, kernel: str
) -> None:
    """Beside a mainline CAV, the ramp CAV's Change Left starts a change at once with
    ``ramp_forcing`` (the default) and is refused without it: it stays on the acceleration
    lane, the same on both backends."""
    env = _scene(BESIDE, ramp_forcing=forcing)
    sim = BatchedFreeway(dict(env.config), True, 1, dtype=torch.float64, kernel=_kernel(kernel))
    load_scene(sim, 0, env)
    env.step(np.array([CL, KL, KL]))
    sim.step(torch.tensor([[CL, KL, KL]]))
    target = sim.state["bodies", "target"][0, sim.state["agents", "slot"][0, 0]]
    assert env.cavs[0].target_lane_index == (RIGHT if forcing else ACCELERATION)
    assert int(target) == (2 if forcing else 3)
    assert env.cavs[0].decision == (CL if forcing else KL)


@pytest.mark.parametrize("kernel", KERNELS)
def test_without_forcing_change_left_or_right_on_the_ramp_is_keep_lane(kernel: str) -> None:
    """Without ``ramp_forcing`` a ramp CAV playing Change Left or Change Right on the
    acceleration lane drives, and is paid, exactly as with Keep Lane: MOBIL finds the gap and
    merges it, counted as a MOBIL merge (no forced merge), the same on both backends."""
    free = [(ACCELERATION, 820.0, 20.0), (("0", "1", 0), 1500.0, 25.0),
            (("0", "1", 0), 1600.0, 25.0)]  # fmt: skip
    runs = []
    for ramp_action in (KL, CL, CR):
        env = _scene(free, ramp_forcing=False)
        sim = BatchedFreeway(dict(env.config), True, 1, dtype=torch.float64,
                             kernel=_kernel(kernel))  # fmt: skip
        load_scene(sim, 0, env)
        rewards = []
        for step in range(4):  # merged by MOBIL in the first step, then Keep Lane
            action = [ramp_action if step == 0 else KL, KL, KL]
            *_, info = env.step(np.array(action))
            reward = info["agent_rewards"]
            result = sim.step(torch.tensor([action]))
            np.testing.assert_allclose(result.reward[0].numpy(), reward, atol=1e-3)
            rewards.append(reward)
        batched = sim.episode_metrics()
        counts = {key: int(batched[key][0]) for key in BEHAVIOUR_COUNTS}
        assert counts == {key: env.episode_metrics()[key] for key in BEHAVIOUR_COUNTS}
        runs.append((np.array(rewards), np.array([v.position for v in env.vehicles_all]), counts))
    for rewards, positions, counts in runs:
        np.testing.assert_array_equal(rewards, runs[0][0])
        np.testing.assert_array_equal(positions, runs[0][1])
        assert counts["ramp_mobil_merges"] == 1 and counts["ramp_forced_merges"] == 0


@pytest.mark.parametrize("kernel", KERNELS)
def test_lane_change_comfort_is_what_a_lane_change_earns_on_both_backends(kernel: str) -> None:
    """A mainline CAV's Change Left earns ``lane_change_comfort`` (eq. 9's 1 by default) in
    place of comfort: under 0 the step of the move (the change ends within it) is paid exactly
    1 less and the next step the same, on both backends."""
    placements = [(RIGHT, 300.0, 25.0), (("0", "1", 0), 1500.0, 25.0),
                  (ACCELERATION, 820.0, 20.0)]  # fmt: skip
    paid = {}
    for comfort in (1.0, 0.0):
        env = _scene(placements, lane_change_comfort=comfort)
        sim = BatchedFreeway(dict(env.config), True, 1, dtype=torch.float64,
                             kernel=_kernel(kernel))  # fmt: skip
        load_scene(sim, 0, env)
        rewards = []
        for action in ([CL, KL, KL], [KL, KL, KL]):
            *_, info = env.step(np.array(action))
            result = sim.step(torch.tensor([action]))
            np.testing.assert_allclose(result.reward[0].numpy(), info["agent_rewards"], atol=1e-3)
            rewards.append(info["agent_rewards"][0])
        paid[comfort] = np.array(rewards)
    np.testing.assert_allclose(paid[1.0] - paid[0.0], [1.0, 0.0], atol=1e-5)


def test_ramp_forcing_is_checked_and_defaults_to_forcing() -> None:
    assert FreewayMergeEnv.default_config()["ramp_forcing"] is True
    with pytest.raises(ValueError, match="ramp_forcing must be True or False, got 'no'"):
        FreewayMergeEnv({"ramp_forcing": "no"})
    with pytest.raises(ValueError, match="ramp_forcing must be True or False, got 1"):
        make_env("freeway-merge", backend="torch", num_envs=1, ramp_forcing=1)
    with pytest.raises(ValueError, match="lane_change_comfort"):
        FreewayMergeEnv({"lane_change_comfort": -1.0})


@pytest.mark.parametrize("kernel", KERNELS)
def test_the_variant_follows_highway_env(kernel: str) -> None:
    """From a recorded highway-env scene under the dilemma settings, 40 steps of random
    decisions (Change Left drawn often, so ramp CAVs try to force) give the same rewards,
    observations, episode metrics (no forced merge) and positions on both simulators, within
    the tolerance of the calibration test of the defaults (``test_torch_freeway.py``)."""
    env = FreewayMergeEnv({"n_vehicles": 30, **VARIANT})
    env.reset(seed=2)
    sim = BatchedFreeway(dict(env.config), True, 1, dtype=torch.float64, kernel=_kernel(kernel))
    load_scene(sim, 0, env)
    rng = np.random.default_rng(2)
    tolerance = 1e-3 if kernel == "native" else 0.5
    for _ in range(40):
        action = rng.choice([KL, KL, CL, CL, CR], size=env.config["n_cavs"])
        obs, _, terminated, truncated, info = env.step(action)
        result = sim.step(torch.as_tensor(action)[None])
        np.testing.assert_allclose(result.reward[0].numpy(), info["agent_rewards"], atol=tolerance)
        np.testing.assert_allclose(result.observation[0].numpy(), obs, atol=tolerance)
        if terminated or truncated:
            break
    ours = torch.stack([sim.state["bodies", "x"], sim.state["bodies", "y"]], -1)[0, :30]
    assert np.abs(ours.numpy() - np.array([v.position for v in env.vehicles_all])).max() < 0.5
    expected = env.episode_metrics()
    assert expected["ramp_forced_merges"] == 0 and expected["ramp_mobil_merges"] > 0
    for key, value in sim.episode_metrics().items():
        assert float(value[0]) == pytest.approx(expected[key], rel=1e-3, abs=1e-6), key
