"""``wrap_pettingzoo``: any PettingZoo ``ParallelEnv`` gets the layout the recipes read (group
``"agents"``, mask, ``("agents", "position")`` from an info key or a callable, per-agent infos),
bad input is refused naming the parameter, the built-in scenarios are in PettingZoo's registry,
and the stock highway-env example's planner reward agrees with its env."""

from __future__ import annotations

import numpy as np
import pettingzoo
import pytest
import torch
from gymnasium import spaces
from highway_pettingzoo import (
    HighwayParallelEnv,
    highway_collision,
    highway_reward,
    make_highway,
    vehicle_positions,
)
from torchrl.envs.utils import check_env_specs

from mapets_rl.envs import (
    GYM_IDS,
    AgentsPettingZooWrapper,
    TrafficPettingZooWrapper,
    make_parallel_env,
    registered_scenario,
    wrap_parallel_env,
    wrap_pettingzoo,
)

AGENTS = ["a", "b", "c"]
CRASH_STEP = 2
"""Agent ``b`` leaves the env in this step (1-based)."""


class LineEnv(pettingzoo.ParallelEnv):
    """Three agents on a line: agent ``k`` at ``(10 k + t, k)`` after step ``t``, observing it;
    ``b`` terminates in step ``CRASH_STEP``; infos ``xy`` ``[2]`` and ``speed``."""

    metadata = {"name": "line_v0"}

    def __init__(self, horizon: int = 4) -> None:
        self.possible_agents = list(AGENTS)
        self.agents: list[str] = []
        self.horizon = horizon

    def observation_space(self, agent: str) -> spaces.Box:
        return spaces.Box(-np.inf, np.inf, shape=(2,), dtype=np.float32)

    def action_space(self, agent: str) -> spaces.Box:
        return spaces.Box(-1.0, 1.0, shape=(1,), dtype=np.float32)

    @property
    def xy(self) -> np.ndarray:
        """``[3, 2]`` positions, in the order of ``possible_agents``."""
        k = np.arange(3, dtype=np.float32)
        return np.stack([10 * k + self.t, k], axis=-1)

    def _out(self, agents: list[str]) -> tuple[dict, dict]:
        xy = self.xy
        obs = {a: xy[AGENTS.index(a)] for a in agents}
        return obs, {a: {"xy": xy[AGENTS.index(a)], "speed": 1.0} for a in agents}

    def reset(self, seed: int | None = None, options: dict | None = None) -> tuple[dict, dict]:
        self.t = 0
        self.agents = list(AGENTS)
        return self._out(self.agents)

    def step(self, actions: dict) -> tuple[dict, dict, dict, dict, dict]:
        self.t += 1
        acting = list(self.agents)
        terminated = {a: a == "b" and self.t == CRASH_STEP for a in acting}
        truncated = {a: self.t >= self.horizon for a in acting}
        self.agents = [a for a in acting if not (terminated[a] or truncated[a])]
        obs, infos = self._out(acting)
        return obs, {a: 1.0 for a in acting}, terminated, truncated, infos


def _expected_positions(steps: int) -> torch.Tensor:
    """``("next", "agents", "position")`` of a rollout of ``steps`` steps from a reset."""
    k = torch.arange(3.0)
    return torch.stack(
        [torch.stack([10 * k + t, k], dim=-1) for t in range(1, steps + 1)]
    )  # [T, 3, 2]


@pytest.mark.parametrize(
    "position, info_keys",
    [("xy", {"speed"}), (lambda env: env.xy, {"xy", "speed"})],
    ids=["info key", "callable"],
)
def test_any_parallel_env_gets_the_agents_layout_with_positions(position, info_keys) -> None:
    env = wrap_pettingzoo(LineEnv(), position=position, seed=0)
    assert isinstance(env, AgentsPettingZooWrapper)
    check_env_specs(env)
    td = env.rollout(3, break_when_any_done=False)
    assert td["agents", "observation"].shape == (3, 3, 2)
    assert td["agents", "action"].shape == (3, 3, 1)
    position_next = td["next", "agents", "position"]
    assert position_next.dtype == torch.float32
    live = td["next", "agents", "mask"]
    # b leaves in step 2: masked from then on, its entries zero (stock wrapper) unless callable
    assert live.tolist() == [[True, True, True], [True, False, True], [True, False, True]]
    expected = _expected_positions(3)
    assert torch.equal(position_next[live], expected[live])
    assert torch.equal(td["agents", "position"][0], expected[0] - torch.tensor([1.0, 0.0]))
    assert set(td["next", "agents", "info"].keys()) == info_keys  # an info key is moved
    assert td["next", "agents", "info", "speed"][live].eq(1.0).all()
    assert td["next", "agents", "terminated"][1, 1].item()


def test_position_none_gives_no_position_key() -> None:
    env = wrap_pettingzoo(LineEnv(), position=None)
    check_env_specs(env)
    td = env.rollout(2)
    assert ("agents", "position") not in td.keys(True)
    assert set(td["next", "agents", "info"].keys()) == {"xy", "speed"}


def test_traffic_parallel_env_takes_the_vectorised_path() -> None:
    env = wrap_pettingzoo(make_parallel_env("freeway", n_vehicles=4, horizon=3), seed=0)
    assert isinstance(env, TrafficPettingZooWrapper)
    check_env_specs(env)
    assert env.rollout(2)["next", "agents", "position"].shape == (2, 4, 2)


