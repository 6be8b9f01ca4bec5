"""Published configurations: every shipped file loads, builds its recipe's config and trains a
tiny run; includes merge; the twins differ in what their comments say; bad names are refused
naming the published ones."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest
from torch import nn

from mapets_rl.app.plugins import load_recipe
from mapets_rl.config import ConfigError
from mapets_rl.experiment.published import available_configs, load_published
from mapets_rl.modules import RunningObsNorm

TINY_FREEWAY = [
    "env_config.num_envs=2",
    "env_config.n_vehicles=6",
    "frames_per_batch=20",
    "total_frames=40",
    "eval_interval=0",
    "checkpoint_interval=0",
    "eval_episodes=1",
    "logger=none",
    "progress=false",
]
TINY_RECIPE: dict[str, list[str]] = {
    "maddpg": ["batch_size=8", "init_random_frames=0", "update_interval=20"],
    "shapley_ac": [
        "batch_size=8",
        "init_random_frames=0",
        "update_interval=20",
        "num_permutations=4",
    ],  # fmt: skip
    "sac": ["batch_size=8", "init_random_frames=0", "update_interval=20"],
    "mappo": ["minibatch_size=10"],
    "coma": ["minibatch_size=10"],
    "svmix": ["minibatch_size=10"],
    "dqn": ["batch_size=8", "init_random_frames=0", "update_interval=20"],
    "firl": ["minibatch_size=10"],
}
TINY_MAPETS = [
    "episodes=1",
    "env_config.n_cavs=3",
    "env_config.n_hvs=2",
    "env_config.horizon=10",
    "planner.horizon=3",
    "planner.population=8",
    "planner.elites=2",
    "planner.iterations=2",
    "planner.particles=5",
    "planner.compile=false",
    "model.hidden=[16]",
    "model.buffer_size=64",
    "model.batch_size=16",
    "model.epochs=2",
    "num_threads=1",
    "progress=false",
]

TINY_HIGHWAY = [
    "frames_per_batch=20",
    "total_frames=40",
    "eval_interval=0",
    "checkpoint_interval=0",
    "eval_episodes=1",
    "logger=none",
    "progress=false",
]
"""The highway-env multi-agent scenarios (``highway-*``): their small defaults, a tiny budget."""
TINY_HIGHWAY_MAPETS = [
    *(item for item in TINY_MAPETS if not item.startswith("env_config.")),
    "eval_episodes=1",
    "env_config.duration=3",
]

TINY_LOOP = [
    "env_config.n_cavs=3",
    "env_config.n_hvs=2",
    "env_config.horizon=20",
    *(item for item in TINY_FREEWAY if not item.startswith("env_config.")),
]
"""The figure-eights (``figure-eight*``) for a model-free recipe: 3 CAVs, a tiny budget."""

NAMES = [c.name for c in available_configs()]


def tiny_overrides(recipe: str, env: str) -> list[str]:
    """The overrides that shrink a published config of ``recipe`` on ``env`` to a tiny run."""
    if env.startswith("highway-"):
        return TINY_HIGHWAY_MAPETS if recipe == "mapets" else [*TINY_HIGHWAY,
                                                              *TINY_RECIPE[recipe]]  # fmt: skip
    if recipe == "mapets":
        return TINY_MAPETS
    if env.startswith("figure-eight"):
        return [*TINY_LOOP, *TINY_RECIPE[recipe]]
    return [*TINY_FREEWAY, *TINY_RECIPE[recipe]]


def test_the_headline_arms_are_published() -> None:
    assert set(NAMES) >= {
        "freeway-merge/maddpg-individual",
        "freeway-merge/maddpg-team",
        "freeway-merge/maddpg-team-shared-critic",
        "freeway-merge/shapley-arm",
        "freeway-merge/shapley-ac-paper",
        "freeway-merge/mappo",
        "freeway-merge/coma",
        "freeway-merge-dilemma/maddpg-individual",
        "freeway-merge-dilemma/maddpg-team",
        "freeway-merge-dilemma/shapley-arm",
        "freeway-merge-dilemma/shapley-ac-paper",
        "figure-eight/mapets",
        "figure-eight-multilane/mapets",
    }
    assert all(c.summary and c.recipe for c in available_configs())


@pytest.mark.parametrize("name", NAMES)
def test_a_published_config_trains_a_tiny_run(name: str, tmp_path: Path) -> None:
    published = load_published(name)
    if published.fields.get("env_config", {}).get("backend") == "sumo":
        pytest.importorskip("libsumo", reason="the SUMO configs need pip install 'mapets-rl[sumo]'")
    cls = load_recipe(published.recipe)
    tiny = tiny_overrides(published.recipe, published.fields.get("env", ""))
    config = cls.Config.from_fields(published.fields, tiny)
    exp = cls(config, tmp_path / "run")
    exp.train()
    assert exp.frames > 0
    assert (tmp_path / "run" / "results.json").is_file()


def test_includes_merge_under_the_files_own_fields() -> None:
    individual = load_published("freeway-merge/maddpg-individual").fields
    team = load_published("freeway-merge/maddpg-team").fields
    stack = load_published("fragments/freeway-merge-stack").fields
    openai = load_published("fragments/openai-maddpg").fields
    assert individual["env_config"] == {**stack["env_config"], "team_reward": False}
    assert all(individual[key] == value for key, value in openai.items())
    differ = {k for k in individual if individual[k] != team[k]}
    assert differ == {"env_config"}
    assert {k for k, v in individual["env_config"].items() if team["env_config"][k] != v} == {
        "team_reward"
    }


def test_the_maddpg_arm_is_the_schedule_the_study_trained() -> None:
    """The file gives what cooperation_control's maddpg_epsilon_shield_w1_individual variant
    set (1M frames, 100k-frame annealing, 256 roads of 30 CAVs)."""
    config = load_recipe("maddpg").Config.from_fields(
        load_published("freeway-merge/maddpg-individual").fields
    )
    expected: dict[str, Any] = {
        "update_interval": 100, "batch_size": 1024, "lr_actor": 0.01, "lr_critic": 0.01,
        "gamma": 0.95, "tau": 0.01, "num_cells": [64, 64], "max_grad_norm": 0.5,
        "frames_per_batch": 1024, "epsilon_anneal_frames": 100_000, "exploration": "epsilon",
        "exploration_actions": [0, 1, 2], "total_frames": 1_000_000,
    }  # fmt: skip
    assert {k: getattr(config, k) for k in expected} == expected
    assert config.env_config == {"backend": "torch", "num_envs": 256, "n_vehicles": 30,
                                 "cav_ratio": 1.0, "shield": True, "velocity_weight": 1.0,
                                 "team_reward": False}  # fmt: skip


def test_a_bad_name_is_refused_naming_the_published_ones(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="freeway-merge/maddpg-individual"):
        load_published("freeway-merge/nosuch")
    with pytest.raises(ConfigError, match="neither a file nor"):
        load_published("../pyproject")
    cycle = tmp_path / "cycle.yaml"
    cycle.write_text(f"include: [{cycle}]\n")
    with pytest.raises(ConfigError, match="nest deeper"):
        load_published(cycle)
    bad = tmp_path / "bad.yaml"
    bad.write_text("include: 3\n")
    with pytest.raises(ConfigError, match="include must be a list"):
        load_published(bad)


def test_the_dilemma_arms_build_the_same_actor(tmp_path: Path) -> None:
    """The dilemma study's MADDPG and Shapley arms differ in the critic and the credit only:
    their actors read the same input (each CAV's own 24-entry observation) through the same
    running normaliser and the same layers; the paper's Shapley AC reads the coalition view,
    unnormalised."""
    actors = {}
    for arm in ("maddpg-individual", "shapley-arm", "shapley-ac-paper"):
        published = load_published(f"freeway-merge-dilemma/{arm}")
        cls = load_recipe(published.recipe)
        config = cls.Config.from_fields(published.fields, TINY_FREEWAY)
        actors[arm] = cls(config, tmp_path / arm).actor
    widths = {
        arm: next(m for m in actor.modules() if isinstance(m, nn.Linear)).in_features
        for arm, actor in actors.items()
    }
    assert widths == {"maddpg-individual": 24, "shapley-arm": 24, "shapley-ac-paper": 6 * 25}
    maddpg, shapley = actors["maddpg-individual"], actors["shapley-arm"]
    assert [type(m) for m in maddpg.modules()] == [type(m) for m in shapley.modules()]
    assert any(isinstance(m, RunningObsNorm) for m in shapley.modules())
    assert not any(isinstance(m, RunningObsNorm) for m in actors["shapley-ac-paper"].modules())
    shapes = [[tuple(p.shape) for p in actor.parameters()] for actor in (maddpg, shapley)]
    assert shapes[0] == shapes[1]


def test_the_dilemma_twins_differ_in_what_their_comments_say() -> None:
    """maddpg-team differs from maddpg-individual in the team reward only; the Shapley arm
    shares MADDPG's task, schedule and exploration and adds only its own fields; all four
    run the dilemma variant's scenario settings."""
    arms = {arm: load_published(f"freeway-merge-dilemma/{arm}").fields for arm in
            ("maddpg-individual", "maddpg-team", "shapley-arm", "shapley-ac-paper")}  # fmt: skip
    stack = load_published("fragments/freeway-merge-dilemma-stack").fields["env_config"]
    assert stack["ramp_forcing"] is False and stack["shield"] is True
    for fields in arms.values():
        assert {k: fields["env_config"][k] for k in stack} == stack
    individual, team, shapley = arms["maddpg-individual"], arms["maddpg-team"], arms["shapley-arm"]
    assert {k for k in individual if individual[k] != team[k]} == {"env_config"}
    assert {k for k, v in individual["env_config"].items() if team["env_config"][k] != v} == {
        "team_reward"
    }
    assert all(shapley[k] == v for k, v in individual.items())
    assert shapley["actor_view"] == "own" and shapley["normalize_obs"] is True
