"""MA-PETS refuses bad input before it writes its run directory, with a one-line ValueError: a
scenario it cannot plan on, a planner or ensemble too large for the memory, planner-reward
settings beside a reward_fn, and a reward_fn that is not an importable callable or given
twice. The Shapley actor-critic and COMA refuse continuous actions the same way."""

from __future__ import annotations

from pathlib import Path

import pytest

from mapets_rl.recipes.mapets import MAPETSConfig
from tests.refusals import refused


# ------------------------------------------------------------- MA-PETS: refusals before writing
@pytest.mark.parametrize(
    "env, overrides, match",
    [
        (
            "freeway",
            [],
            r"mapets needs continuous actions \(the CEM planner optimises real-valued action "
            r"sequences\); env 'freeway' has discrete actions",
        ),
        (
            "figure-eight",
            ["planner.population=100000000", "planner.elites=2"],
            r"need about .* GiB on cpu .* more than the .* GiB available: lower",
        ),
        (
            "figure-eight",
            ["model.hidden=[100000, 100000, 100000]"],
            r"need about .* GiB on cpu .* model.hidden=\[100000, 100000, 100000\]",
        ),
    ],
    ids=["discrete actions", "planner too large", "ensemble too large"],
)
def test_mapets_refuses_a_scenario_or_size_before_writing_the_run_dir(
    env: str, overrides: list[str], match: str, tmp_path: Path
) -> None:
    from mapets_rl.recipes.mapets import MAPETS

    config = MAPETSConfig(env=env, preset="cpu").with_overrides(overrides)
    refused(lambda: MAPETS(config, tmp_path / "run"), match)
    assert not (tmp_path / "run").exists()


@pytest.mark.parametrize("recipe", ["shapley_ac", "coma"])
def test_a_discrete_recipe_refuses_continuous_actions_before_writing_the_run_dir(
    recipe: str, tmp_path: Path
) -> None:
    from mapets_rl.app.plugins import load_recipe

    cls = load_recipe(recipe)
    config = cls.Config(env="figure-eight", env_config={"n_cavs": 2, "n_hvs": 1, "horizon": 5})
    refused(
        lambda: cls(config, tmp_path / "run"),
        rf"{recipe} needs discrete actions( \(.*\))?; env 'figure-eight' has continuous actions",
    )
    assert not (tmp_path / "run").exists()


def test_mapets_refuses_planner_reward_settings_beside_a_reward_fn(tmp_path: Path) -> None:
    """planner_reward.collision_gap & co. configure the scenario's planner reward; with a
    reward_fn of the user's (argument or config field) they were silently ignored."""
    from mapets_rl.envs import FigureEightPlannerReward
    from mapets_rl.recipes.mapets import MAPETS

    config = MAPETSConfig(env="figure-eight", preset="cpu", planner_reward={"collision_gap": 3})
    reward = FigureEightPlannerReward().reward
    refused(
        lambda: MAPETS(config, tmp_path / "run", reward_fn=reward),
        r"planner_reward.collision_gap=3.0 configures the scenario's planner reward, which a "
        "given reward_fn replaces",
    )
    refused(
        lambda: MAPETS(
            config.with_overrides(["reward_fn=mapets_rl.envs:FigureEightPlannerReward"]),
            tmp_path / "run",
        ),
        "planner_reward.collision_gap=3.0 configures",
    )
    assert not (tmp_path / "run").exists()


@pytest.mark.parametrize(
    ("value", "why"),
    [
        ("no_such_package_xyz.rewards:speed", "ModuleNotFoundError"),
        ("mapets_rl.envs:no_such_reward", "AttributeError"),
        ("mapets_rl.envs.figure_eight:COLLISION_REWARD", "a float, not callable"),
        ("not a name", "ValueError"),
    ],
)
def test_mapets_reward_fn_must_name_an_importable_callable(value: str, why: str) -> None:

    refused(
        lambda: MAPETSConfig(preset="cpu").with_overrides([f"reward_fn={value}"]),
        rf"reward_fn must be 'package.module:function', an importable callable .*{why}",
    )


def test_mapets_refuses_a_reward_fn_given_twice(tmp_path: Path) -> None:
    from mapets_rl.recipes.mapets import MAPETS

    config = MAPETSConfig(preset="cpu", reward_fn="tests.recipes.test_recipe_mapets:speed_reward")
    refused(
        lambda: MAPETS(config, tmp_path / "run", reward_fn=lambda o, a, n: n[..., 0]),
        "reward_fn is given twice",
    )
    assert not (tmp_path / "run").exists()


def test_mapets_planner_reward_is_refused_for_a_scenario_without_one() -> None:

    refused(
        lambda: MAPETSConfig(env="freeway").with_overrides(["planner_reward.headway=1"]),
        "planner_reward must be left out for env 'freeway', whose scenario registers no "
        "planner reward",
    )
