"""Shapley actor-critic recipe: tiny freeway runs end to end, checkpoint and exact resume."""

from pathlib import Path

import pytest
import torch
import yaml

from mapets_rl.experiment import ConfigError, list_checkpoints
from mapets_rl.recipes.shapley_ac import ShapleyAC, ShapleyACConfig


def _config(**overrides):
    base = dict(
        total_frames=30,
        frames_per_batch=10,
        eval_interval=15,
        checkpoint_interval=15,
        eval_episodes=1,
        init_random_frames=10,
        batch_size=8,
        updates_per_batch=2,
        num_cells=[16],
        critic_cells=[32, 32],
        logger="none",
        progress=False,
        env_config={"n_vehicles": 4, "cav_ratio": 0.5, "horizon": 5},
    )
    base.update(overrides)
    return ShapleyACConfig(**base)


def _actor_params(exp):
    return torch.cat([p.detach().flatten() for p in exp.actor.parameters()])


def test_train_checkpoint_and_resume(tmp_path: Path) -> None:
    full = ShapleyAC(_config(), tmp_path / "full")
    p0 = _actor_params(full)
    full_evals = full.train()
    assert not torch.equal(p0, _actor_params(full))  # the actors learned something
    assert [e["frames"] for e in full_evals] == [20, 30]  # crossings of 15 and the end
    metrics = full_evals[-1]["metrics"]
    assert {"system_return", "average_velocity", "average_comfort"} <= set(metrics)
    assert len(list_checkpoints(tmp_path / "full")) == 2
    sample = full.buffer.sample()
    assert sample["agents", "coalition"].dtype == torch.bool  # (s, a, C, r, s') replayed

    part = ShapleyAC(_config(total_frames=20), tmp_path / "part")
    part.train()
    resumed = ShapleyAC.from_run_dir(tmp_path / "part", overrides=["total_frames=30"])
    assert resumed.frames == 20
    assert resumed.train() == full_evals
    assert torch.equal(_actor_params(resumed), _actor_params(full))


def test_config_validation() -> None:
    with pytest.raises(ConfigError, match="join_prob"):
        _config(join_prob=1.5)
    with pytest.raises(ConfigError, match="num_permutations"):
        _config(num_permutations=3)
    with pytest.raises(ConfigError, match="eval_coalition"):
        _config(eval_coalition="half")
    with pytest.raises(ConfigError, match="coalition_sizes"):
        _config(coalition_sizes="poisson")
    with pytest.raises(ConfigError, match="critic_embed_cells"):
        _config(critic_embed_cells=[16, 0])


def test_a_per_agent_critic_embedding_reaches_the_critic_and_trains(tmp_path: Path) -> None:
    exp = ShapleyAC(_config(critic_embed_cells=[8]), tmp_path)
    weights = exp.critic.embed_weights
    assert [tuple(w.shape) for w in weights] == [(2, exp.critic.observation_dim + 4, 8)]
    before = weights[0].detach().clone()
    exp.train()
    assert not torch.equal(before, exp.loss.critic_network_params.get(("embed_weights", "0")))
    exp.close()


def test_member_heads_reach_the_critic_and_train(tmp_path: Path) -> None:
    exp = ShapleyAC(_config(critic_member_heads=True), tmp_path)
    assert exp.critic.member_heads and exp.loss.critic_network.member_heads
    mlp = exp.critic.head[1]
    assert mlp[-1].out_features == exp.critic.n_agents == 2  # one output per CAV
    before = mlp[-1].weight.detach().clone()
    exp.train()
    trained = exp.loss.critic_network_params.get(("head", "1", str(len(mlp) - 1), "weight"))
    assert trained.shape == before.shape and not torch.equal(before, trained)
    exp.close()


def test_uniform_coalition_sizes_reach_the_sampler(tmp_path: Path) -> None:
    exp = ShapleyAC(_config(coalition_sizes="uniform"), tmp_path)
    assert exp.coalition.sizes == "uniform"
    exp.close()


def test_config_written_before_ego_first_views_keeps_index_order(tmp_path: Path) -> None:
    cfg = _config()
    assert cfg.ego_first and cfg.share_params  # today's defaults
    data = cfg.to_dict()
    del data["ego_first"]
    path = tmp_path / "config.yaml"
    path.write_text(yaml.safe_dump(data))
    old = ShapleyACConfig.from_yaml(path)
    assert old.ego_first is False and old.share_params is True


def test_a_run_made_before_the_critic_embedding_resumes_without_it(tmp_path: Path) -> None:
    ShapleyAC(_config(total_frames=10), tmp_path).train()
    path = tmp_path / "config.yaml"
    data = yaml.safe_load(path.read_text())
    del data["critic_embed_cells"], data["critic_member_heads"]
    path.write_text(yaml.safe_dump(data))
    resumed = ShapleyAC.from_run_dir(tmp_path)
    assert resumed.config.critic_embed_cells == [] and len(resumed.critic.embed_weights) == 0
    assert resumed.config.critic_member_heads is False and not resumed.critic.member_heads
    resumed.close()
