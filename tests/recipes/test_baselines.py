"""MADDPG, MAPPO and SAC recipes: tiny training runs on both scenarios (parameters move, losses
finite, scenario metrics reported), variants, exact resume, config validation."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch
import yaml
from PIL import Image
from torchrl.modules import MultiAgentMLP

from mapets_rl.experiment import ConfigError
from mapets_rl.recipes.maddpg import MADDPG, MADDPGConfig
from mapets_rl.recipes.mappo import MAPPO, MAPPOConfig
from mapets_rl.recipes.sac import SAC, SACConfig

pytestmark = pytest.mark.usefixtures("toy_scenario")

SCENARIOS = {
    "figure-eight": ({"n_cavs": 3, "n_hvs": 2, "horizon": 40}, 120, ("agility", "safety")),
    "freeway": ({"n_vehicles": 4, "cav_ratio": 0.5}, 80, ("average_velocity", "average_comfort")),
}
RECIPES = {
    "mappo": (MAPPO, MAPPOConfig, {"minibatch_size": 20, "epochs": 2}),
    "maddpg": (
        MADDPG,
        MADDPGConfig,
        {"batch_size": 32, "updates_per_batch": 3, "init_random_frames": 40},
    ),
    "sac": (SAC, SACConfig, {"batch_size": 32, "updates_per_batch": 3, "init_random_frames": 40}),
}
COMMON = {
    "frames_per_batch": 40,
    "eval_interval": 0,
    "checkpoint_interval": 0,
    "progress": False,
    "logger": "none",
}


def _params(exp) -> torch.Tensor:
    return torch.cat([p.detach().flatten().clone() for p in exp.loss.parameters()])


def _train_recording_losses(exp) -> list[dict[str, float]]:
    logs: list[dict[str, float]] = []
    step = exp.train_step

    def recording(batch):
        out = step(batch)
        logs.append(out)
        return out

    exp.train_step = recording
    exp.train()
    return logs


@pytest.mark.parametrize("scenario", sorted(SCENARIOS))
@pytest.mark.parametrize("recipe", sorted(RECIPES))
def test_recipe_trains_on_scenario(recipe: str, scenario: str, tmp_path: Path) -> None:
    cls, config_cls, extra = RECIPES[recipe]
    env_config, frames, metrics = SCENARIOS[scenario]
    config = config_cls(env=scenario, env_config=env_config, total_frames=frames, **COMMON, **extra)
    exp = cls(config, tmp_path)
    before = _params(exp)
    logs = _train_recording_losses(exp)
    losses = [v for log in logs for k, v in log.items() if k.startswith("loss_")]
    assert losses and all(torch.isfinite(torch.tensor(losses)))
    assert not torch.equal(before, _params(exp))
    final = exp.results.evaluations[-1]
    assert final["frames"] == frames
    for name in (*metrics, "reward", "return"):
        assert torch.isfinite(torch.tensor(final["metrics"][name]))


@pytest.mark.parametrize(
    "cls, config",
    [
        (MAPPO, MAPPOConfig(ippo=True, share_params=False, minibatch_size=20)),
        (
            SAC,
            SACConfig(share_params=False, batch_size=16, updates_per_batch=2, init_random_frames=0),
        ),
        (MADDPG, MADDPGConfig(share_params=False, batch_size=16, updates_per_batch=2)),
    ],
)
def test_variants_on_toy_env(cls, config, tmp_path: Path) -> None:
    config = config.with_overrides(
        [
            "env=toy",
            "total_frames=80",
            "frames_per_batch=40",
            "progress=false",
            "logger=none",
            "eval_interval=0",
        ]
    )
    exp = cls(config, tmp_path)
    before = _params(exp)
    exp.train()
    assert not torch.equal(before, _params(exp))


@pytest.mark.parametrize("shared", [False, True])
def test_maddpg_critic_values_each_agent_unless_shared(shared: bool, tmp_path: Path) -> None:
    """One shared centralised critic reads the same joint input for every agent and so gives
    them all one Q (the mean of their returns); per-agent critics (the default) can give each
    agent its own return."""
    config = MADDPGConfig(env="toy", logger="none", progress=False, critic_share_params=shared)
    exp = MADDPG(config, tmp_path)
    td = exp.env.rollout(3)
    q = exp.critic(td.select(*exp.critic.in_keys))["agents", "state_action_value"]
    same = torch.allclose(q, q[..., :1, :].expand_as(q))
    assert same == shared


def test_maddpg_critic_view_own_reads_each_agents_own_observation_and_action(
    tmp_path: Path,
) -> None:
    """``critic_view="own"``: agent i's Q changes with its own action and not with another's;
    the default centralised critic reads every agent's; anything else is refused."""
    config = MADDPGConfig(env="toy", logger="none", progress=False, critic_view="own")
    exp = MADDPG(config, tmp_path)
    td = exp.env.rollout(2).select(*exp.critic.in_keys)[0]
    assert [m.centralized for m in exp.critic.modules() if isinstance(m, MultiAgentMLP)] == [False]
    q = exp.critic(td.clone())["agents", "state_action_value"]
    moved = td.clone()
    moved["agents", "action"][1] = moved["agents", "action"][1] + 0.5
    q_moved = exp.critic(moved)["agents", "state_action_value"]
    assert torch.equal(q[0], q_moved[0]) and not torch.equal(q[1], q_moved[1])
    central = MADDPG(MADDPGConfig(env="toy", logger="none", progress=False), tmp_path / "c")
    q = central.critic(td.clone())["agents", "state_action_value"]
    assert not torch.equal(q[0], central.critic(moved)["agents", "state_action_value"][0])
    with pytest.raises(ConfigError, match="critic_view must be 'all' or 'own', got 'mine'"):
        MADDPGConfig(env="toy", critic_view="mine")


