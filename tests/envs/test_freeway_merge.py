"""The ``freeway-merge`` scenario (issue 21): API conformance, the merge features on constructed
scenes, ramp vehicles merging, ramp actions, one target-speed range, rendering, bad config."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
from pettingzoo.test import parallel_api_test
from torchrl.envs.utils import check_env_specs

from mapets_rl.envs import (
    GYM_IDS,
    FreewayMergeEnv,
    FreewayMergeParallelEnv,
    make_env,
    registered_scenario,
)
from mapets_rl.envs.freeway import CL, CR, KL
from mapets_rl.envs.freeway_merge import OBS_DIM, RAMP_ROAD

SCENE = {"merge_start": 800.0, "merge_length": 100.0, "perception": 100.0}
"""Geometry of the constructed scenes: acceleration lane from x = 800 to the merge point at
x = 900 (y = 12), ramp lane id 3."""


def test_registered_like_the_other_scenarios() -> None:
    assert registered_scenario("freeway-merge").parallel_env is FreewayMergeParallelEnv
    env = gym.make(GYM_IDS["freeway-merge"])
    assert isinstance(env.unwrapped, FreewayMergeEnv)
    obs, _ = env.reset(seed=0)
    assert obs.shape == (30, OBS_DIM)
    env.close()


def test_pettingzoo_parallel_api() -> None:
    parallel_api_test(FreewayMergeParallelEnv(n_vehicles=8, cav_ratio=0.5, horizon=10), 40)


def test_torchrl_env_specs_and_keys() -> None:
    env = make_env("freeway-merge", seed=0, n_vehicles=8)
    check_env_specs(env)
    td = env.rollout(5)
    assert td["agents", "observation"].shape == (5, 8, OBS_DIM)
    assert td["agents", "action"].shape == (5, 8, 4)
    assert td["next", "agents", "reward"].shape == (5, 8, 1)


def _scene(**config) -> FreewayMergeEnv:
    """An env after reset with 3 vehicles, one CAV (``env.cavs[0]``), to be re-placed."""
    env = FreewayMergeEnv(
        {"n_vehicles": 3, "cav_ratio": 1 / 3, "ramp_fraction": 1 / 3, **SCENE, **config}
    )
    env.reset(seed=0)
    return env


def _place(env: FreewayMergeEnv, vehicle, lane_index: tuple, x: float, speed: float) -> None:
    lane = env.road.network.get_lane(lane_index)
    s = (x - lane.start[0]) / lane.direction[0]  # the ramp lane slants: x is not s
    vehicle.position = lane.position(s, 0.0)
    vehicle.heading = lane.heading_at(s)
    vehicle.lane_index = vehicle.target_lane_index = lane_index
    vehicle.lane, vehicle.speed = lane, speed


def _others(env: FreewayMergeEnv) -> list:
    return [v for v in env.road.vehicles if v is not env.cavs[0]]


def test_mainline_cav_sees_the_ramp_and_the_merge_point() -> None:
    env = _scene()
    cav, (a, b) = env.cavs[0], _others(env)
    _place(env, cav, ("0", "1", 2), 770.0, 25.0)
    _place(env, a, ("0", "1", 3), 810.0, 15.0)  # on the acceleration lane, 40 m ahead
    _place(env, b, ("0", "1", 1), 720.0, 27.0)  # left lane, 50 m behind
    env.road.refresh()
    obs = env.observe_agents()[0]
    nb = obs[4:22].reshape(3, 2, 3)
    assert obs[0] == pytest.approx(25.0) and obs[1] == 2.0
    np.testing.assert_allclose(nb[0], [[0, 100, 0], [1, -50, 2]], atol=1e-5)  # left: lane 1
    np.testing.assert_allclose(nb[1], [[0, 100, 0], [0, -100, 0]], atol=1e-5)  # own: lane 2
    np.testing.assert_allclose(nb[2], [[1, 40, -10], [0, -100, 0]], atol=1e-5)  # right: ramp
    np.testing.assert_allclose(obs[22:], [30.0, 100.0])  # 130 m to the merge point, clipped


def test_the_end_of_the_ramp_is_not_a_neighbour() -> None:
    env = _scene()
    cav, (a, b) = env.cavs[0], _others(env)
    _place(env, cav, ("0", "1", 2), 850.0, 25.0)  # the obstacle is 50 m ahead on the ramp
    _place(env, a, ("0", "1", 0), 1500.0, 25.0)
    _place(env, b, ("0", "1", 0), 1600.0, 25.0)
    env.road.refresh()
    assert env.road.neighbour_vehicles(cav, ("0", "1", 3))[0] is env.road.objects[0]
    obs = env.observe_agents()[0]
    np.testing.assert_allclose(obs[4:22].reshape(3, 2, 3)[2, 0], [0, 100, 0])
    np.testing.assert_allclose(obs[22:], [-50.0, 50.0])


def test_ramp_cav_sees_the_rightmost_lane_on_its_left() -> None:
    env = _scene()
    cav, (a, b) = env.cavs[0], _others(env)
    _place(env, cav, ("0", "1", 3), 820.0, 20.0)
    _place(env, a, ("0", "1", 2), 800.0, 26.0)  # left rear, 20 m behind
    _place(env, b, (*RAMP_ROAD, 0), 700.0, 15.0)  # on the slanted ramp, 120 m behind
    env.road.refresh()
    obs = env.observe_agents()[0]
    nb = obs[4:22].reshape(3, 2, 3)
    assert obs[1] == 3.0
    np.testing.assert_allclose(nb[0], [[0, 100, 0], [1, -20, 6]], atol=1e-4)
    np.testing.assert_allclose(nb[1], [[0, 100, 0], [0, -100, 0]], atol=1e-4)  # b beyond 100 m
    np.testing.assert_allclose(nb[2], [[0, 100, 0], [0, -100, 0]])  # nothing right of the ramp
    np.testing.assert_allclose(obs[22:], [-20.0, 80.0])
    _place(env, b, (*RAMP_ROAD, 0), 760.0, 15.0)
    env.road.refresh()
    np.testing.assert_allclose(env.observe_agents()[0][4:22].reshape(3, 2, 3)[1, 1], [1, -60, -5])


def _ramp_vehicles(env: FreewayMergeEnv) -> list:
    return [v for v in env.road.vehicles if env.on_ramp(v)]


def test_team_reward_pays_every_cav_the_mean_and_keeps_the_system_reward() -> None:
    """``team_reward=True``: on the same episode (same seed, same actions, a crash included)
    every driving CAV is paid the mean of the CAVs' own rewards, so the system reward (the sum
    over CAVs) of every step is unchanged and the CAVs' rewards are equal."""
    per_step = {}
    for team in (False, True):
        env = FreewayMergeEnv({"n_vehicles": 12, "cav_ratio": 1.0, "team_reward": team})
        env.reset(seed=4)
        rewards = []
        for t in range(15):
            actions = np.where(np.arange(len(env.cavs)) % 3 == t % 3, CL, KL)
            _, _, terminated, truncated, info = env.step(actions)
            rewards.append(np.asarray(info["agent_rewards"], dtype=np.float64).copy())
            if terminated or truncated:
                break
        per_step[team] = rewards
    own, team = per_step[False], per_step[True]
    assert len(own) == len(team) and any(np.ptp(r) > 0 for r in own)
    for r_own, r_team in zip(own, team, strict=True):
        assert r_team.sum() == pytest.approx(r_own.sum(), rel=1e-5)
        paid = r_team != 0
        assert np.allclose(r_team[paid], r_team[paid][0])


