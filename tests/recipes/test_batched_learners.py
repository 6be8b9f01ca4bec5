"""The model-free recipes on the batched torch freeway (``env_config.backend="torch"``,
``num_envs`` roads in one env): each trains on ``[B, T]`` batches and writes its results, a bad
``num_envs`` / ``frames_per_batch`` pair is refused before any work, the update-to-data ratio
(``update_interval``, ``updates_per_batch``) is its own validated config, time-wise estimators
(GAE, TD(lambda), n-step) treat each road as its own sequence, and a resumed run equals an
uninterrupted one."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest
import torch
from PIL import Image
from tensordict import TensorDictBase

from mapets_rl.experiment import ConfigError
from mapets_rl.modules import TRANSITION_KEYS
from mapets_rl.objectives.n_step import n_step_transitions
from mapets_rl.recipes.coma import COMA, COMAConfig
from mapets_rl.recipes.maddpg import M3DDPG, MADDPG, OPENAI_MADDPG, M3DDPGConfig, MADDPGConfig
from mapets_rl.recipes.mapets import MAPETSConfig
from mapets_rl.recipes.mappo import MAPPO, MAPPOConfig
from mapets_rl.recipes.sac import SAC, SACConfig
from mapets_rl.recipes.shapley_ac import ShapleyAC, ShapleyACConfig

ROADS = 4
ENV_CONFIG = {"backend": "torch", "num_envs": ROADS, "n_vehicles": 6, "cav_ratio": 1.0}
COMMON: dict[str, Any] = {
    "env": "freeway-merge",
    "env_config": ENV_CONFIG,
    "frames_per_batch": 40,  # 10 steps of each of the 4 roads
    "total_frames": 80,
    "eval_interval": 0,
    "checkpoint_interval": 0,
    "eval_episodes": 1,
    "num_cells": [16],
    "progress": False,
    "logger": "none",
}
OFF_POLICY = {"batch_size": 16, "updates_per_batch": 2, "init_random_frames": 0}
RECIPES: dict[str, tuple[type, type, dict[str, Any]]] = {
    "maddpg": (MADDPG, MADDPGConfig, OFF_POLICY),
    "m3ddpg": (M3DDPG, M3DDPGConfig, OFF_POLICY),
    "sac": (SAC, SACConfig, OFF_POLICY),
    "shapley_ac": (ShapleyAC, ShapleyACConfig, {**OFF_POLICY, "critic_cells": [16]}),
    "mappo": (MAPPO, MAPPOConfig, {"minibatch_size": 20}),
    "coma": (COMA, COMAConfig, {"minibatch_size": 20, "critic_cells": [16]}),
}


def _params(exp) -> torch.Tensor:
    return torch.cat([p.detach().flatten().clone() for p in exp.loss.parameters()])


@pytest.mark.parametrize("recipe", sorted(RECIPES))
def test_recipe_trains_on_batched_roads_and_writes_results(recipe: str, tmp_path: Path) -> None:
    cls, config_cls, extra = RECIPES[recipe]
    exp = cls(config_cls(**COMMON, **extra), tmp_path)
    assert exp.env.batch_size == torch.Size([])  # evaluation steps one road
    shapes: list[torch.Size] = []
    losses: list[float] = []
    step = exp.train_step

    def recording(batch: TensorDictBase) -> dict[str, float]:
        shapes.append(batch.shape)
        out = step(batch)
        losses.extend(v for k, v in out.items() if k.startswith("loss"))
        return out

    exp.train_step = recording
    before = _params(exp)
    evaluations = exp.train()
    assert shapes == [torch.Size([ROADS, 10])] * 2  # two batches of [road, time]
    assert exp.frames == 80
    assert losses and all(torch.isfinite(torch.tensor(losses)))
    assert not torch.equal(before, _params(exp))
    results = json.loads((tmp_path / "results.json").read_text())
    assert [e["frames"] for e in results["evaluations"]] == [80]
    metrics = evaluations[-1]["metrics"]
    for name in ("reward", "return", "average_velocity", "average_comfort"):
        assert torch.isfinite(torch.tensor(metrics[name]))
    assert metrics["length"] >= 1


@pytest.mark.parametrize(
    "changes, field",
    [
        ({"frames_per_batch": 42}, "frames_per_batch"),  # not a multiple of the 4 roads
        ({"env_config": {**ENV_CONFIG, "num_envs": 0}}, "env_config.num_envs"),
        ({"env_config": {**ENV_CONFIG, "num_envs": 2.5}}, "env_config.num_envs"),
        ({"collector_workers": 2, "collector": "multi_sync"}, "collector_workers"),
    ],
)
def test_a_bad_batch_of_roads_is_refused_before_any_work(
    changes: dict[str, Any], field: str, tmp_path: Path
) -> None:
    with pytest.raises(ConfigError, match=field):
        MADDPG(MADDPGConfig(**{**COMMON, **OFF_POLICY, **changes}), tmp_path / "run")
    assert not (tmp_path / "run").exists()


def test_a_recipe_that_steps_one_road_refuses_num_envs() -> None:
    with pytest.raises(ConfigError, match="env_config.num_envs"):
        MAPETSConfig(env="freeway", env_config={"backend": "torch", "num_envs": 4})


# ------------------------------------------------------------------ the update-to-data ratio
def test_update_interval_is_validated_and_the_default_keeps_updates_per_batch() -> None:
    with pytest.raises(ConfigError, match="update_interval"):
        MADDPGConfig(update_interval=-1)
    config = MADDPGConfig(updates_per_batch=3)
    assert config.update_interval == 0
    assert config.gradient_steps(0, 200) == config.gradient_steps(200, 240) == 3
    every_100 = MADDPGConfig(update_interval=100, updates_per_batch=2)
    # two gradient steps per multiple of 100 passed, carried across batches of any size
    assert [every_100.gradient_steps(a, b) for a, b in [(0, 40), (40, 120), (120, 520)]] == [
        0,
        2,
        8,
    ]


def test_the_openai_maddpg_schedule_sets_its_fields() -> None:
    config = MADDPGConfig().with_overrides(OPENAI_MADDPG)
    assert (config.update_interval, config.updates_per_batch, config.batch_size) == (100, 1, 1024)
    assert (config.lr_actor, config.lr_critic, config.gamma, config.tau) == (1e-2, 1e-2, 0.95, 0.01)
    assert (config.num_cells, config.max_grad_norm) == ([64, 64], 0.5)


def _adam_steps(optim: torch.optim.Optimizer) -> int:
    states = list(optim.state.values())
    return int(states[0]["step"]) if states else 0


@pytest.mark.parametrize("frames_per_batch", [40, 80])
def test_gradient_steps_follow_the_frames_not_the_batches(
    frames_per_batch: int, tmp_path: Path
) -> None:
    changes = {"total_frames": 160, "frames_per_batch": frames_per_batch, "updates_per_batch": 1}
    config = MADDPGConfig(**{**COMMON, **OFF_POLICY, **changes}, update_interval=20)
    exp = MADDPG(config, tmp_path)
    exp.train()
    assert _adam_steps(exp.optim_critic) == 160 // 20  # one step per 20 frames, either way


def test_legacy_config_without_update_interval_reads_as_per_batch_updates() -> None:
    data = MADDPGConfig().to_dict()
    del data["update_interval"]
    assert MADDPGConfig.from_dict(MADDPGConfig.upgrade_dict(data)).update_interval == 0


@pytest.mark.parametrize("config_cls", [MADDPGConfig, ShapleyACConfig])
def test_legacy_config_without_initial_logits_or_shield_penalty_reads_as_before(
    config_cls: type,
) -> None:
    """A run saved before ``actor_initial_logits`` and ``shield_penalty`` existed resumes and
    evaluates with the random initialisation and the transition that ran."""
    data = config_cls(env="freeway-merge").to_dict()
    del data["actor_initial_logits"], data["shield_penalty"]
    config = config_cls.from_dict(config_cls.upgrade_dict(data))
    assert config.actor_initial_logits == [] and config.shield_penalty is None


# ----------------------------------------------------------------------- one sequence per road
def _batch(exp) -> TensorDictBase:
    batch = exp.collector.next()
    exp.collector.shutdown()
    return batch


def test_mappo_advantages_of_batched_roads_are_those_of_each_road(tmp_path: Path) -> None:
    exp = MAPPO(MAPPOConfig(**COMMON, minibatch_size=20), tmp_path)
    batch = _batch(exp)
    kwargs = dict(
        params=exp.loss.critic_network_params,
        target_params=exp.loss.target_critic_network_params,
    )
    with torch.no_grad():
        whole = exp.loss.value_estimator(batch.clone(), **kwargs)
        rows = torch.stack([exp.loss.value_estimator(r.clone(), **kwargs) for r in batch.unbind(0)])
    torch.testing.assert_close(whole["advantage"], rows["advantage"])
    torch.testing.assert_close(whole["value_target"], rows["value_target"])


def test_coma_targets_of_each_road_read_only_that_road(tmp_path: Path) -> None:
    exp = COMA(COMAConfig(**COMMON, minibatch_size=20, critic_cells=[16]), tmp_path)
    batch = _batch(exp)
    changed = batch.clone()
    changed["next", "agents", "reward"][0] += 100.0
    targets = []
    for data in (batch, changed):  # the same draws of the bootstrap's next actions
        torch.manual_seed(0)
        with torch.no_grad():
            targets.append(
                exp.loss.value_targets(data.clone()).get(exp.loss.tensor_keys.value_target)
            )
    whole, other = targets
    assert whole.shape[:2] == (ROADS, 10)
    torch.testing.assert_close(other[1:], whole[1:])
    assert not torch.allclose(other[0], whole[0])


def test_n_step_transitions_of_batched_roads_are_those_of_each_road(tmp_path: Path) -> None:
    exp = MADDPG(MADDPGConfig(**COMMON, **OFF_POLICY), tmp_path)
    batch = _batch(exp)
    whole = n_step_transitions(batch, 0.9, 3)
    rows = torch.stack([n_step_transitions(row, 0.9, 3) for row in batch.unbind(0)])
    assert (whole == rows).all()


# --------------------------------------------------------------------- resume and evaluation
@pytest.mark.parametrize("recipe", ["maddpg", "mappo", "shapley_ac"])
def test_resume_on_batched_roads_matches_the_uninterrupted_run(recipe: str, tmp_path: Path) -> None:
    cls, config_cls, extra = RECIPES[recipe]

    def config(total: int):
        changes = {"total_frames": total, "eval_interval": 80, "checkpoint_interval": 80}
        return config_cls(**{**COMMON, **extra, **changes})

    full = cls(config(160), tmp_path / "full")
    expected = full.train()
    cls(config(80), tmp_path / "part").train()
    resumed = cls.from_run_dir(tmp_path / "part", overrides=["total_frames=160"])
    assert resumed.train() == expected
    assert torch.equal(_params(resumed), _params(full))


def test_evaluation_video_of_the_torch_backend_plays_one_road_in_real_time(
    tmp_path: Path,
) -> None:
    import imageio.v2 as imageio

    env_config = {**ENV_CONFIG, "horizon": 3}
    exp = MAPPO(MAPPOConfig(**{**COMMON, "env_config": env_config}, minibatch_size=20), tmp_path)
    metrics = exp.evaluate(episodes=1, video=True)
    path = tmp_path / "videos" / "eval_000000000000.gif"
    frames = imageio.mimread(path)
    assert len(frames) == metrics["length"] == 3 and frames[0].ndim == 3
    with Image.open(path) as gif:  # the freeway's policy runs at 1 Hz
        assert gif.info["duration"] == 1000


@pytest.mark.parametrize("recipe", ["maddpg", "sac"])
def test_the_replay_buffer_keeps_only_what_the_loss_reads(recipe: str, tmp_path: Path) -> None:
    cls, config_cls, extra = RECIPES[recipe]
    exp = cls(config_cls(**COMMON, **extra), tmp_path)
    exp.train()
    sample = exp.buffer.sample()
    kept = set(sample.exclude("index").keys(include_nested=True, leaves_only=True))
    assert kept == set(TRANSITION_KEYS)


def test_maddpg_with_the_advantage_critic_head_trains_and_moves_only_its_own_advantage(
    tmp_path: Path,
) -> None:
    """``critic_head="advantage"``: the critic is V(o) + A(o_i, a_i) - A(o_i, Keep Lane), so an
    agent's Q at Keep Lane is its value, another agent's action changes nothing of it, and
    the run trains its parameters; an unknown head is refused."""
    exp = MADDPG(MADDPGConfig(**COMMON, **OFF_POLICY, critic_head="advantage"), tmp_path)
    td = exp.env.rollout(2)[0].select(*exp.critic.in_keys)
    keep = td.clone()
    keep["agents", "action"] = torch.nn.functional.one_hot(
        torch.zeros(keep["agents", "action"].shape[:-1], dtype=torch.long), 4
    ).to(keep["agents", "action"].dtype)
    out = exp.critic(keep.clone())
    torch.testing.assert_close(out["agents", "state_action_value"], out["agents", "state_value"])
    other = keep.clone()
    other["agents", "action"][1:] = torch.nn.functional.one_hot(torch.tensor(1), 4).to(
        other["agents", "action"].dtype
    )
    q = exp.critic(other)["agents", "state_action_value"]
    torch.testing.assert_close(q[0], out["agents", "state_action_value"][0])
    before = _params(exp)
    exp.train()
    assert not torch.equal(before, _params(exp))
    with pytest.raises(ConfigError, match="critic_head must be 'joint' or 'advantage'"):
        MADDPGConfig(env="freeway-merge", critic_head="dueling")


@pytest.mark.parametrize("recipe", ["maddpg", "shapley_ac"])
@pytest.mark.parametrize("share_params", [True, False])
def test_actor_initial_logits_start_the_greedy_actor_at_keep_lane(
    tmp_path: Path, recipe: str, share_params: bool
) -> None:
    """``actor_initial_logits=[3, 0, 0, 0]``: every agent's greedy action is Keep Lane (0) on
    every state of a rollout before any update (MADDPG's actor and the Shapley arm's, one
    network or one per agent, observations normalised as in the dilemma arms, the
    normaliser fitted to the states as after a run's first batch); without it the random
    actor chooses other actions too; a wrong length or a non-finite value is refused, and so
    is the coalition actor."""
    cls, config_cls, extra = RECIPES[recipe]
    extra = {**extra, "share_params": share_params, "exploration": "epsilon", "normalize_obs": True}
    if recipe == "shapley_ac":
        extra["actor_view"] = "own"  # the Shapley arm's actor: MADDPG's
    states = None
    chosen = {}
    for logits in ([], [3.0, 0.0, 0.0, 0.0]):
        config = config_cls(**COMMON, **extra, actor_initial_logits=logits)
        exp = cls(config, tmp_path / str(len(logits)))
        if states is None:
            states = exp.env.rollout(6).reshape(-1)
        exp.obs_norm.update(states["agents", "observation"], states["agents", "mask"])
        chosen[len(logits)] = exp.actor(states.clone())["agents", "action"].argmax(-1)
    assert (chosen[4] == 0).all()
    assert (chosen[0] != 0).any()
    with pytest.raises(ValueError, match="initial_logits must hold one value per action"):
        cls(config_cls(**COMMON, **extra, actor_initial_logits=[3.0, 0.0]), tmp_path / "short")
    with pytest.raises(ConfigError, match="actor_initial_logits"):
        config_cls(env="freeway-merge", actor_initial_logits=[float("nan"), 0, 0, 0])
    with pytest.raises(ConfigError, match="actor_initial_logits must be empty unless"):
        ShapleyACConfig(
            env="freeway-merge", actor_view="coalition", actor_initial_logits=[1, 0, 0, 0]
        )


@pytest.mark.parametrize("recipe", ["maddpg", "shapley_ac"])
def test_shield_penalty_stores_the_punished_proposal(tmp_path: Path, recipe: str) -> None:
    """``shield_penalty=p``: the replay buffer holds the proposed move and the reward minus
    ``p`` where the shield replaced a move (post-posed shielding with punishment), the
    transition that ran elsewhere; without the shield the field is refused before training."""
    cls, config_cls, extra = RECIPES[recipe]
    shielded = {**COMMON, "env_config": {**ENV_CONFIG, "n_vehicles": 30, "shield": True}}
    exp = cls(config_cls(**shielded, **extra, shield_penalty=10.0), tmp_path / "run")
    td = exp.env.reset()
    if recipe == "shapley_ac":
        td = exp.coalition(td)  # the replayed coalition, as the collection policy writes it
    moves = torch.full(td.get(("agents", "observation")).shape[:-1], 1)  # Change Left
    td.set(("agents", "action"), torch.nn.functional.one_hot(moves, 4).float())
    batch = exp.env.step(td)
    replaced = batch.get(("next", "agents", "info", "shielded")) > 0  # [roads, I]
    assert 0 < int(replaced.sum()) < replaced.numel()
    exp.frames = batch.numel()
    exp.train_step(batch)
    stored, batch = exp.buffer[:], batch.reshape(-1)  # [transitions]
    assert torch.equal(stored.get(("agents", "action")), batch.get(("agents", "proposed_action")))
    reward = batch.get(("next", "agents", "reward"))
    torch.testing.assert_close(
        stored.get(("next", "agents", "reward")),
        reward - 10.0 * replaced.reshape(reward.shape).float(),
    )
    with pytest.raises(ConfigError, match="shield_penalty=10.0 needs the shield's proposals"):
        cls(config_cls(**COMMON, **extra, shield_penalty=10.0), tmp_path / "plain")
    with pytest.raises(ConfigError, match="shield_penalty must be None or a number >= 0"):
        config_cls(env="freeway-merge", shield_penalty=-1.0)
