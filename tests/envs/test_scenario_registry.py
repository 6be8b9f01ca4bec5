"""The one scenario registry (``mapets_rl.envs.registry``): what ``register_env`` adds is seen by
``mapets_rl.envs`` and ``mapets_rl.experiment`` alike, built by name, protected against silent
replacement and resolved by the sweep; the built-in scenarios, the registry's names and the
gymnasium ids agree."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import gymnasium as gym
import pytest
from toy_scenario import ToyAgentsEnv

import mapets_rl.envs as envs
import mapets_rl.experiment as experiment
from mapets_rl.app.sweep import SweepSpec, plan_trials, trial_scenarios
from mapets_rl.envs import registry
from mapets_rl.envs.registry import SCENARIO_GROUP

TOY_CONFIG = {"n_agents": 2, "horizon": 3}


@pytest.fixture(autouse=True)
def own_registry(monkeypatch) -> None:
    """Every test registers into a copy of the registry (nothing leaks into other tests)."""
    monkeypatch.setattr(registry, "_SCENARIOS", dict(registry._SCENARIOS))


@pytest.mark.parametrize("register_env", [envs.register_env, experiment.register_env])
def test_a_registered_scenario_is_listed_and_built_through_both_packages(register_env) -> None:
    register_env("toy-line", ToyAgentsEnv)
    assert "toy-line" in envs.available_envs()
    assert envs.available_envs() == experiment.available_envs()
    for build_env in (envs.build_env, experiment.build_env):
        env = build_env("toy-line", TOY_CONFIG)
        assert isinstance(env, ToyAgentsEnv)
        assert env.full_observation_spec["agents", "observation"].shape == (2, 2)
    assert envs.registered_scenario("toy-line").factory is ToyAgentsEnv
    assert not envs.registered_scenario("toy-line").builtin
    assert envs.scenario_defaults("toy-line") == {}
    assert "toy-line" not in envs.builtin_envs()


def test_a_duplicate_name_is_refused_without_overwrite() -> None:
    envs.register_env("toy-line", ToyAgentsEnv)
    envs.register_env("toy-line", ToyAgentsEnv)  # the same factory again: a no-op

    def other(**config: Any) -> ToyAgentsEnv:
        return ToyAgentsEnv(n_agents=4, horizon=config.get("horizon", 10))

    with pytest.raises(ValueError, match="'toy-line' is already registered; pass overwrite=True"):
        experiment.register_env("toy-line", other)
    with pytest.raises(ValueError, match="'figure-eight' is a built-in scenario"):
        envs.register_env("figure-eight", other)
    assert isinstance(envs.build_env("toy-line", TOY_CONFIG), ToyAgentsEnv)
    assert envs.build_env("toy-line", TOY_CONFIG).n_agents == 2

    experiment.register_env("toy-line", other, overwrite=True)
    assert envs.build_env("toy-line", {"horizon": 3}).n_agents == 4
    envs.register_env("figure-eight", other, overwrite=True)
    assert envs.build_env("figure-eight", {"horizon": 3}).n_agents == 4
    assert "figure-eight" not in envs.builtin_envs()
    assert "figure-eight" in envs.available_envs()
    # the replaced scenario no longer has the built-in's defaults
    assert envs.scenario_defaults("figure-eight") == {}


def test_an_installed_scenario_is_listed_by_both_packages_and_built(add_entry_point) -> None:
    add_entry_point(SCENARIO_GROUP, "toy-plugin", "toy_scenario:ToyAgentsEnv")
    assert "toy-plugin" in envs.available_envs()
    assert "toy-plugin" in experiment.available_envs()
    assert envs.registered_scenario("toy-plugin") is None  # loaded only when built
    assert isinstance(envs.build_env("toy-plugin", TOY_CONFIG), ToyAgentsEnv)
    with pytest.raises(ValueError, match="'toy-plugin' is an installed scenario"):
        envs.register_env("toy-plugin", ToyAgentsEnv)


def test_an_unknown_name_is_refused_naming_every_scenario() -> None:
    envs.register_env("toy-line", ToyAgentsEnv)
    with pytest.raises(ValueError, match=r"unknown scenario name 'nowhere'.*'toy-line'") as err:
        experiment.build_env("nowhere")
    assert "figure-eight" in str(err.value) and "\n" not in str(err.value)


def test_the_sweep_resolves_the_registered_scenario(toy_recipe, tmp_path: Path) -> None:
    """The sweep checks and builds a scenario registered in this process through the registry,
    and hands its factory to the trials by import path; a built-in scenario is not handed over
    (every process has it), a replaced one is."""
    built: list[dict[str, Any]] = []

    def recording(**config: Any) -> ToyAgentsEnv:
        built.append(config)
        return ToyAgentsEnv(**config)

    envs.register_env("toy-line", recording)
    spec = SweepSpec(
        recipe="toy",
        env="toy-line",
        seeds=[0],
        out=tmp_path / "sweep",
        grid={"env_config.n_agents": [2, 3]},
    )
    _, trials = plan_trials(spec)
    assert [t.config["env"] for t in trials] == ["toy-line", "toy-line"]
    assert [config["n_agents"] for config in built] == [2, 3]
    with pytest.raises(ValueError, match="scenario 'toy-line' .* is not importable"):
        trial_scenarios("toy-line")

    experiment.register_env("toy-line", ToyAgentsEnv, overwrite=True)
    assert trial_scenarios("toy-line") == {"toy-line": "toy_scenario:ToyAgentsEnv"}
    assert trial_scenarios("figure-eight") == {}
    envs.register_env("freeway", ToyAgentsEnv, overwrite=True)
    assert trial_scenarios("freeway") == {"freeway": "toy_scenario:ToyAgentsEnv"}


def test_builtin_names_registry_names_and_gym_ids_agree() -> None:
    builtin = envs.builtin_envs()
    assert builtin == [
        "figure-eight",
        "figure-eight-multilane",
        "freeway",
        "freeway-merge",
        "highway-intersection",
        "highway-merge",
        "highway-multi",
        "highway-roundabout",
    ]
    assert set(builtin) <= set(envs.available_envs())
    assert sorted(envs.GYM_IDS) == builtin
    for name in builtin:
        scenario = envs.registered_scenario(name)
        assert scenario.builtin and scenario.gym_id == envs.GYM_IDS[name]
        spec = gym.spec(scenario.gym_id)
        env_class = scenario.parallel_env.env_class
        assert spec.entry_point == f"{env_class.__module__}:{env_class.__name__}"
        assert spec.kwargs == {"config": dict(scenario.changes)}
        assert envs.scenario_defaults(name) == {
            **env_class.default_config(),
            **scenario.changes,
        }
    assert envs.registered_scenario("figure-eight-multilane").changes == {
        "lanes": 2,
        "n_cavs": 22,
        "horizon": 400,
    }


def test_a_builtin_scenario_is_built_by_name_with_its_changes() -> None:
    env = envs.build_env("figure-eight-multilane", {"n_hvs": 2, "horizon": 5})
    assert env.full_observation_spec["agents", "observation"].shape[0] == 22
    assert isinstance(envs.make_parallel_env("freeway-merge"), envs.FreewayMergeParallelEnv)