@pytest.mark.parametrize("cav_ratio", [0.0, 1.0])
def test_ramp_vehicles_merge_into_a_free_rightmost_lane(cav_ratio: float) -> None:
    """Humans (MOBIL) and CAVs playing KL on the ramp (MOBIL) join the rightmost lane when
    nobody drives there: every vehicle starts on the ramp."""
    env = FreewayMergeEnv({"n_vehicles": 6, "cav_ratio": cav_ratio, "ramp_fraction": 1.0})
    env.reset(seed=0)
    ramp = _ramp_vehicles(env)
    assert len(ramp) == 6
    for _ in range(40):
        _, _, terminated, truncated, info = env.step(np.full(len(env.cavs), KL))
    assert truncated and not terminated and int((~env.alive).sum()) == 0
    assert info["episode"]["ramp_stuck"] == 0 and not _ramp_vehicles(env)
    for vehicle in ramp:
        assert vehicle in env.road.vehicles and not vehicle.crashed
        assert vehicle.lane_index[:2] == ("0", "1") and vehicle.lane_index[2] in (0, 1, 2)
        assert vehicle.position[0] > env.merge_end


def test_a_ramp_vehicle_without_a_gap_stops_before_the_merge_point() -> None:
    """A slow ramp vehicle beside a platoon in the rightmost lane cannot merge (MOBIL refuses
    the gaps: too much braking for the new follower), stops before the obstacle at the end of
    the acceleration lane and, standing, stays there after the platoon has passed."""
    env = _scene(n_vehicles=6, cav_ratio=1 / 6, ramp_fraction=1 / 6, merge_length=45.0)
    cav, others = env.cavs[0], _others(env)
    ramp_vehicle, platoon = others[0], [cav, *others[1:]]
    _place(env, ramp_vehicle, ("0", "1", 3), 825.0, 6.0)  # 20 m before the obstacle (x = 845)
    for k, vehicle in enumerate(platoon):
        _place(env, vehicle, ("0", "1", 2), 700.0 + 25.0 * k, 25.0)
        vehicle.target_speed = 25.0
    env.road.refresh()
    for _ in range(15):
        env.step(np.array([KL]))
    assert env.on_ramp(ramp_vehicle) and ramp_vehicle.speed < 1.0 and not ramp_vehicle.crashed
    assert 825.0 < ramp_vehicle.position[0] < env.merge_end
    assert all(v.position[0] > env.merge_end + 100 for v in platoon)  # the platoon is gone
    assert env.episode_metrics()["ramp_stuck"] == 1


