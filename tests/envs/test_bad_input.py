"""Scenarios refuse bad input with a one-line ValueError naming the parameter, before any work
starts: constructor arguments, actions that are not one-hot, of the wrong shape or given after
the episode ended, and registry entries that are not callable or would replace a scenario."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np
import pytest
import torch
from tensordict import TensorDict
from toy_scenario import ToyAgentsEnv

from mapets_rl.envs import FigureEightEnv, FreewayEnv, make_env, registry
from mapets_rl.experiment import register_env
from tests.refusals import INF, NAN, refused

pytestmark = pytest.mark.usefixtures("toy_scenario")


# ------------------------------------------------------------------- scenario constructors
ENV_CASES = [
    (
        "highway-env's other_vehicles_type",
        lambda: FigureEightEnv({"other_vehicles_type": "x.IDMVehicle"}),
        r"unknown config key\(s\) \['other_vehicles_type'\]",
    ),
    (
        "highway-env's action dict",
        lambda: FreewayEnv({"action": {"type": "ContinuousAction"}}),
        r"unknown config key\(s\) \['action'\]",
    ),
    (
        "highway-env's observation dict on the freeway",
        lambda: FreewayEnv({"observation": {"type": "Kinematics"}}),
        r"unknown config key\(s\) \['observation'\]",
    ),
    (
        "the freeway's derived n_cavs",
        lambda: FreewayEnv({"n_cavs": 3}),
        r"unknown config key\(s\) \['n_cavs'\]",
    ),
    ("max_speed=1e9", lambda: FigureEightEnv({"max_speed": 1e9}), "max_speed must be .* <= 60"),
    (
        "hv_target_speed above max_speed",
        lambda: FigureEightEnv({"hv_target_speed": (10.0, 1e9)}),
        r"hv_target_speed must be a range .* hi <= 13.89",
    ),
    (
        "freeway speed_limit=1e9",
        lambda: FreewayEnv({"speed_limit": 1e9}),
        "speed_limit must be .* <= 60",
    ),
    (
        "freeway hv_target_speed above the limit",
        lambda: FreewayEnv({"hv_target_speed": (10.0, 1e9)}),
        r"hv_target_speed must be a range .* hi <= 31.3",
    ),
    ("length=inf", lambda: FigureEightEnv({"length": INF}), "length must be a finite number > 0"),
    ("length=-1", lambda: FigureEightEnv({"length": -1.0}), "length must be a finite number > 0"),
    (
        "max_speed=-5",
        lambda: FigureEightEnv({"max_speed": -5.0}),
        "max_speed must be a finite number > 0",
    ),
    (
        "max_speed=nan",
        lambda: FigureEightEnv({"max_speed": NAN}),
        "max_speed must be a finite number > 0",
    ),
    (
        "initial_speed low > high",
        lambda: FigureEightEnv({"initial_speed": (8.0, 4.0)}),
        "initial_speed must be a range",
    ),
    (
        "initial_speed negative",
        lambda: FigureEightEnv({"initial_speed": (-5.0, -1.0)}),
        "initial_speed must be a range .* 0 <= lo <= hi",
    ),
    (
        "initial_speed above max_speed",
        lambda: FigureEightEnv({"initial_speed": (4.0, 30.0)}),
        r"initial_speed .* hi <= 13.89",
    ),
    (
        "hv_target_speed nan",
        lambda: FigureEightEnv({"hv_target_speed": (NAN, 10.0)}),
        "hv_target_speed must be a range",
    ),
    ("n_hvs=many", lambda: FigureEightEnv({"n_hvs": "many"}), "n_hvs must be an int >= 0"),
    ("n_hvs=2.5", lambda: FigureEightEnv({"n_hvs": 2.5}), "n_hvs must be an int >= 0"),
    ("lanes=1.5", lambda: FigureEightEnv({"lanes": 1.5}), "lanes must be 1 or 2"),
    (
        "collision_reward=nan",
        lambda: FigureEightEnv({"collision_reward": NAN}),
        "collision_reward must be a finite number",
    ),
    ("n_cavs=True", lambda: FigureEightEnv({"n_cavs": True}), "n_cavs must be an integer"),
    (
        "min_spacing=nan",
        lambda: FigureEightEnv({"min_spacing": NAN}),
        "min_spacing must be a finite number >= 7",
    ),
    (
        "freeway velocity_weight=nan",
        lambda: FreewayEnv({"velocity_weight": NAN}),
        "velocity_weight must be a finite number",
    ),
    (
        "freeway speed_limit=-1",
        lambda: FreewayEnv({"speed_limit": -1.0}),
        "speed_limit must be a finite number > 0",
    ),
    (
        "freeway cav_ratio='half'",
        lambda: FreewayEnv({"cav_ratio": "half"}),
        r"cav_ratio must be a number in \[0, 1\]",
    ),
    (
        "freeway initial_speed low > high",
        lambda: FreewayEnv({"initial_speed": (28.0, 22.0)}),
        "initial_speed must be a range",
    ),
    (
        "freeway perception=0",
        lambda: FreewayEnv({"perception": 0.0}),
        "perception must be a finite number > 0",
    ),
    (
        "freeway collision_reward=nan",
        lambda: FreewayEnv({"collision_reward": NAN}),
        "collision_reward must be a finite number",
    ),
    (
        "torchrl env length=inf",
        lambda: make_env("figure-eight", length=INF),
        "length must be a finite number",
    ),
    (
        "torchrl env speed_limit=nan",
        lambda: make_env("freeway", speed_limit=NAN),
        "speed_limit must be a finite number",
    ),
]


@pytest.mark.parametrize("call, match", [c[1:] for c in ENV_CASES], ids=[c[0] for c in ENV_CASES])
def test_scenario_configrefused(call: Callable[[], Any], match: str) -> None:
    refused(call, match)


# ------------------------------------------------------------------------------- actions
@pytest.fixture(scope="module")
def freeway() -> Any:
    return make_env("freeway", n_vehicles=4, seed=0)


def _one_hot_rows(rows: list[list[float]]) -> torch.Tensor:
    return torch.tensor(rows, dtype=torch.float32)


KL = [1.0, 0.0, 0.0, 0.0]
FREEWAY_ACTIONS = [
    ("all-zero", [KL, KL, KL, [0.0, 0.0, 0.0, 0.0]]),
    ("two-hot", [KL, [1.0, 1.0, 0.0, 0.0], KL, KL]),
    ("fractional", [KL, KL, [0.25, 0.25, 0.25, 0.25], KL]),
    ("nan", [[NAN, 0.0, 0.0, 0.0], KL, KL, KL]),
    ("negative", [KL, KL, KL, [2.0, -1.0, 0.0, 0.0]]),
]


@pytest.mark.parametrize(
    "rows", [a[1] for a in FREEWAY_ACTIONS], ids=[a[0] for a in FREEWAY_ACTIONS]
)
def test_freeway_torchrl_env_refuses_actions_that_are_not_one_hot(freeway, rows) -> None:
    td = freeway.reset()
    td["agents", "action"] = _one_hot_rows(rows)
    refused(lambda: freeway.step(td), "must be one-hot per CAV")
    # a valid one passes, also as a straight-through estimator writes it (1 - 6e-8)
    td["agents", "action"] = _one_hot_rows([KL] * 3 + [[0.99999994, 0.0, 0.0, 0.0]])
    assert freeway.step(td)["next", "agents", "reward"].shape == (4, 1)


def test_torchrl_env_refuses_a_wrong_batch_shape_and_a_missing_action(freeway) -> None:
    td = freeway.reset()
    td["agents"] = TensorDict({"action": torch.zeros(2, 4, 4)}, [])
    refused(lambda: freeway.step(td), r"must have shape \[4, 4\], got \[2, 4, 4\]")
    refused(lambda: freeway.step(freeway.reset()), "step needs the CAVs' actions")


RAW_ACTIONS = [
    ("None", None, r"step needs the CAVs' action \(got None\)"),
    ("strings", [["fast"]] * 8, "action must be an array of numbers, got a list of dtype <U4"),
    ("dict", {"cav_0": 3.0}, "action must be an array of numbers, got a dict"),
    ("ragged", [[1.0], [2.0, 3.0]], "action must be an array of numbers"),
    ("bools", np.ones((8, 1), dtype=bool), "action must be an array of numbers"),
    ("wrong shape", np.ones((7, 1)), r"action must have shape \(8, 1\)"),
    ("nan", np.full((8, 1), NAN), "action must be finite"),
]


@pytest.mark.parametrize(
    "action, match", [a[1:] for a in RAW_ACTIONS], ids=[a[0] for a in RAW_ACTIONS]
)
def test_raw_env_refuses_bad_actions(action: Any, match: str) -> None:
    env = FigureEightEnv({"n_hvs": 4})
    refused(lambda: env.step(action), match)


def test_raw_env_refuses_a_step_after_the_episode_ended() -> None:
    env = FigureEightEnv({"n_hvs": 2, "horizon": 2})
    env.reset(seed=0)
    action = np.full((8, 1), 5.0, dtype=np.float32)
    assert [env.step(action)[3] for _ in range(2)] == [False, True]
    refused(lambda: env.step(action), r"the episode is over .* call reset\(\)")
    env.reset(seed=1)
    assert env.step(action)[3] is False  # a reset makes it usable again


# ------------------------------------------------------------------------------ registry
def test_register_env_refuses_a_non_callable_factory() -> None:
    refused(lambda: register_env("x", 42), "factory must be callable")
    assert "x" not in registry._SCENARIOS


def test_register_env_does_not_silently_replace_a_scenario(monkeypatch) -> None:
    monkeypatch.setattr(registry, "_SCENARIOS", dict(registry._SCENARIOS))
    refused(lambda: register_env("freeway", ToyAgentsEnv), "'freeway' is a built-in scenario")
    refused(lambda: register_env("toy", lambda: None), "'toy' is already registered")
    refused(lambda: register_env("", ToyAgentsEnv), "name must be a non-empty scenario name")
    register_env("toy", ToyAgentsEnv)  # the same factory again: a no-op
    register_env("freeway", ToyAgentsEnv, overwrite=True)
    assert registry._SCENARIOS["freeway"].factory is ToyAgentsEnv
