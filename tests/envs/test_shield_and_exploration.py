"""The tools of issue 32's positive control: the batched freeway's model-predictive shield
(``env_config.shield``) and the epsilon-greedy exploration without random braking of MADDPG and
the Shapley actor-critic."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest
import torch
from torchrl.envs.utils import check_env_specs

from mapets_rl.envs import make_env
from mapets_rl.envs.freeway import ES, KL
from mapets_rl.envs.torch_freeway.simulator import BatchedFreeway
from mapets_rl.experiment import ConfigError
from mapets_rl.recipes.maddpg import MADDPG, MADDPGConfig
from mapets_rl.recipes.shapley_ac import ShapleyAC, ShapleyACConfig

ROADS = 16


def _random_episode(shield: bool, seed: int = 0) -> list[dict[str, float]]:
    """One 40-step episode of uniformly random decisions on ``ROADS`` roads of 30 CAVs."""
    env = make_env("freeway-merge", backend="torch", num_envs=ROADS, shield=shield)
    env.set_seed(seed)
    td = env.reset()
    generator = torch.Generator().manual_seed(seed)
    for _ in range(40):
        index = torch.randint(0, 4, (ROADS, 30), generator=generator)
        td.set(("agents", "action"), torch.nn.functional.one_hot(index, 4))
        td = env.step(td).get("next")
    return env.pop_finished_episodes()


def _random_decisions(
    shield: bool, seed: int, steps: int, high: int = 4
) -> Iterator[tuple[BatchedFreeway, torch.Tensor]]:
    """``ROADS`` roads of freeway-merge (30 CAVs) reset with ``seed``, and ``steps`` draws of
    uniformly random decisions ``[ROADS, CAVs]`` in ``[0, high)``; the caller steps the roads."""
    env = make_env("freeway-merge", backend="torch", num_envs=ROADS, shield=shield)
    env.set_seed(seed)
    env.reset()
    generator = torch.Generator().manual_seed(seed)
    for _ in range(steps):
        yield env.sim, torch.randint(0, high, (ROADS, env.sim.n_cavs), generator=generator)


def test_the_shield_leaves_the_roads_as_they_were_and_replaces_only_moves() -> None:
    replaced_any = False
    for sim, action in _random_decisions(shield=True, seed=3, steps=12):
        before = sim.snapshot()
        safe, replaced = sim.shield(action)
        after = sim.snapshot()
        for key in before.keys(True, True):
            assert torch.equal(before.get(key), after.get(key)), key
        assert torch.equal(replaced, safe != action)
        assert bool((safe[replaced] == KL).all())  # a replaced decision becomes Keep Lane
        assert not bool((replaced & (action == KL)).any())  # Keep Lane is never replaced
        replaced_any |= bool(replaced.any())
        sim.step(action)
    assert replaced_any


def test_the_predicted_first_step_is_the_real_step() -> None:
    """The shield's check steps a copy deterministically: its first row is exactly the crashes
    of the real step with the same decisions (random ones, unshielded, so that some crash)."""
    crashes = 0
    for sim, action in _random_decisions(shield=False, seed=5, steps=12):
        predicted = sim.predicted_crashes(action)
        assert predicted.shape == (sim.config["shield_horizon"], ROADS, sim.n_cavs)
        collided = sim.step(action).collided
        assert torch.equal(predicted[0], collided)
        crashes += int(collided.sum())
    assert crashes > 0


def test_repeated_passes_leave_no_move_that_the_check_predicts_to_crash() -> None:
    """With ``shield_passes`` large the corrected decisions are a fixed point of the check: no
    move that runs is predicted to crash beside the others that run; one pass leaves some
    (random lane changes on a crowded merge), and more passes only add replacements."""
    left_by_one_pass = 0
    for sim, action in _random_decisions(shield=True, seed=0, steps=25, high=ES):  # KL, CL, CR
        sim.config["shield_passes"] = 1
        once, replaced_once = sim.shield(action)
        sim.config["shield_passes"] = 40
        safe, replaced = sim.shield(action)
        assert not bool((sim.predicted_crashes(safe).any(0) & (safe != KL)).any())
        assert bool((replaced >= replaced_once).all())
        left_by_one_pass += int((sim.predicted_crashes(once).any(0) & (once != KL)).sum())
        sim.step(action)
    assert left_by_one_pass > 0


def test_the_shield_prevents_most_crashes_of_random_decisions_and_counts_itself() -> None:
    unshielded = _random_episode(shield=False)
    shielded = _random_episode(shield=True)
    crashes = sum(e["collisions"] for e in unshielded)
    crashes_shielded = sum(e["collisions"] for e in shielded)
    assert crashes_shielded < 0.5 * crashes, (crashes_shielded, crashes)
    assert all(e["shielded"] > 0 for e in shielded)
    assert "shielded" not in unshielded[0]


def test_a_shielded_env_reports_its_interventions_in_the_specs() -> None:
    env = make_env("freeway-merge", backend="torch", num_envs=2, n_vehicles=8, shield=True)
    check_env_specs(env)
    td = env.rollout(3)
    assert td.get(("next", "agents", "info", "shielded")).shape == (2, 3, 8)


@pytest.mark.parametrize(
    ("backend", "config", "match"),
    [
        ("highway-env", {"shield": True}, "backend='torch'"),
        ("torch", {"shield": "yes"}, "shield"),
        ("torch", {"shield": True, "shield_horizon": 0}, "shield_horizon"),
        ("torch", {"shield": True, "shield_horizon": 2.5}, "shield_horizon"),
        ("torch", {"shield": True, "shield_passes": 0}, "shield_passes"),
        ("torch", {"shield": True, "shield_passes": 41}, "shield_passes"),
    ],
)
def test_a_bad_shield_is_refused(backend: str, config: dict, match: str) -> None:
    with pytest.raises(ValueError, match=match):
        make_env("freeway-merge", backend=backend, n_vehicles=8, **config)


def _learner(tmp_path: Path, recipe: type = MADDPG, **changes) -> MADDPG | ShapleyAC:
    settings = {
        "env_config": {"backend": "torch", "num_envs": 8, "n_vehicles": 8, "cav_ratio": 1.0},
        "frames_per_batch": 160,
        "total_frames": 320,
        "eval_interval": 0,
        "checkpoint_interval": 0,
        "num_cells": [16],
        "batch_size": 16,
        "init_random_frames": 0,
        "progress": False,
        "logger": "none",
    }
    config = recipe.Config(env="freeway-merge", **{**settings, **changes})
    return recipe(config, tmp_path)


@pytest.mark.parametrize("recipe", [MADDPG, ShapleyAC])
def test_epsilon_greedy_exploration_draws_only_the_allowed_actions_and_anneals(
    tmp_path: Path, recipe: type
) -> None:
    exp = _learner(
        tmp_path,
        recipe,
        exploration="epsilon",
        exploration_actions=[0, 1, 2],
        epsilon_init=1.0,
        epsilon_end=0.5,
        epsilon_anneal_frames=320,
    )
    batch = next(iter(exp.collector))
    drawn = batch.get(("agents", "action")).argmax(-1)
    assert not bool((drawn == ES).any())
    assert set(drawn.unique().tolist()) == {0, 1, 2}  # epsilon 1: uniform over the three
    exp.train()
    assert float(exp.exploration.eps) == pytest.approx(0.5, abs=1e-4)


@pytest.mark.parametrize("recipe", [MADDPG, ShapleyAC])
def test_gumbel_exploration_stays_the_default(tmp_path: Path, recipe: type) -> None:
    exp = _learner(tmp_path, recipe)
    assert exp.exploration is None  # the actor's Gumbel samples explore


def test_a_resumed_shapley_run_explores_where_it_stopped(tmp_path: Path) -> None:
    settings = {"exploration": "epsilon", "epsilon_end": 0.1, "epsilon_anneal_frames": 640}
    exp = _learner(tmp_path, ShapleyAC, checkpoint_interval=320, **settings)
    exp.train()
    eps = float(exp.exploration.eps)
    assert 0.1 < eps < 1.0  # half-way through the annealing
    exp.close()
    resumed = ShapleyAC.from_run_dir(tmp_path)
    assert float(resumed.exploration.eps) == pytest.approx(eps)
    resumed.close()


@pytest.mark.parametrize(
    ("changes", "field"),
    [
        ({"exploration": "boltzmann"}, "exploration"),
        ({"epsilon_init": 1.5}, "epsilon_init"),
        ({"epsilon_init": 0.1, "epsilon_end": 0.2}, "epsilon_end"),
        ({"epsilon_anneal_frames": 0}, "epsilon_anneal_frames"),
        ({"exploration_actions": [0, 0]}, "exploration_actions"),
        ({"exploration_actions": [-1]}, "exploration_actions"),
    ],
)
@pytest.mark.parametrize("config", [MADDPGConfig, ShapleyACConfig])
def test_bad_exploration_settings_are_refused(changes: dict, field: str, config: type) -> None:
    with pytest.raises(ConfigError, match=field):
        config(env="freeway-merge", **changes)


@pytest.mark.parametrize("recipe", [MADDPG, ShapleyAC])
def test_exploration_actions_beyond_the_action_space_are_refused(
    tmp_path: Path, recipe: type
) -> None:
    with pytest.raises(ValueError, match="exploration_actions"):
        _learner(tmp_path, recipe, exploration="epsilon", exploration_actions=[0, 4])


def test_epsilon_greedy_is_refused_for_continuous_actions(tmp_path: Path) -> None:
    config = MADDPGConfig(
        env="figure-eight",
        env_config={"n_cavs": 2, "n_hvs": 1, "horizon": 5},
        exploration="epsilon",
        progress=False,
        logger="none",
    )
    with pytest.raises(ValueError, match="exploration"):
        MADDPG(config, tmp_path)