def test_lane_actions_on_the_ramp_and_beside_it() -> None:
    env = _scene()
    cav = env.cavs[0]
    _place(env, cav, (*RAMP_ROAD, 0), 700.0, 15.0)
    env.road.refresh()
    for action in (CL, CR):
        env.action_type.act(np.array([action]))
        assert cav.decision == KL and cav.target_lane_index == (*RAMP_ROAD, 0)
    _place(env, cav, ("0", "1", 2), 700.0, 25.0)
    env.action_type.act(np.array([CR]))  # the acceleration lane is not a lane to drive in
    assert cav.target_lane_index == ("0", "1", 2)
    _place(env, cav, ("0", "1", 3), 820.0, 20.0)
    env.action_type.act(np.array([CL]))  # CL on the acceleration lane merges at once
    assert cav.target_lane_index == ("0", "1", 2)


def test_cavs_and_humans_draw_target_speeds_from_one_range() -> None:
    env = FreewayMergeEnv({"n_vehicles": 30, "cav_ratio": 0.5, "target_speed": (22.0, 30.0)})
    env.reset(seed=3)
    cavs = {id(v) for v in env.cavs}
    speeds = {True: [], False: []}
    for vehicle in env.road.vehicles:
        speeds[id(vehicle) in cavs].append(vehicle.target_speed)
    for group in speeds.values():
        assert len(group) == 15
        assert min(group) >= 22.0 and max(group) <= 30.0 and max(group) - min(group) > 2.0


