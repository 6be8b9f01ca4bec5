"""Scenarios: geometry, signals, crossing rule, determinism, API compliance, bad input."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
import torch
from highway_env.road.lane import CircularLane, StraightLane
from highway_env.vehicle.behavior import IDMVehicle
from highway_env.vehicle.controller import ControlledVehicle
from pettingzoo.test import parallel_api_test
from tensordict.nn import TensorDictModule
from torchrl.envs import ParallelEnv, SerialEnv
from torchrl.envs.libs.pettingzoo import PettingZooWrapper
from torchrl.envs.utils import check_env_specs, step_mdp

from mapets_rl.envs import (
    FigureEightEnv,
    FigureEightParallelEnv,
    FigureEightPlannerReward,
    FreewayEnv,
    FreewayParallelEnv,
    ScriptedCAVPolicy,
    make_env,
    make_parallel_env,
    traffic_env,
)
from mapets_rl.envs.figure_eight_road import SEGMENTS, FigureEightGeometry
from mapets_rl.envs.freeway import CL, ES, KL
from mapets_rl.envs.lanes import FastCircularLane, FastStraightLane
from mapets_rl.envs.pettingzoo_wrapper import TrafficPettingZooWrapper
from mapets_rl.envs.vehicles import FastIDMVehicle, stock_control

MAX_SPEED = 13.89
#: The fixed margins (no time headway, no closing-speed share) these tests were written with.
FIXED_MARGINS = FigureEightPlannerReward(headway=0.0, lane_change_time=0.0)


def place(env: FigureEightEnv, vehicle, coordinate: float, speed: float, lane: int = 0) -> None:
    """Put ``vehicle`` at route coordinate ``coordinate`` on ``lane`` with ``speed``."""
    index, s = env.geometry.lane_at(coordinate, lane)
    lane_obj = env.geometry.network.get_lane(index)
    vehicle.position = lane_obj.position(s, 0.0)
    vehicle.heading = lane_obj.heading_at(s)
    vehicle.speed = speed
    vehicle.lane_index = vehicle.target_lane_index = index
    vehicle.lane = lane_obj


@pytest.mark.parametrize("lanes", [1, 2])
def test_loop_length_and_continuity(lanes: int) -> None:
    geometry = FigureEightGeometry(480.0, lanes)
    for lane in range(lanes):
        lane_objs = [geometry.network.get_lane((*seg, lane)) for seg in SEGMENTS]
        assert sum(obj.length for obj in lane_objs) == pytest.approx(480.0, rel=0.01)
        for here, nxt in zip(lane_objs, lane_objs[1:] + lane_objs[:1], strict=True):
            np.testing.assert_allclose(here.position(here.length, 0), nxt.position(0, 0), atol=1e-6)
    # The two straights cross at the origin, at their middles.
    for branch, coordinate in enumerate(geometry.crossing_coordinates):
        index, s = geometry.lane_at(coordinate, 0)
        assert index[:2] == SEGMENTS[0 if branch == 0 else 3]
        if lanes == 1:
            np.testing.assert_allclose(
                geometry.network.get_lane(index).position(s, 0), 0, atol=1e-6
            )


def test_two_cavs_sent_into_the_crossing_collide() -> None:
    env = FigureEightEnv({"n_cavs": 2, "n_hvs": 0, "horizon": 100})
    env.reset(seed=0)
    for cav, crossing in zip(env.cavs, env.geometry.crossing_coordinates, strict=True):
        place(env, cav, crossing - 30.0, 10.0)
    env.road.refresh()
    action = np.full((2, 1), 10.0, dtype=np.float32)
    for _ in range(60):
        obs, _, terminated, _, info = env.step(action)
        if terminated:
            break
    assert terminated
    assert info["agent_terminated"].all() and info["collided"].all()
    expected = obs[:, 0] + obs[:, 3] + obs[:, 4] - 10.0  # eq. 26 with beta = -10
    np.testing.assert_allclose(info["agent_rewards"], expected, atol=1e-5)
    metrics = info["episode"]
    assert metrics["collisions"] == 2 and metrics["safety"] < 0.3


def test_a_crash_on_the_last_step_is_not_safe() -> None:
    # the two CAVs sent into the crossing collide in step 27; make that the last step
    env = FigureEightEnv({"n_cavs": 2, "n_hvs": 0, "horizon": 27})
    env.reset(seed=0)
    for cav, crossing in zip(env.cavs, env.geometry.crossing_coordinates, strict=True):
        place(env, cav, crossing - 30.0, 10.0)
    env.road.refresh()
    for _ in range(27):
        _, _, terminated, truncated, info = env.step(np.full((2, 1), 10.0, dtype=np.float32))
    assert terminated and truncated and info["collided"].all()
    metrics = info["episode"]
    assert metrics["collisions"] == 2
    assert metrics["safety"] == pytest.approx(26 / 27)  # t_c = 26 steps completed
    assert metrics["agility"] == pytest.approx(1.0, abs=1e-6)  # 27 steps at 10 m/s, 0.1 s


def test_observation_and_reward_on_constructed_situation() -> None:
    env = FigureEightEnv({"n_cavs": 1, "n_hvs": 2, "horizon": 10, "observation": "paper"})
    env.reset(seed=0)
    cav = env.cavs[0]
    ahead, behind = [v for v in env.road.vehicles if v is not cav]
    place(env, cav, 120.0, 10.0)
    place(env, ahead, 140.0, 5.0)  # centre distance 20 m -> gap 15 m
    place(env, behind, 105.0, 7.0)  # centre distance 15 m -> gap 10 m
    env.road.refresh()
    obs = env.observe_agents()[0]
    np.testing.assert_allclose(obs[[0, 3, 4, 5, 6]], [10.0, 5.0, 7.0, 15.0, 10.0], atol=1e-4)
    np.testing.assert_allclose(obs[1:3], cav.position, atol=1e-4)
    reward = env.agent_rewards(obs[None], None)[0]
    assert reward == pytest.approx(10.0 + 5.0 + 7.0, abs=1e-4)  # eq. 26
    # Far neighbours: gaps clip at 75 m and their speeds read 0.
    place(env, ahead, 240.0, 5.0)
    place(env, behind, 20.0, 7.0)
    env.road.refresh()
    obs = env.observe_agents()[0]
    np.testing.assert_allclose(obs[3:], [0.0, 0.0, 75.0, 75.0])


def test_planning_reward_penalises_predicted_collisions() -> None:
    next_obs = torch.tensor([[10.0, 0, 0, 5, 7, 15, 10], [10.0, 0, 0, 5, 7, 0.2, 10]])
    reward = FIXED_MARGINS.reward(next_obs, torch.zeros(2, 1), next_obs)
    torch.testing.assert_close(reward, torch.tensor([22.0, 12.0]))


def test_planning_collision_tests_the_gap_ahead_and_the_crossing() -> None:
    rows = torch.tensor(
        [
            [10.0, 0, 0, 5, 7, 15, 10, 30, 40, 8],  # free
            [10.0, 0, 0, 5, 7, 1.5, 10, 30, 40, 8],  # gap ahead below 2 m
            [10.0, 0, 0, 5, 7, 15, 0.5, 30, 40, 8],  # fast follower: not the CAV's crash
            [10.0, 0, 0, 5, 7, 15, 10, 3, -2, 8],  # both inside the conflict zone
            [10.0, 0, 0, 5, 7, 15, 10, 3, 20, 8],  # the other vehicle still 20 m away
            [10.0, 0, 0, 5, 7, 15, 10, 3, -6, 8],  # the other vehicle has cleared it
        ]
    )
    collided = FIXED_MARGINS.collision(rows, torch.zeros(6, 1), rows)
    assert collided.tolist() == [False, True, False, True, False, False]
    # the paper's 7 features: only the gap ahead
    assert FIXED_MARGINS.collision(rows[:, :7], None, rows[:, :7]).tolist() == [
        False,
        True,
        False,
        False,
        False,
        False,
    ]
    reward = FIXED_MARGINS.reward(rows, None, rows)
    torch.testing.assert_close(reward, 22.0 - 10.0 * collided.float())


def test_crossing_observation_on_constructed_scene() -> None:
    env = FigureEightEnv({"n_cavs": 1, "n_hvs": 3, "horizon": 10})
    assert env.obs_dim == 10 and env.observation_space.shape == (1, 10)
    env.reset(seed=0)
    cav = env.cavs[0]
    cleared, conflict, behind_it = [v for v in env.road.vehicles if v is not cav]
    c0, c1 = env.geometry.crossing_coordinates
    place(env, cav, c0 - 30.0, 10.0)  # 30 m before the crossing on branch 0
    place(env, cleared, c1 + 8.0, 12.0)  # 8 m past it on branch 1: cleared
    place(env, conflict, c1 - 20.0, 6.0)  # 20 m before it on branch 1
    place(env, behind_it, c1 - 45.0, 9.0)
    env.road.refresh()
    obs = env.observe_agents()[0]
    np.testing.assert_allclose(obs[7:], [30.0, 20.0, 6.0], atol=1e-3)
    # a vehicle 3 m past the crossing point still occupies it: it is the conflicting vehicle
    place(env, cleared, c1 + 3.0, 12.0)
    env.road.refresh()
    np.testing.assert_allclose(env.observe_agents()[0, 7:], [30.0, -3.0, 12.0], atol=1e-3)
    # the CAV inside the crossing: negative distance until it has cleared it by 5 m
    place(env, cav, c0 + 2.0, 10.0)
    env.road.refresh()
    assert env.observe_agents()[0, 7] == pytest.approx(-2.0, abs=1e-3)
    # nobody on the other branch within 75 m: distance clips at 75, speed 0
    for vehicle, where in ((cleared, c1 + 100.0), (conflict, c1 + 150.0), (behind_it, c1 - 90)):
        place(env, vehicle, where, 5.0)
    place(env, cav, c0 - 100.0, 10.0)
    env.road.refresh()
    np.testing.assert_allclose(env.observe_agents()[0, 7:], [75.0, 75.0, 0.0], atol=1e-3)


def test_crossing_conflict_is_no_neighbour_change_and_crashed_cavs_keep_their_position():
    env = make_env("figure-eight", seed=0, n_cavs=3, n_hvs=0, horizon=100)
    td = env.reset()
    raw: FigureEightEnv = env._env.env
    c0, c1 = raw.geometry.crossing_coordinates
    for cav, where in zip(raw.cavs, (c0 - 30.0, c1 - 30.0, c0 + 120.0), strict=True):
        place(raw, cav, where, 10.0)
    raw.road.refresh()
    raw._info(raw.observe_agents())  # the scene above is the reference for the flags
    flags = []
    while not td.get(("next", "agents", "terminated"), torch.zeros(1, dtype=torch.bool)).any():
        td = step_mdp(td) if "next" in td.keys() else td
        td["agents", "action"] = torch.full((3, 1), 10.0)
        td = env.step(td)
        flags.append(td["next", "agents", "info", "neighbour_changed"].clone())
        assert len(flags) < 60
    crashed = td["next", "agents", "info", "collided"]
    assert crashed.tolist() == [True, True, False]  # the two sent into the crossing
    # each saw the other as its conflicting vehicle all along: no identity change flagged
    assert not torch.stack(flags)[:, :2].any()
    crash_site = td["next", "agents", "position"][:2].clone()
    assert (crash_site.norm(dim=-1) < 8.0).all() and (crash_site.norm(dim=-1) > 0.1).all()
    # one step later the crashed CAVs are removed but reported where they crashed, not at 0
    td = step_mdp(td)
    td["agents", "action"] = torch.full((3, 1), 10.0)
    td = env.step(td)
    assert td["next", "agents", "mask"].tolist() == [False, False, True]
    torch.testing.assert_close(td["next", "agents", "position"][:2], crash_site)


def test_neighbour_changed_flags_a_new_leader() -> None:
    env = FigureEightEnv({"n_cavs": 1, "n_hvs": 2, "horizon": 10, "observation": "paper"})
    env.reset(seed=0)
    cav = env.cavs[0]
    near, far = [v for v in env.road.vehicles if v is not cav]
    place(env, cav, 100.0, 5.0)
    place(env, near, 120.0, 5.0)
    place(env, far, 160.0, 5.0)
    env.road.refresh()
    env._info(env.observe_agents())
    _, _, _, _, info = env.step(np.full((1, 1), 5.0, dtype=np.float32))
    assert not info["neighbour_changed"][0]
    env.road.vehicles.remove(near)  # the leader leaves the road: the next car becomes leader
    _, _, _, _, info = env.step(np.full((1, 1), 5.0, dtype=np.float32))
    assert info["neighbour_changed"][0]
    _, _, _, _, info = env.step(np.full((1, 1), 5.0, dtype=np.float32))
    assert not info["neighbour_changed"][0]


@pytest.mark.parametrize("lanes,n_cavs", [(1, 8), (2, 22)])
def test_human_drivers_never_crash_with_scripted_cavs(lanes: int, n_cavs: int) -> None:
    env = FigureEightEnv({"lanes": lanes, "n_cavs": n_cavs, "n_hvs": 20, "horizon": 600})
    env.reset(seed=0)
    crashes = 0
    for _ in range(600):
        _, _, terminated, truncated, info = env.step(env.scripted_action())
        crashes += sum(v.crashed for v in env.road.vehicles) + int(info["collided"].sum())
    assert truncated and not terminated
    assert crashes == 0
    assert len(env.road.vehicles) == n_cavs + 20
    assert info["episode"]["safety"] == 1.0 and info["episode"]["agility"] > 0.1


def test_seeded_episodes_are_deterministic() -> None:
    def rollout(seed: int) -> np.ndarray:
        env = FigureEightEnv({"n_cavs": 3, "horizon": 30})
        obs, _ = env.reset(seed=seed)
        trace = [obs]
        for _ in range(30):
            trace.append(env.step(env.scripted_action())[0])
        return np.stack(trace)

    np.testing.assert_array_equal(rollout(7), rollout(7))
    assert not np.array_equal(rollout(7), rollout(8))


def test_metrics_in_info_match_distances() -> None:
    env = FigureEightEnv({"n_cavs": 2, "n_hvs": 2, "horizon": 20})
    env.reset(seed=0)
    total = np.zeros(2)
    for _ in range(20):
        _, _, _, truncated, info = env.step(np.full((2, 1), 8.0, dtype=np.float32))
        total += info["distance"]
    assert truncated
    assert info["episode"]["agility"] == pytest.approx(total.mean() / 20)
    assert info["episode"]["safety"] == 1.0


def test_freeway_rewards_and_comfort() -> None:
    env = FreewayEnv({"n_vehicles": 6, "cav_ratio": 0.5, "horizon": 5})
    obs, _ = env.reset(seed=0)
    assert obs.shape == (3, 22)
    _, _, _, _, info = env.step(np.array([KL, ES, CL]))
    speeds = np.array([cav.speed for cav in env.cavs])
    comfort = info["agent_rewards"] - 0.1 * speeds
    assert min(abs(comfort[0] - 2.0), abs(comfort[0] - 3.0)) < 1e-4  # KL: 3 smooth, else 2
    assert comfort[1] == pytest.approx(0.0, abs=1e-4)  # ES
    assert comfort[2] == pytest.approx(1.0, abs=1e-4)  # CL
    assert 0.0 <= info["traffic_comfort"] <= 3.0 and info["traffic_velocity"] > 0


def test_freeway_all_human_traffic_runs() -> None:
    env = FreewayEnv({"n_vehicles": 9, "cav_ratio": 0.0, "horizon": 5})
    env.reset(seed=0)
    for _ in range(5):
        _, reward, terminated, truncated, info = env.step(np.zeros(0, dtype=np.int64))
    assert truncated and not terminated and reward == 0.0
    assert info["episode"]["average_velocity"] > 10.0


@pytest.mark.parametrize(
    "make",
    [
        lambda: FigureEightParallelEnv(n_cavs=3, n_hvs=3, horizon=30),
        lambda: FigureEightParallelEnv(n_cavs=4, n_hvs=4, lanes=2, horizon=30),
        lambda: FreewayParallelEnv(n_vehicles=6, cav_ratio=0.5, horizon=10),
    ],
)
def test_pettingzoo_parallel_api(make) -> None:
    parallel_api_test(make(), num_cycles=40)


@pytest.mark.parametrize(
    "name,config,act_shape",
    [
        ("figure-eight", {"n_cavs": 3, "n_hvs": 3}, (3, 1)),
        ("figure-eight-multilane", {"n_cavs": 4, "n_hvs": 4}, (4, 2)),
        ("freeway", {"n_vehicles": 6}, (6, 4)),
    ],
)
def test_torchrl_env_specs_and_keys(name: str, config: dict, act_shape: tuple) -> None:
    env = make_env(name, seed=0, **config)
    check_env_specs(env)
    td = env.rollout(5)
    n = act_shape[0]
    assert td["agents", "action"].shape == (5, *act_shape)
    assert td["next", "agents", "reward"].shape == (5, n, 1)
    assert td["next", "agents", "terminated"].shape == (5, n, 1)
    assert td["next", "agents", "position"].shape == (5, n, 2)
    assert td["next", "done"].shape == (5, 1)


@pytest.mark.parametrize(
    "name,config,speed",
    [
        ("figure-eight", {"n_cavs": 4, "n_hvs": 4, "horizon": 60}, 13.89),
        ("freeway", {"n_vehicles": 8, "horizon": 10}, None),
    ],
)
def test_vectorised_wrapper_matches_stock_pettingzoo_wrapper(name, config, speed) -> None:
    """Same seed, same actions: identical outputs, including crashes, masks and resets."""
    rollouts = []
    for wrapper in (PettingZooWrapper, TrafficPettingZooWrapper):
        parallel = make_parallel_env(name, **config)
        env = wrapper(
            env=parallel,
            group_map={"agents": parallel.possible_agents},
            use_mask=True,
            categorical_actions=False,
            done_on_any=False,
            seed=3,
        )
        torch.manual_seed(0)
        policy = None
        if speed is not None:
            policy = TensorDictModule(
                lambda obs: torch.full((*obs.shape[:-1], 1), speed),
                in_keys=[("agents", "observation")],
                out_keys=[("agents", "action")],
            )
        rollouts.append(env.rollout(150, policy, break_when_any_done=False))
    stock, ours = rollouts
    assert stock["next", "agents", "info", "collided"].sum() > 0  # crashes happened
    assert stock["next", "done"].sum() > 0  # and resets
    for prefix in ((), ("next",)):  # ours moves the positions out of the info
        position = ours.get((*prefix, "agents", "position"))
        del ours[(*prefix, "agents", "position")]
        # ... and reports a removed CAV where it last drove (the stock wrapper: zeros)
        stock_position = stock.get((*prefix, "agents", "info", "position"))
        removed = ~stock.get((*prefix, "agents", "mask")) & (stock_position == 0).all(-1)
        assert torch.equal(position[~removed], stock_position[~removed])
        assert (position[removed].abs().sum(-1) > 0).all()
        del stock[(*prefix, "agents", "info", "position")]
    assert set(stock.keys(True, True)) == set(ours.keys(True, True))
    for key in stock.keys(True, True):
        assert torch.equal(stock[key], ours[key]), key


def test_torchrl_crashed_agents_stay_masked_in_the_batch() -> None:
    env = make_env("figure-eight", seed=0, n_cavs=2, n_hvs=0, horizon=100)
    start = env.reset()
    scenario = traffic_env(env)
    for cav, crossing in zip(scenario.cavs, scenario.geometry.crossing_coordinates, strict=True):
        place(scenario, cav, crossing - 30.0, 10.0)
    scenario.road.refresh()
    td = env.rollout(
        60,
        lambda td: td.set(("agents", "action"), torch.full((2, 1), 10.0)),
        auto_reset=False,
        tensordict=start,
    )
    assert td["next", "agents", "terminated"][-1].all() and td["next", "done"][-1].all()
    assert not td["next", "agents", "mask"][-1].any()
    assert td["next", "agents", "observation"].shape == (td.shape[0], 2, 10)


def test_torchrl_env_in_serial_env_with_scripted_policy() -> None:
    env = SerialEnv(2, lambda: make_env("figure-eight", n_cavs=2, n_hvs=2))
    td = env.rollout(3)
    assert td.shape == (2, 3) and td["agents", "position"].shape == (2, 3, 2, 2)
    single = make_env("figure-eight", seed=1, n_cavs=2, n_hvs=8)
    td = single.rollout(20, ScriptedCAVPolicy(single))
    assert (td["next", "agents", "reward"] > 0).all()


def _small_figure_eight():
    return make_env("figure-eight", n_cavs=2, n_hvs=2)


def test_torchrl_env_in_multiprocess_parallel_env() -> None:
    env = ParallelEnv(2, _small_figure_eight)
    try:
        td = env.rollout(3)
    finally:
        env.close()
    assert td.shape == (2, 3) and td["next", "agents", "position"].shape == (2, 3, 2, 2)


def test_gymnasium_ids_and_rendering() -> None:
    env = gym.make("mapets_rl/FigureEight-v0", render_mode="rgb_array", config={"n_cavs": 2})
    obs, _ = env.reset(seed=0)
    assert obs.shape == (2, 10)
    frame = env.render()
    assert frame.ndim == 3 and frame.shape[2] == 3 and frame.std() > 0
    multi = gym.make("mapets_rl/FigureEightMultiLane-v0").unwrapped
    assert multi.config["lanes"] == 2 and multi.config["horizon"] == 400
    assert gym.make("mapets_rl/Freeway-v0").unwrapped.config["horizon"] == 40


@pytest.mark.parametrize(
    "build,match",
    [
        (lambda: make_env("ring-road"), "scenario name"),
        (lambda: FigureEightEnv({"n_cavs": 0}), "n_cavs"),
        (lambda: FigureEightEnv({"n_cavs": 30, "n_hvs": 20}), "n_cavs \\+ n_hvs"),
        (lambda: FigureEightEnv({"lanes": 3}), "lanes"),
        (lambda: FigureEightEnv({"horizon": 0}), "horizon"),
        (lambda: FigureEightEnv({"policy_frequency": 0}), "policy_frequency"),
        (lambda: FigureEightEnv({"simulation_frequency": 15}), "simulation_frequency"),
        (lambda: FigureEightEnv({"n_hvs": (5, 2)}), "n_hvs"),
        (lambda: FreewayEnv({"cav_ratio": 1.5}), "cav_ratio"),
        (lambda: FreewayEnv({"n_vehicles": 500}), "n_vehicles"),
        (lambda: FreewayParallelEnv(n_vehicles=4, cav_ratio=0.0), "cav_ratio"),
    ],
)
def test_bad_configuration_is_rejected(build, match: str) -> None:
    with pytest.raises(ValueError, match=match):
        build()


def test_bad_actions_are_rejected() -> None:
    env = FigureEightEnv({"n_cavs": 2, "n_hvs": 0})
    env.reset(seed=0)
    with pytest.raises(ValueError, match="shape"):
        env.step(np.zeros((3, 1)))
    with pytest.raises(ValueError, match="out of bounds"):
        env.step(np.full((2, 1), MAX_SPEED + 5))
    with pytest.raises(ValueError, match="finite"):
        env.step(np.full((2, 1), np.nan))
    freeway = FreewayEnv({"n_vehicles": 3})
    freeway.reset(seed=0)
    with pytest.raises(ValueError, match="integers in \\[0, 3\\]"):
        freeway.step(np.array([0, 4, 1]))


# --- float-math overrides of highway-env's per-step control ------------------------------------
def _sampled_scene(seed: int) -> FigureEightEnv:
    """A two-lane figure-eight 40 steps into a random-action episode (lane changes included)."""
    env = FigureEightEnv({"lanes": 2, "n_cavs": 6, "n_hvs": 10, "horizon": 100})
    env.reset(seed=seed)
    rng = np.random.default_rng(seed)
    space = env.action_space
    for _ in range(40):
        env.step(rng.uniform(space.low, space.high).astype(np.float32))
    return env


def _same(ours: float | tuple, stock: float | tuple) -> bool:
    """Equal up to a few ulp (NumPy may use SIMD libm variants on other CPUs; bitwise equal
    on the AVX2 machine the overrides were checked on)."""
    return np.allclose(ours, stock, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("seed", [0, 1])
def test_float_math_control_equals_highway_env(seed: int) -> None:
    env = _sampled_scene(seed)
    rng = np.random.default_rng(seed)
    vehicles = list(env.road.vehicles)
    assert sum(isinstance(v, FastIDMVehicle) for v in vehicles) >= 5
    for vehicle in vehicles:
        # off the lane centre, heading and speed perturbed: the clips and the wrap are exercised
        vehicle.heading += rng.normal(0.0, 0.5)
        vehicle.speed = float(rng.uniform(0.0, 15.0))
        vehicle.position = vehicle.position + rng.normal(0.0, 1.5, 2)
    lanes = env.road.network.lanes_list()
    for vehicle in vehicles:
        for lane_index in {vehicle.lane_index, vehicle.target_lane_index}:
            assert _same(
                vehicle.steering_control(lane_index),
                ControlledVehicle.steering_control(vehicle, lane_index),
            )
        for lane in lanes:
            stock = StraightLane if isinstance(lane, FastStraightLane) else CircularLane
            assert _same(
                lane.local_coordinates(vehicle.position),
                stock.local_coordinates(lane, vehicle.position),
            )
        if isinstance(vehicle, FastIDMVehicle):
            assert _same(vehicle.acceleration(vehicle), IDMVehicle.acceleration(vehicle, vehicle))
            for other in vehicles:
                if other is not vehicle:
                    assert _same(
                        vehicle.desired_gap(vehicle, other),
                        IDMVehicle.desired_gap(vehicle, vehicle, other),
                    )
                    assert _same(
                        vehicle.acceleration(vehicle, other),
                        IDMVehicle.acceleration(vehicle, vehicle, other),
                    )
    for lane in lanes:
        if isinstance(lane, FastCircularLane):
            for s in rng.uniform(-5.0, lane.length + 5.0, 20):
                assert _same(lane.heading_at(s), CircularLane.heading_at(lane, s))


@pytest.mark.parametrize(
    "name,config",
    [
        ("figure-eight-multilane", {"n_cavs": 10, "n_hvs": 12}),
        ("freeway", {"n_vehicles": 20, "cav_ratio": 0.5}),
    ],
)
def test_float_math_control_gives_identical_trajectories(name, config) -> None:
    """A seeded random-action episode is the same with highway-env's stock methods."""

    def trajectory() -> np.ndarray:
        env = make_parallel_env(name, horizon=60, **config).env
        env.reset(seed=5)
        rng = np.random.default_rng(5)
        space, rows = env.action_space, []
        for _ in range(60):
            if hasattr(space, "nvec"):
                action = rng.integers(0, space.nvec)
            else:
                action = rng.uniform(space.low, space.high).astype(np.float32)
            obs, reward, terminated, truncated, _ = env.step(action)
            state = [(*v.position, v.heading, v.speed) for v in env.road.vehicles]
            rows.append(np.concatenate([np.ravel(state), obs.ravel(), [reward]]))
            if terminated or truncated:
                break
        return np.concatenate(rows)

    ours = trajectory()
    with stock_control():
        stock = trajectory()
    assert FastIDMVehicle.act is not IDMVehicle.act  # restored
    np.testing.assert_allclose(ours, stock, rtol=0, atol=1e-9)
