"""highway-env's multi-agent scenarios (``mapets_rl.envs.highway_multi_agent``): the four
registered ones pass PettingZoo's API and seed tests and torchrl's spec check, rewards and
terminations are highway-env's per agent, the intersection's one crash ends the episode,
positions reach the communication graph, the intersection leaves the other scenarios' IDM
drivers alone, the merge can keep its ramp driver, the planner rewards (highway-multi's,
highway-merge's) are the env's reward on observed steps, bad input is refused
naming the parameter, and MAPPO trains on a scenario through the CLI."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
from highway_env.vehicle.behavior import IDMVehicle
from pettingzoo.test import parallel_api_test, parallel_seed_test
from torchrl.envs.utils import check_env_specs

from mapets_rl.envs import (
    GYM_IDS,
    HighwayMergePlannerReward,
    HighwayMultiAgentParallelEnv,
    HighwayPlannerReward,
    make_env,
    make_parallel_env,
    registered_scenario,
    scenario_defaults,
)
from mapets_rl.envs.highway_multi_agent import SCENARIOS
from mapets_rl.experiment.published import load_published
from tests.cli_run import run_cli

NAMES = list(SCENARIOS)


@pytest.mark.parametrize("name", NAMES)
def test_a_scenario_passes_pettingzoo_and_torchrl_checks(name: str) -> None:
    parallel_api_test(make_parallel_env(name), num_cycles=15)
    parallel_seed_test(lambda: make_parallel_env(name), num_cycles=5)
    env = make_env(name, seed=0)
    check_env_specs(env)
    td = env.rollout(3, break_when_any_done=False)
    n = len(make_parallel_env(name).possible_agents)
    assert td["next", "agents", "position"].shape == (3, n, 2)
    assert td["next", "agents", "info", "speed"].shape == (3, n)
    assert td["agents", "action"].shape[-2:] == (n, env.action_spec["agents", "action"].shape[-1])
    categorical = make_env(name, seed=0, categorical_actions=True)
    assert categorical.action_spec["agents", "action"].shape == (n,)


def test_the_scenarios_are_registered_with_their_defaults() -> None:
    for name, (cls, gym_id, changes) in SCENARIOS.items():
        scenario = registered_scenario(name)
        assert scenario.parallel_env is cls and GYM_IDS[name] == gym_id
        defaults = scenario_defaults(name)
        assert defaults["controlled_vehicles"] == changes["controlled_vehicles"] >= 2
        assert defaults["observation"]["type"] == "MultiAgentObservation"
    assert registered_scenario("highway-multi").planner_reward is HighwayPlannerReward
    assert registered_scenario("highway-merge").planner_reward is HighwayMergePlannerReward


def test_rewards_and_terminations_are_highway_envs_per_agent() -> None:
    """The intersection reports ``agents_rewards`` / ``agents_terminated`` and they are the
    agents'; on the highway each agent gets highway-v0's reward as its own ego."""
    env = make_parallel_env("highway-intersection")
    env.reset(seed=3)
    _, rewards, terminations, _, _ = env.step({a: 2 for a in env.agents})
    raw = env.env
    expected = [raw._agent_reward(2, v) for v in raw.controlled_vehicles]
    assert [rewards[a] for a in env.possible_agents] == pytest.approx(expected)
    assert not any(terminations.values())

    env = make_parallel_env("highway-multi")
    env.reset(seed=1)
    _, rewards, _, _, _ = env.step({a: 1 for a in env.agents})
    for agent, vehicle in zip(env.possible_agents, env.vehicles, strict=True):
        forward = vehicle.speed * np.cos(vehicle.heading)
        speed = np.clip((forward - 20) / 10, 0, 1)
        assert rewards[agent] == pytest.approx((0.4 * speed + 1) / 1.4, abs=1e-5)


def test_one_crash_ends_the_intersection_episode_for_every_agent() -> None:
    """Every agent at full speed: the first crash terminates all agents (highway-env's
    ``_is_terminated``), the crashed one with the collision reward."""
    for seed in range(20):
        env = make_parallel_env("highway-intersection")
        env.reset(seed=seed)
        while env.agents:
            _, rewards, terminations, truncations, infos = env.step({a: 2 for a in env.agents})
            crashed = [a for a in infos if infos[a]["collided"]]
            if crashed:
                assert all(terminations.values()) and not env.agents
                assert all(rewards[a] == -5.0 for a in crashed)
                assert env.last_episode_metrics["collisions"] == len(crashed)
                return
    pytest.fail("no crash in 20 episodes at full speed")


def test_a_highway_agent_ends_alone_on_its_crash() -> None:
    """On highway-v0 (no multi-agent termination of its own) a crashed agent leaves
    ``agents``, the others drive on."""
    for seed in range(30):
        env = make_parallel_env("highway-multi", vehicles_count=12)
        env.reset(seed=seed)
        while env.agents:
            acting = list(env.agents)
            _, _, terminations, truncations, infos = env.step({a: 3 for a in acting})
            crashed = {a for a in acting if infos[a]["collided"]}
            if crashed and len(crashed) < len(acting) and not any(truncations.values()):
                assert {a for a in acting if terminations[a]} == crashed
                assert set(env.agents) == set(acting) - crashed
                return
    pytest.fail("no single crash in 30 episodes")


def test_positions_are_the_controlled_vehicles() -> None:
    env = make_env("highway-roundabout", seed=0)
    td = env.rollout(2)
    vehicles = env.vehicles  # attribute reads reach the ParallelEnv
    expected = torch.tensor(np.array([v.position for v in vehicles]), dtype=torch.float32)
    assert torch.equal(td["next", "agents", "position"][-1], expected)


def test_the_intersection_leaves_the_idm_class_alone() -> None:
    before = (IDMVehicle.DISTANCE_WANTED, IDMVehicle.COMFORT_ACC_MAX, IDMVehicle.COMFORT_ACC_MIN)
    make_parallel_env("highway-intersection").reset(seed=0)
    assert (
        IDMVehicle.DISTANCE_WANTED,
        IDMVehicle.COMFORT_ACC_MAX,
        IDMVehicle.COMFORT_ACC_MIN,
    ) == before


def test_merge_and_roundabout_hand_their_scene_to_agents() -> None:
    env = make_parallel_env("highway-merge", controlled_vehicles=3)
    env.reset(seed=0)
    ramp = env.vehicles[1]
    assert ramp.lane_index[:2] == ("j", "k") and len(env.agents) == 3
    with pytest.raises(ValueError, match=r"controlled_vehicles must be in \[1, 5\]"):
        make_parallel_env("highway-roundabout", controlled_vehicles=6)


def test_the_planner_reward_is_the_envs_reward_on_observed_steps() -> None:
    """On real transitions of ``highway-multi`` with continuous longitudinal actions, the
    planner reward equals every live agent's reward where neither the env nor the planner
    sees a crash; the predicted crash flags most crash steps."""
    torch.manual_seed(0)
    action = {"type": "MultiAgentAction", "action_config": {"type": "ContinuousAction",
              "lateral": False}}  # fmt: skip
    env = make_env("highway-multi", action=action, vehicles_count=12)
    planner = HighwayPlannerReward()
    crashes = flagged_crashes = 0
    for seed in range(4):
        env.set_seed(seed)
        td = env.rollout(10)
        obs, act = td["agents", "observation"], td["agents", "action"]
        next_obs = td["next", "agents", "observation"]
        reward = td["next", "agents", "reward"].squeeze(-1)
        acted = td["agents", "mask"]
        crash = td["next", "agents", "info", "collided"].bool() & acted
        flagged = planner.termination_fn(obs, act, next_obs)
        calm = acted & ~crash & ~flagged
        assert torch.allclose(planner.reward(obs, act, next_obs)[calm], reward[calm], atol=1e-4)
        assert torch.allclose(reward[crash], torch.zeros_like(reward[crash]))
        crashes += int(crash.sum())
        flagged_crashes += int((flagged & crash).sum())
    assert flagged_crashes >= 0.8 * crashes


def test_the_merge_planner_reward_is_merge_v0s_reward_on_observed_steps() -> None:
    """On real steps of ``highway-merge`` with highway agents (the published MA-PETS config's
    env_config), the merge planner reward equals every agent's merge-v0 reward where neither
    sees a crash, no vehicle is on the ramp's curve and the vehicles on the merging lane are
    those the agent observes near it; the merging vehicle's slowdown is among the steps
    compared; a crash ends a planned trajectory."""
    config = load_published("highway-merge/mapets").fields["env_config"]
    env = make_parallel_env("highway-merge", **config)
    planner = HighwayMergePlannerReward()
    compared = slowed = 0
    for seed in range(6):
        obs, _ = env.reset(seed=seed)
        rng = np.random.default_rng(seed)
        while env.agents:
            actions = {a: rng.uniform(-1, 1, 1).astype(np.float32) for a in env.agents}
            next_obs, rewards, _, _, infos = env.step(actions)
            vehicles = env.env.road.vehicles
            curve = any(v.lane_index[:2] == ("k", "b") for v in vehicles)
            merging = sum(v.lane_index == ("b", "c", 2) for v in vehicles)
            for agent, reward in rewards.items():
                step = [torch.as_tensor(x) for x in (obs[agent], actions[agent], next_obs[agent])]
                rows = step[2].view(-1, 5)
                y = 12 * (rows[0, 2] + rows[1:, 2])
                seen = int(((rows[1:, 0] > 0.5) & ((y - 8).abs() < 2)).sum())
                crash = bool(planner.crash(*step)) or infos[agent]["collided"]
                assert bool(planner.termination_fn(*step)) == bool(planner.crash(*step))
                if crash or curve or seen != merging:
                    continue
                assert float(planner.reward(*step)) == pytest.approx(reward, abs=1e-4)
                compared += 1
                slowed += merging > 0
            obs = next_obs
    assert compared >= 60 and slowed >= 5, (compared, slowed)
    with pytest.raises(ValueError, match="ramp_target_speed must be > 0"):
        HighwayMergePlannerReward(ramp_target_speed=0.0)
    with pytest.raises(ValueError, match="ramp_agent must be true or false"):
        make_parallel_env("highway-merge", ramp_agent=1)


def test_the_merge_can_keep_its_ramp_driver() -> None:
    """``ramp_agent: false``: the agents are the highway's vehicles (ego first), the ramp
    vehicle stays highway-env's IDM driver; at most 4 agents."""
    env = make_parallel_env("highway-merge", controlled_vehicles=4, ramp_agent=False)
    env.reset(seed=0)
    assert all(v.lane_index[:2] == ("a", "b") for v in env.vehicles)
    (ramp,) = [v for v in env.env.road.vehicles if v.lane_index[:2] == ("j", "k")]
    assert type(ramp) is IDMVehicle and ramp not in env.vehicles
    with pytest.raises(ValueError, match=r"controlled_vehicles must be in \[1, 4\]"):
        make_parallel_env("highway-merge", controlled_vehicles=5, ramp_agent=False)


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"env_id": "nosuch-v0"}, "env_id must be a registered gymnasium id"),
        ({"env_id": "CartPole-v1"}, "is no highway-env env"),
        ({"env_id": "highway-v0"}, r"config\['observation'\] must be"),
        (
            {"env_id": "highway-v0", "config": {"controlled_vehicles": 0}},
            "controlled_vehicles must be an integer >= 1",
        ),
        (
            {
                "env_id": "merge-v0",
                "config": {
                    "controlled_vehicles": 2,
                    "observation": {
                        "type": "MultiAgentObservation",
                        "observation_config": {"type": "Kinematics"},
                    },
                    "action": {
                        "type": "MultiAgentAction",
                        "action_config": {"type": "DiscreteMetaAction"},
                    },
                },
            },
            "merge-v0 spawned 1 controlled vehicle",
        ),  # fmt: skip
        ({"env_id": "highway-v0", "render_mode": "human"}, "render_mode must be"),
    ],
)
def test_bad_input_is_refused(kwargs: dict, match: str) -> None:
    with pytest.raises(ValueError, match=match):
        HighwayMultiAgentParallelEnv(**kwargs)


def test_bad_actions_and_planner_settings_are_refused() -> None:
    env = make_parallel_env("highway-multi")
    env.reset(seed=0)
    with pytest.raises(ValueError, match=r"action of cav_0 must be one integer in \[0, 4\]"):
        env.step({"cav_0": 7})
    with pytest.raises(ValueError, match="unknown agents"):
        env.step({"car": 1})
    with pytest.raises(ValueError, match="speed_high must be above speed_low"):
        HighwayPlannerReward(speed_high=10.0)


def test_mappo_trains_on_a_highway_scenario(tmp_path: Path, capsys) -> None:
    code, _, err = run_cli(
        ["train", "mappo", "--env", "highway-intersection", "--run-dir", str(tmp_path / "run"),
         "total_frames=20", "frames_per_batch=10", "minibatch_size=10", "eval_interval=0",
         "checkpoint_interval=0", "eval_episodes=1", "logger=none", "progress=false"],
        capsys,
    )  # fmt: skip
    assert code == 0, err
    assert (tmp_path / "run" / "results.json").is_file()