def test_rendering_shows_the_ramp() -> None:
    env = FreewayMergeEnv({"n_vehicles": 8, **SCENE}, render_mode="rgb_array")
    env.reset(seed=0)
    for cav in env.cavs:  # the camera follows the CAVs: bring them to the merge
        _place(env, cav, ("0", "1", 1), 850.0, 25.0)
    frame = env.render()
    surface = env.viewer.sim_surface
    assert frame.shape[2] == 3
    # the acceleration lane's outer (continuous) line at x = 880, y = 14, and grass 10 m out
    line = surface.pos2pix(880.0, 3 * 4.0 + 2.0)
    grass = surface.pos2pix(880.0, 3 * 4.0 + 12.0)
    frame_line = frame[line[1], line[0]].astype(int)
    assert (frame_line > 200).all(), frame_line  # white
    assert not (frame[grass[1], grass[0]] > 200).all()
    env.close()


@pytest.mark.parametrize(
    ("config", "message"),
    [
        ({"ramp_fraction": 1.5}, "ramp_fraction must be a number in"),
        ({"ramp_fraction": "half"}, "ramp_fraction must be a number in"),
        ({"merge_length": 5.0}, "merge_length must be a finite number >= 10"),
        ({"merge_start": -1.0}, "merge_start must be a finite number > 0"),
        ({"merge_start": 2960.0}, "merge_start must be a finite number > 0 and <= 2955"),
        ({"ramp_length": 10.0}, "ramp_length must be a finite number >= 20"),
        ({"ramp_speed": (20.0, 10.0)}, "ramp_speed must be a range"),
        ({"target_speed": (25.0, 40.0)}, "target_speed must be a range"),
        ({"target_speed": (0.0, 30.0)}, "target_speed must be a range with lo > 0"),
        ({"ramp_fraction": 0.9, "ramp_length": 100.0}, "ramp_fraction=0.9 puts 27"),
        ({"ramp_fraction": 0.0, "n_vehicles": 95}, "n_vehicles=95 leave 95 on the mainline"),
        ({"cav_target_speed": 31.0}, "unknown config key"),
        ({"team_reward": 1}, "team_reward must be True or False"),
    ],
)
def test_bad_config_is_refused(config: dict, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        FreewayMergeEnv(config)
    with pytest.raises(ValueError, match=message):
        make_env("freeway-merge", **config)


@pytest.mark.parametrize("recipe", ["shapley_ac", "coma", "maddpg", "mappo"])
def test_freeway_recipes_train_on_freeway_merge(recipe: str, tmp_path) -> None:
    """The recipes that run on ``freeway`` accept ``env="freeway-merge"``: a tiny run trains
    and evaluates, and the evaluation reports the scenario's metrics."""
    from mapets_rl.recipes.coma import COMA, COMAConfig
    from mapets_rl.recipes.maddpg import MADDPG, MADDPGConfig
    from mapets_rl.recipes.mappo import MAPPO, MAPPOConfig
    from mapets_rl.recipes.shapley_ac import ShapleyAC, ShapleyACConfig

    cls, config_cls, extra = {
        "shapley_ac": (ShapleyAC, ShapleyACConfig, {"batch_size": 8, "updates_per_batch": 1}),
        "coma": (COMA, COMAConfig, {"minibatch_size": 5}),
        "maddpg": (MADDPG, MADDPGConfig, {"batch_size": 8, "updates_per_batch": 1}),
        "mappo": (MAPPO, MAPPOConfig, {"minibatch_size": 5}),
    }[recipe]
    config = config_cls(
        env="freeway-merge",
        env_config={"n_vehicles": 4, "cav_ratio": 0.5, "horizon": 5},
        total_frames=20,
        frames_per_batch=10,
        eval_interval=20,
        checkpoint_interval=0,
        eval_episodes=1,
        logger="none",
        progress=False,
        **extra,
    )
    evals = cls(config, tmp_path / recipe).train()
    assert evals[-1]["frames"] == 20
    metrics = evals[-1]["metrics"]
    assert {"return", "average_velocity", "ramp_stuck"} <= set(metrics)
    assert np.isfinite(metrics["return"]) and 0 <= metrics["ramp_stuck"] <= 2