def test_agent_index_places_each_agent_in_the_joint_arrays() -> None:
    """``agent_index[agent]`` is the agent's row of the raw env's joint arrays: an action
    written there is the one ``joint_action`` builds from the agents' dict; read-only."""
    env = make_parallel_env("freeway", n_vehicles=4, horizon=3)
    env.reset(seed=0)
    assert dict(env.agent_index) == {agent: i for i, agent in enumerate(env.possible_agents)}
    actions = {agent: (i + 1) % 3 for i, agent in enumerate(env.agents)}
    joint = env.joint_action(actions)
    assert all(joint[env.agent_index[agent]] == move for agent, move in actions.items())
    with pytest.raises(TypeError):
        env.agent_index["cav_0"] = 1  # type: ignore[index]
    env.close()


def test_wrap_parallel_env_is_a_deprecated_name() -> None:
    with pytest.warns(DeprecationWarning, match="use mapets_rl.envs.wrap_pettingzoo"):
        env = wrap_parallel_env(make_parallel_env("freeway", n_vehicles=4, horizon=3))
    assert isinstance(env, TrafficPettingZooWrapper)


@pytest.mark.parametrize(
    "parallel_env, position, message",
    [
        (None, "xy", "parallel_env must be a pettingzoo.ParallelEnv"),
        ("freeway", "xy", "parallel_env must be a pettingzoo.ParallelEnv"),
        (LineEnv, 3, "position must be a per-agent info key"),
        (LineEnv, "where", r"position='where' names no per-agent info .* \['xy', 'speed'\]"),
        (LineEnv, "speed", r"position='speed' must give each of the 3 agents .* got \[3\]"),
        (LineEnv, lambda env: env.xy[:2], r"must return the positions of the 3 agents"),
        (lambda: make_parallel_env("freeway", n_vehicles=4), "xy", "must be 'position' for a"),
    ],
)
def test_bad_input_is_refused_naming_the_parameter(parallel_env, position, message) -> None:
    built = parallel_env() if callable(parallel_env) else parallel_env
    with pytest.raises(ValueError, match=message):
        wrap_pettingzoo(built, position=position)


@pytest.mark.parametrize("name", sorted(GYM_IDS))
def test_builtin_scenarios_are_in_pettingzoo_registry(name: str) -> None:
    scenario = registered_scenario(name)
    spec = pettingzoo.spec("parallel", GYM_IDS[name])
    assert spec.kwargs == dict(scenario.changes)
    length = "duration" if name.startswith("highway-") else "horizon"  # highway-env's [s]
    env = pettingzoo.make("parallel", GYM_IDS[name], **{length: 3})
    assert type(env) is scenario.parallel_env
    assert env.env.config[length] == 3
    for key, value in scenario.changes.items():
        assert key == length or env.env.config[key] == value


# ------------------------------------------------------------ the stock highway-env example
def test_highway_example_wraps_a_stock_env_with_its_vehicles_positions() -> None:
    env = make_highway(duration=3)
    check_env_specs(env)
    td = env.rollout(2)
    vehicles = env.vehicles  # attribute reads reach the ParallelEnv
    assert torch.equal(
        td["next", "agents", "position"][-1], torch.as_tensor(vehicle_positions(env._env))
    )
    assert td["next", "agents", "position"][-1, :, 0].tolist() == pytest.approx(
        [float(v.position[0]) for v in vehicles]
    )
    assert td["agents", "observation"].shape == (2, 3, 15)
    assert td["agents", "action"].shape == (2, 3, 1)


def test_highway_planner_reward_is_the_envs_reward_on_observed_steps() -> None:
    """On real transitions (random actions), ``highway_reward`` gives every live vehicle that
    did not crash the env's speed reward, and ``highway_collision`` (a geometric test on 1 s
    steps, so approximate) flags most crash steps and few others."""
    torch.manual_seed(0)
    env = make_highway(duration=10, n_others=10)
    crashes = flagged_crashes = false_alarms = live_steps = 0
    for seed in range(6):
        env.set_seed(seed)
        td = env.rollout(10)
        obs, action = td["agents", "observation"], td["agents", "action"]
        next_obs = td["next", "agents", "observation"]
        reward = td["next", "agents", "reward"].squeeze(-1)
        acted = td["agents", "mask"]
        crash = td["next", "agents", "terminated"].squeeze(-1) & acted
        flagged = highway_collision(obs, action, next_obs)
        assert torch.equal(reward[crash], torch.full_like(reward[crash], -1.0))
        calm = acted & ~crash & ~flagged
        assert torch.allclose(highway_reward(obs, action, next_obs)[calm], reward[calm], atol=1e-4)
        crashes += int(crash.sum())
        flagged_crashes += int((flagged & crash).sum())
        false_alarms += int((flagged & acted & ~crash).sum())
        live_steps += int(acted.sum())
    assert crashes >= 3 and flagged_crashes >= 0.8 * crashes
    assert false_alarms <= 0.05 * live_steps


@pytest.mark.parametrize(
    "key, value", [("n_agents", 0), ("n_others", -1), ("duration", 1.5), ("observed", True)]
)
def test_highway_adapter_refuses_bad_config(key: str, value: object) -> None:
    with pytest.raises(ValueError, match=f"{key} must be an integer >= "):
        HighwayParallelEnv(**{key: value})
