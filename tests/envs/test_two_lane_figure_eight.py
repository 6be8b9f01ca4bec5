"""The two-lane figure-eight's observation, neighbour-change filter and planning termination."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from mapets_rl.envs import FigureEightPlannerReward, figure_eight_observation_bounds, make_env
from mapets_rl.envs.figure_eight import TWO_LANE_OBS_DIM, FigureEightEnv, neighbour_speed_columns
from mapets_rl.envs.figure_eight_kinematics import FigureEightKinematicModel
from tests.envs.test_envs import place

#: The fixed margins (no time headway, no closing-speed share) these tests were written with.
FIXED_MARGINS = FigureEightPlannerReward(headway=0.0, lane_change_time=0.0)


def two_lane_env(n_hvs: int) -> FigureEightEnv:
    env = FigureEightEnv({"lanes": 2, "n_cavs": 1, "n_hvs": n_hvs, "horizon": 50})
    env.reset(seed=0)
    return env


def test_two_lane_observation_on_constructed_scene() -> None:
    env = two_lane_env(n_hvs=4)
    assert env.obs_dim == TWO_LANE_OBS_DIM and env.observation_space.shape == (1, 15)
    cav = env.cavs[0]
    ahead, behind, other_ahead, other_behind = [v for v in env.road.vehicles if v is not cav]
    # straight 2 (route coordinates ~190-260 m), far from the crossing points
    place(env, cav, 200.0, 10.0, lane=0)
    place(env, ahead, 230.0, 11.0, lane=0)  # 30 m centre to centre: gap 25 m
    place(env, behind, 185.0, 9.0, lane=0)  # gap 10 m
    place(env, other_ahead, 212.0, 12.0, lane=1)  # gap 7 m in the other lane
    place(env, other_behind, 160.0, 8.0, lane=1)  # gap 35 m
    env.road.refresh()
    obs = env.observe_agents()[0]
    np.testing.assert_allclose(obs[3:7], [11.0, 9.0, 25.0, 10.0], atol=1e-3)
    np.testing.assert_allclose(obs[10:], [0.0, 12.0, 8.0, 7.0, 35.0], atol=1e-3)
    # the same scene seen from lane 1: own and other lane swap, lane position 1
    for vehicle, lane in ((cav, 1), (ahead, 1), (behind, 1), (other_ahead, 0), (other_behind, 0)):
        place(env, vehicle, env.road.route_coordinate(vehicle), vehicle.speed, lane)
    env.road.refresh()
    obs = env.observe_agents()[0]
    np.testing.assert_allclose(obs[3:7], [11.0, 9.0, 25.0, 10.0], atol=1e-2)
    np.testing.assert_allclose(obs[10:], [1.0, 12.0, 8.0, 7.0, 35.0], atol=1e-2)
    # nobody in the other lane within 75 m: gaps clip at 75, speeds 0
    for vehicle in (other_ahead, other_behind):
        place(env, vehicle, 400.0, 5.0, lane=0)
    env.road.refresh()
    np.testing.assert_allclose(env.observe_agents()[0, 11:], [0.0, 0.0, 75.0, 75.0], atol=1e-3)
    # the paper's observation stays 7 features on two lanes
    paper = FigureEightEnv({"lanes": 2, "n_cavs": 1, "n_hvs": 0, "observation": "paper"})
    assert paper.obs_dim == 7


@pytest.mark.parametrize("held", [False, True])
def test_lane_position_moves_continuously_through_a_lane_change(held: bool) -> None:
    env = two_lane_env(n_hvs=0)
    cav = env.cavs[0]
    place(env, cav, 200.0, 8.0, lane=0)
    env.road.refresh()
    positions, lanes = [env.observe_agents()[0, 10]], [0]
    for step in range(40):
        flag = 1.0 if step == 0 or held else 0.0
        obs, *_ = env.step(np.array([[8.0, flag]], dtype=np.float32))
        positions.append(obs[0, 10])
        lanes.append(cav.lane_index[2])
    positions = np.array(positions)
    assert positions[0] == pytest.approx(0.0, abs=1e-3)
    assert np.abs(np.diff(positions)).max() < 0.25  # no jump when the lane index switches
    # a flag held through the change does not turn the CAV back once its lane index switched
    arrived = int(np.argmax(positions > 0.87))  # settled: within 0.5 m of the centre
    assert arrived > 0 and (np.diff(positions[: arrived + 1]) > -1e-3).all()
    assert lanes[arrived] == 1


def test_neighbour_changed_flags_a_new_leader_in_either_lane_but_not_a_steady_scene() -> None:
    env = two_lane_env(n_hvs=3)
    cav = env.cavs[0]
    own, other, far = [v for v in env.road.vehicles if v is not cav]
    place(env, cav, 200.0, 8.0, lane=0)
    place(env, own, 230.0, 8.0, lane=0)
    place(env, other, 225.0, 8.0, lane=1)
    place(env, far, 400.0, 8.0, lane=1)
    env.road.refresh()
    env._info(env.observe_agents())
    keep = np.array([[8.0, 0.0]], dtype=np.float32)
    flags = [bool(env.step(keep)[4]["neighbour_changed"][0]) for _ in range(5)]
    assert not any(flags)  # everyone drives at 8 m/s: the same neighbours
    env.road.vehicles.remove(other)  # the other lane's leader leaves: nobody there in range
    assert env.step(keep)[4]["neighbour_changed"][0]
    assert not env.step(keep)[4]["neighbour_changed"][0]
    env.road.vehicles.remove(own)  # the own leader leaves
    assert env.step(keep)[4]["neighbour_changed"][0]


def test_planning_termination_refuses_a_lane_change_into_a_short_gap() -> None:
    base = [8.0, 0, 0, 8, 8, 30, 30, 60, 60, 0, 0.0, 8, 8, 20, 20]
    rows = torch.tensor(
        [
            base,
            base[:13] + [5.0, 20],  # other lane: a car 5 m ahead
            base[:13] + [20, 3.0],  # other lane: a car 3 m behind
            base[:13] + [0.0, 0.0],  # side by side
        ]
    )
    change = torch.tensor([[8.0, 0.9]]).expand(4, 2)
    keep = torch.tensor([[8.0, 0.1]]).expand(4, 2)
    assert FIXED_MARGINS.collision(rows, change, rows).tolist() == [False, True, True, True]
    assert FIXED_MARGINS.collision(rows, keep, rows).tolist() == [False, False, False, False]
    assert FIXED_MARGINS.replace(lane_change_gap=2.0).collision(rows, change, rows).tolist() == [
        False,
        False,
        False,
        True,
    ]
    # halfway through a change a request is ignored by the env: no lane-change test
    rows[:, 10] = 0.5
    assert FIXED_MARGINS.collision(rows, change, rows).tolist() == [False, False, False, False]


def test_lane_change_margin_grows_with_the_closing_speed() -> None:
    """``lane_change_time``: the other lane's gaps must also cover what they close while the
    CAV moves over (the CAV at 8 m/s; features 11/12 the other lane's leader/follower speeds)."""
    base = [8.0, 0, 0, 8, 8, 30, 30, 60, 60, 0, 0.0, 8, 8, 12, 12]
    rows = torch.tensor(
        [
            base,  # other lane at the CAV's speed, 12 m gaps both ways
            base[:11] + [4.0, 8, 12, 12],  # a leader 4 m/s slower: 12 < 8 + 1 * 4? no; 2 s: yes
            base[:11] + [8.0, 14, 12, 12],  # a follower 6 m/s faster: 12 < 8 + 6
            base[:11] + [12.0, 4, 12, 12],  # faster leader, slower follower: opening gaps
        ]
    )
    change = torch.tensor([[8.0, 0.9]]).expand(4, 2)
    assert FIXED_MARGINS.collision(rows, change, rows).tolist() == [False] * 4
    one = FIXED_MARGINS.replace(lane_change_time=1.0).collision(rows, change, rows)
    assert one.tolist() == [False, False, True, False]
    two = FIXED_MARGINS.replace(lane_change_time=2.0).collision(rows, change, rows)
    assert two.tolist() == [False, True, True, False]
    # one lane (10 features): no lane-change test, so the single-lane planner is unchanged
    one_lane = rows[:, :10]
    for seconds in (0.0, 1.0, 2.0):
        assert (
            FIXED_MARGINS.replace(lane_change_time=seconds)
            .collision(one_lane, change[:, :1], one_lane)
            .tolist()
            == [False] * 4
        )


def test_observation_bounds_on_two_lanes_cover_an_episode() -> None:
    low, high = figure_eight_observation_bounds({"lanes": 2})
    assert low.shape == high.shape == (TWO_LANE_OBS_DIM,)
    env = make_env("figure-eight-multilane", seed=0, n_hvs=10, horizon=60)
    obs = env.rollout(60, break_when_any_done=False)["agents", "observation"]
    assert (obs >= torch.from_numpy(low) - 1e-4).all()
    assert (obs <= torch.from_numpy(high) + 1e-4).all()


@pytest.mark.parametrize(("name", "slots"), [("figure-eight", 3), ("figure-eight-multilane", 5)])
def test_neighbour_cav_names_the_cav_whose_speed_is_observed(name: str, slots: int) -> None:
    """``info["neighbour_cav"]``: where slot ``k`` of a driving CAV ``i`` names CAV ``j``, the
    speed column of that slot equals CAV ``j``'s own speed; humans and empty slots are -1 (the
    rows of CAVs that no longer drive are the wrapper's zeros, masked out)."""
    env = make_env(name, seed=4, n_cavs=8, n_hvs=6)
    td = env.rollout(30, break_when_any_done=False)
    obs = td["next", "agents", "observation"]  # [T, I, S]
    named = td["next", "agents", "info", "neighbour_cav"].long()  # [T, I, K]
    driving = td["next", "agents", "mask"].unsqueeze(-1)
    named = torch.where(driving, named, -1)
    columns = neighbour_speed_columns(obs.shape[-1])
    assert named.shape[-1] == slots == len(columns)
    checked = 0
    for k, column in enumerate(columns):
        t, i = torch.nonzero(named[..., k] >= 0, as_tuple=True)
        j = named[t, i, k]
        torch.testing.assert_close(obs[t, i, column], obs[t, j, 0])
        checked += len(t)
    assert checked > 0 and (named >= -1).all()


def test_brake_when_lost_overrules_the_plan_only_where_every_plan_crashes_at_once() -> None:
    """``lost``: the gap test already failed (below 2 m, or inside the headway margin while
    closing); ``fallback`` brakes those CAVs and keeps their lane, the others' actions stand;
    off by default (the paper's planner)."""
    obs = torch.zeros(4, 15)
    obs[:, [6, 7, 8, 13, 14]] = 75.0  # nobody behind, at the crossing or in the other lane
    obs[:, [0, 3, 5]] = torch.tensor(
        [
            [5.0, 0.0, 1.5],  # 1.5 m behind a stopped leader
            [1.0, 3.0, 1.5],  # below 2 m, the leader pulling away: still every plan
            [6.0, 3.0, 4.0],  # inside 2 + 0.5 * 6 = 5 m, closing
            [6.0, 7.0, 4.0],  # inside 5 m, opening: free
        ]
    )
    reward = FigureEightPlannerReward(headway=0.5, brake_when_lost=True)
    assert reward.lost(obs).tolist() == [True, True, True, False]
    action = torch.tensor([[13.0, 1.0]]).expand(4, 2)
    assert reward.fallback(obs, action).tolist() == [[0.0, 0.0]] * 3 + [[13.0, 1.0]]
    assert FigureEightPlannerReward().fallback is None
    # every first step of the exact own-motion model is a predicted crash for the lost CAVs
    model = FigureEightKinematicModel(n_agents=4, obs_dim=15, action_dim=2)
    for target in (0.0, 13.89):
        step = torch.tensor([[target, 0.0]]).expand(4, 2)
        crash = reward.collision(obs, step, obs + model.predict(obs, step)[0])
        assert crash.tolist() == [True, True, True, False]