def test_maddpg_advantage_critic_head_is_refused_on_continuous_actions(tmp_path: Path) -> None:
    config = MADDPGConfig(env="toy", logger="none", progress=False, critic_head="advantage")
    with pytest.raises(ValueError, match="critic_head='advantage' needs discrete actions"):
        MADDPG(config, tmp_path)


def test_a_maddpg_config_written_before_critic_share_params_keeps_its_shared_critic(
    tmp_path: Path,
) -> None:
    data = MADDPGConfig(env="toy").to_dict()
    assert data.pop("critic_share_params") is False  # today's default
    assert data.pop("critic_view") == "all"
    assert data.pop("critic_head") == "joint"
    path = tmp_path / "config.yaml"
    path.write_text(yaml.safe_dump(data))
    loaded = MADDPGConfig.from_yaml(path)
    assert loaded.critic_share_params is True and loaded.critic_view == "all"
    assert loaded.critic_head == "joint"


def test_ippo_value_is_decentralised(tmp_path: Path) -> None:
    def centralised(exp) -> list[bool]:
        return [m.centralized for m in exp.critic.modules() if isinstance(m, MultiAgentMLP)]

    cfg = dict(env="toy", logger="none", progress=False)
    assert centralised(MAPPO(MAPPOConfig(**cfg, ippo=True), tmp_path / "i")) == [False]
    assert centralised(MAPPO(MAPPOConfig(**cfg), tmp_path / "m")) == [True]


@pytest.mark.parametrize(
    "cls, config_cls, extra",
    [
        (
            MADDPG,
            MADDPGConfig,
            {
                "batch_size": 16,
                "updates_per_batch": 2,
                "init_random_frames": 30,
                "sigma_anneal_frames": 60,
            },
        ),
        (MAPPO, MAPPOConfig, {"minibatch_size": 10}),
    ],
)
def test_resume_matches_uninterrupted(cls, config_cls, extra, tmp_path: Path) -> None:
    def config(total: int):
        return config_cls(
            env="toy",
            total_frames=total,
            frames_per_batch=20,
            eval_interval=20,
            checkpoint_interval=40,
            progress=False,
            logger="none",
            **extra,
        )

    full = cls(config(100), tmp_path / "full")
    expected = full.train()
    cls(config(40), tmp_path / "part").train()
    resumed = cls.from_run_dir(tmp_path / "part", overrides=["total_frames=100"])
    assert resumed.train() == expected
    assert torch.equal(_params(resumed), _params(full))


@pytest.mark.parametrize(
    "config_cls, override, field",
    [
        (MAPPOConfig, "minibatch_size=1000", "minibatch_size"),
        (MAPPOConfig, "lmbda=1.5", "lmbda"),
        (MADDPGConfig, "tau=0", "tau"),
        (MADDPGConfig, "sigma_end=0.9", "sigma_end"),
        (SACConfig, "buffer_size=2", "buffer_size"),
        (SACConfig, "num_cells=[]", "num_cells"),
    ],
)
def test_config_validation(config_cls, override: str, field: str) -> None:
    with pytest.raises(ConfigError, match=field):
        config_cls().with_overrides([override])


def test_evaluation_video_is_a_gif(tmp_path: Path) -> None:
    import imageio.v2 as imageio

    config = MAPPOConfig(
        env="figure-eight",
        env_config={"n_cavs": 2, "n_hvs": 1, "horizon": 5},
        progress=False,
        logger="none",
    )
    exp = MAPPO(config, tmp_path)
    metrics = exp.evaluate(episodes=1, video=True)
    path = tmp_path / "videos" / "eval_000000000000.gif"
    frames = imageio.mimread(path)
    assert len(frames) == metrics["length"] == 5 and frames[0].ndim == 3
    with Image.open(path) as gif:  # real time: 0.1 s steps on the figure-eight
        assert gif.info["duration"] == 100
