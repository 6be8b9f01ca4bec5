"""Configuration reaches the experiment as the user wrote it: scenario defaults come from the
scenario (declared once), unknown scenario keys are refused before anything runs."""

from __future__ import annotations

from pathlib import Path

import gymnasium as gym
import pytest

from mapets_rl.app.cli import main
from mapets_rl.envs import GYM_IDS, builtin_envs, make_env, make_parallel_env
from mapets_rl.recipes.mapets import MAPETS, MAPETSConfig

TINY_PLANNER = dict(
    preset="cpu",
    planner={"horizon": 2, "population": 4, "elites": 1, "iterations": 1, "particles": 5},
    model={"hidden": [8]},
    num_threads=1,
    progress=False,
)


def test_a_recipe_trains_the_scenario_s_own_agent_count(tmp_path: Path) -> None:
    multilane = MAPETS(MAPETSConfig(env="figure-eight-multilane", **TINY_PLANNER), tmp_path / "a")
    assert multilane.n_agents == 22 and multilane.model.n_agents == 22
    single = MAPETS(MAPETSConfig(env="figure-eight", **TINY_PLANNER), tmp_path / "b")
    assert single.n_agents == 8


@pytest.mark.parametrize("name", builtin_envs())
def test_unknown_scenario_keys_are_refused_with_the_accepted_ones(name: str) -> None:
    # the freeways derive n_cavs from n_vehicles x cav_ratio: n_vehicles is what a user sets;
    # highway-env's multi-agent scenarios count controlled_vehicles
    size_key = {"freeway": "n_vehicles", "highway": "controlled_vehicles"}.get(
        name.split("-")[0], "n_cavs"
    )
    with pytest.raises(
        ValueError,
        match=rf"unknown config key\(s\) \['bogus'\].*accepted keys.*'{size_key}'",
    ):
        make_env(name, bogus=1)
    with pytest.raises(ValueError, match="n_cav"):
        make_parallel_env(name, n_cav=4)


def test_an_env_config_typo_fails_before_the_run_directory_exists(tmp_path: Path, capsys) -> None:
    run_dir = tmp_path / "run"
    with pytest.raises(ValueError, match=r"\['n_cav'\]"):
        MAPETS(MAPETSConfig(env_config={"n_cav": 4}, **TINY_PLANNER), run_dir)
    assert not run_dir.exists()
    with pytest.raises(SystemExit) as exit_info:
        main(
            [
                "train",
                "mapets",
                "--env",
                "figure-eight",
                "--run-dir",
                str(run_dir),
                "env_config.n_cav=4",
                "preset=cpu",
            ]
        )
    code, err = exit_info.value.code, capsys.readouterr().err
    assert code == 2 and "n_cav" in err and err.count("\n") == 1
    assert not run_dir.exists()


@pytest.mark.parametrize("name", sorted(GYM_IDS))
def test_gymnasium_ids_use_the_scenario_defaults(name: str) -> None:
    raw = gym.make(GYM_IDS[name]).unwrapped
    parallel = make_parallel_env(name).env
    for key in ("n_cavs", "horizon", "lanes", "n_vehicles", "cav_ratio"):
        if key in parallel.config:
            assert raw.config[key] == parallel.config[key], key
    if name == "figure-eight-multilane":
        assert (raw.config["n_cavs"], raw.config["horizon"], raw.config["lanes"]) == (22, 400, 2)
