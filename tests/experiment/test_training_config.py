"""The model-free recipes declare their shared training fields once, under one set of names
(``mapets_rl.experiment.training``), and run directories written under the old names resume."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import pytest
import torch
import yaml
from tensordict import TensorDict

from mapets_rl.experiment import ConfigError
from mapets_rl.experiment.training import ModelFreeConfig, OffPolicyConfig, OnPolicyConfig
from mapets_rl.recipes.maddpg import MADDPGConfig
from mapets_rl.recipes.mappo import MAPPOConfig
from mapets_rl.recipes.sac import SAC, SACConfig
from mapets_rl.recipes.shapley_ac import ShapleyAC, ShapleyACConfig

OFF_POLICY = (MADDPGConfig, SACConfig, ShapleyACConfig)
SHARED_OFF_POLICY = (
    "gamma",
    "tau",
    "buffer_size",
    "batch_size",
    "updates_per_batch",
    "init_random_frames",
    "lr_actor",
    "lr_critic",
    "max_grad_norm",
    "num_cells",
    "share_params",
)
OLD_NAMES = (
    "actor_lr",
    "critic_lr",
    "warmup_frames",
    "gumbel_temperature",
    "actor_cells",
    "share_actor_params",
    "lr",
)
TINY = dict(logger="none", progress=False)


@pytest.mark.parametrize("cls", OFF_POLICY, ids=lambda c: c.__name__)
def test_off_policy_configs_share_one_set_of_names(cls) -> None:
    assert issubclass(cls, OffPolicyConfig)
    names = set(cls.field_names())
    assert set(SHARED_OFF_POLICY) <= names
    assert not names & set(OLD_NAMES)


def test_model_free_configs_share_the_common_names() -> None:
    assert issubclass(MAPPOConfig, OnPolicyConfig)
    common = {f.name for f in dataclasses.fields(ModelFreeConfig)}
    for cls in (*OFF_POLICY, MAPPOConfig):
        assert common <= set(cls.field_names()), cls.__name__
    # discrete MADDPG and Shapley AC call the Gumbel-softmax temperature the same
    assert "gumbel_tau" in MADDPGConfig.field_names()
    assert "gumbel_tau" in ShapleyACConfig.field_names()


@pytest.mark.parametrize("cls", OFF_POLICY, ids=lambda c: c.__name__)
@pytest.mark.parametrize(
    "field, value, message",
    [
        ("lr_actor", 0.0, "lr_actor must be > 0"),
        ("lr_critic", -1.0, "lr_critic must be > 0"),
        ("tau", 0.0, r"tau must be in \(0, 1\]"),
        ("init_random_frames", -1, "init_random_frames must be >= 0"),
        ("num_cells", [], "num_cells must be a non-empty list"),
        ("buffer_size", 2, "buffer_size must be >= batch_size"),
    ],
)
def test_shared_fields_are_validated_the_same_way(cls, field, value, message) -> None:
    with pytest.raises(ConfigError, match=message):
        cls(**{field: value})


def test_per_recipe_defaults_are_kept() -> None:
    shapley, sac, maddpg, mappo = ShapleyACConfig(), SACConfig(), MADDPGConfig(), MAPPOConfig()
    assert (shapley.share_params, shapley.batch_size, shapley.updates_per_batch) == (
        True,
        128,
        10,
    )
    assert (shapley.gamma, shapley.tau, shapley.lr_actor, shapley.lr_critic) == (
        0.95,
        0.01,
        1e-3,
        1e-3,
    )
    assert (sac.gamma, sac.tau, sac.lr_actor, sac.lr_critic, sac.lr_alpha) == (
        0.99,
        0.005,
        3e-4,
        3e-4,
        3e-4,
    )
    assert (maddpg.gamma, maddpg.tau, maddpg.share_params, maddpg.batch_size) == (
        0.95,
        0.01,
        True,
        256,
    )
    assert (mappo.gamma, mappo.lr, mappo.minibatch_size) == (0.99, 3e-4, 100)


def _shapley_config(**overrides) -> ShapleyACConfig:
    base = dict(
        total_frames=20,
        frames_per_batch=10,
        eval_interval=10,
        checkpoint_interval=10,
        init_random_frames=10,
        batch_size=8,
        updates_per_batch=2,
        num_cells=[16],
        critic_cells=[16],
        gumbel_tau=0.5,
        lr_actor=2e-3,
        share_params=False,
        env_config={"n_vehicles": 4, "cav_ratio": 0.5, "horizon": 5},
        **TINY,
    )
    base.update(overrides)
    return ShapleyACConfig(**base)


def test_a_shapley_run_saved_with_the_old_names_resumes(tmp_path: Path) -> None:
    run = tmp_path / "run"
    ShapleyAC(_shapley_config(), run).train()
    path = run / "config.yaml"
    data = yaml.safe_load(path.read_text())
    new_to_old = {new[0]: old for old, new in ShapleyACConfig.renamed_fields.items()}
    old_data = {new_to_old.get(key, key): value for key, value in data.items()}
    assert "actor_lr" in old_data and "lr_actor" not in old_data
    path.write_text(yaml.safe_dump(old_data, sort_keys=False))

    with pytest.warns(UserWarning, match="'warmup_frames'"):
        resumed = ShapleyAC.from_run_dir(run, overrides=["total_frames=30"])
    assert resumed.frames == 20
    cfg = resumed.config
    assert (cfg.lr_actor, cfg.num_cells, cfg.gumbel_tau, cfg.init_random_frames) == (
        2e-3,
        [16],
        0.5,
        10,
    )
    assert cfg.share_params is False
    rewritten = yaml.safe_load(path.read_text())
    assert "lr_actor" in rewritten and not set(rewritten) & set(ShapleyACConfig.renamed_fields)
    assert resumed.train()[-1]["frames"] == 30

    (tmp_path / "old.yaml").write_text(yaml.safe_dump({"actor_cells": [8], "critic_lr": 0.5}))
    with pytest.warns(UserWarning, match="'actor_cells'"):
        from_file = ShapleyACConfig.from_yaml(tmp_path / "old.yaml")
    assert from_file.num_cells == [8] and from_file.lr_critic == 0.5


def test_sac_old_lr_key_sets_every_learning_rate(tmp_path: Path) -> None:
    (tmp_path / "sac.yaml").write_text("lr: 0.002\n")
    with pytest.warns(UserWarning, match="'lr'"):
        cfg = SACConfig.from_yaml(tmp_path / "sac.yaml")
    assert cfg.lr_actor == cfg.lr_critic == cfg.lr_alpha == 0.002


def test_sac_loads_a_one_group_optimizer_state(tmp_path: Path) -> None:
    config = SACConfig(total_frames=20, frames_per_batch=10, **TINY)
    old = SAC(config, tmp_path / "old")
    # the optimiser as it was when SAC had one ``lr``: one group over loss.parameters()
    old.optim = torch.optim.Adam(old.loss.parameters(), lr=config.lr_actor)
    for i, param in enumerate(old.loss.parameters()):
        param.grad = torch.full_like(param, float(i + 1))
    old.optim.step()
    state = old.state_dict()

    new = SAC(config, tmp_path / "new")
    new.load_state_dict(state)
    assert len(new.optim.param_groups) == 3
    for p_old, p_new in zip(old.loss.parameters(), new.loss.parameters(), strict=True):
        assert torch.equal(p_old, p_new)
        assert torch.equal(old.optim.state[p_old]["exp_avg"], new.optim.state[p_new]["exp_avg"])


def test_the_latest_batch_buffer_holds_one_batch_and_counts_the_minibatch_steps() -> None:
    """``latest_batch_buffer`` + ``load_latest_batch``: the buffer holds exactly the last batch
    (the previous one dropped), minibatches of ``minibatch_size`` cover it without replacement,
    and the step count is ``epochs * max(numel // minibatch_size, 1)``."""
    config = MAPPOConfig(frames_per_batch=12, minibatch_size=4, epochs=3)
    buffer = config.latest_batch_buffer("cpu")
    old = TensorDict({"x": -torch.ones(2, 6)}, batch_size=[2, 6])
    assert config.load_latest_batch(buffer, old) == 3 * 3
    batch = TensorDict({"x": torch.arange(12.0).reshape(2, 6)}, batch_size=[2, 6])
    assert config.load_latest_batch(buffer, batch) == 3 * 3
    assert len(buffer) == 12
    seen = torch.cat([buffer.sample()["x"] for _ in range(3)])
    assert seen.shape == (12,)
    assert sorted(seen.tolist()) == list(range(12))
    small = TensorDict({"x": torch.zeros(3)}, batch_size=[3])
    assert config.load_latest_batch(buffer, small) == 3
    assert len(buffer) == 3
