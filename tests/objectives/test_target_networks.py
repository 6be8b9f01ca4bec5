"""What made MADDPG saturate at top speed: target networks normalising with stale statistics
(the critic diverged) and an actor pre-activation that grows without bound (tanh saturates, its
gradient vanishes). Both fixes are checked here on constructed problems."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModule, TensorDictSequential
from torch import nn
from torchrl.objectives import DDPGLoss, SoftUpdate

from mapets_rl.modules import RunningObsNorm, sync_target_statistics
from mapets_rl.objectives.ddpg import PreactivationRegularisedDDPGLoss
from mapets_rl.objectives.n_step import STEPS_TO_NEXT_OBS, n_step_transitions


def _networks(obs_dim: int = 3, norm: RunningObsNorm | None = None):
    """A tanh actor o -> a in [-1, 1] writing its pre-activation, and a critic Q(o, a) = a."""
    front = [] if norm is None else [TensorDictModule(norm, in_keys=["obs"], out_keys=["obs_n"])]
    key = "obs" if norm is None else "obs_n"
    actor = TensorDictSequential(
        *front,
        TensorDictModule(nn.Linear(obs_dim, 1), in_keys=[key], out_keys=["param"]),
        TensorDictModule(torch.tanh, in_keys=["param"], out_keys=["action"]),
    )
    critic = TensorDictSequential(
        *front,
        TensorDictModule(SlopeCritic(), in_keys=[key, "action"], out_keys=["state_action_value"]),
    )
    return actor, critic


class SlopeCritic(nn.Module):
    """``Q(o, a) = w a`` [..., 1] with ``w = 1`` initially: ``dQ/da = 1`` everywhere."""

    def __init__(self) -> None:
        super().__init__()
        self.w = nn.Parameter(torch.ones(()))

    def forward(self, obs: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        return self.w * action


def _batch(n: int = 64, obs_dim: int = 3) -> TensorDict:
    obs = torch.randn(n, obs_dim) * 10 + 40
    return TensorDict(
        {
            "obs": obs,
            "action": torch.rand(n, 1) * 2 - 1,
            "next": {
                "obs": obs + 1,
                "reward": torch.ones(n, 1),
                "done": torch.zeros(n, 1, dtype=torch.bool),
                "terminated": torch.zeros(n, 1, dtype=torch.bool),
            },
        },
        batch_size=[n],
    )


def test_targets_normalise_with_the_online_statistics() -> None:
    norm = RunningObsNorm(3)
    actor, critic = _networks(norm=norm)
    loss = DDPGLoss(actor, critic, delay_actor=True, delay_value=True)
    updater = SoftUpdate(loss, tau=0.01)
    norm.update(torch.randn(500, 3) * 10 + 40)

    targets = (loss.target_actor_network_params, loss.target_value_network_params)
    key = ("module", "0", "module")

    # without the sync a soft update moves the target copies only 1% of the way
    updater.step()
    for params in targets:
        assert (params.get((*key, "mean")) - norm.mean).abs().min() > 30
    assert sync_target_statistics(loss, norm) == 2 * 3  # mean, var, count in each target copy
    for params in targets:
        torch.testing.assert_close(params.get((*key, "mean")), norm.mean)
        torch.testing.assert_close(params.get((*key, "var")), norm.var)
    # equal copies stay equal under soft updates
    updater.step()
    for params in targets:
        torch.testing.assert_close(params.get((*key, "mean")), norm.mean)


def test_sync_without_target_copies_writes_nothing() -> None:
    norm = RunningObsNorm(3)
    actor, critic = _networks(norm=norm)
    loss = DDPGLoss(actor, critic, delay_actor=False, delay_value=False)
    assert sync_target_statistics(loss, norm) == 0


def test_preactivation_penalty_is_its_closed_form() -> None:
    actor, critic = _networks()
    loss = PreactivationRegularisedDDPGLoss(
        actor, critic, preactivation_key="param", preactivation_coef=0.5
    )
    batch = _batch()
    out = loss(batch)
    param = actor(batch.select("obs").clone()).get("param")
    torch.testing.assert_close(out["loss_actor_reg"], 0.5 * param.pow(2).mean())
    torch.testing.assert_close(
        loss.total(out), out["loss_actor"] + out["loss_actor_reg"] + out["loss_value"]
    )


@pytest.mark.parametrize("coef, bounded", [(0.0, False), (1e-2, True)])
def test_penalty_keeps_the_actor_out_of_tanh_saturation(coef: float, bounded: bool) -> None:
    """Under a critic with ``dQ/da = 1`` everywhere the deterministic policy gradient pushes
    the pre-activation up forever; the penalty stops it where ``1 - tanh(p)^2 = 2 coef p``."""
    torch.manual_seed(0)
    actor, critic = _networks()
    loss = PreactivationRegularisedDDPGLoss(
        actor, critic, preactivation_key="param", preactivation_coef=coef
    )
    optim = torch.optim.Adam(loss.actor_network_params.values(True, True), lr=0.05)
    batch = _batch()
    batch["obs"] = torch.randn(64, 3)
    for _ in range(600):
        out = loss(batch)
        optim.zero_grad()
        (out["loss_actor"] + out["loss_actor_reg"]).backward()
        optim.step()
    param = actor(batch.select("obs").clone()).get("param")
    if bounded:  # -tanh(p) + coef p^2 is stationary at p ~ 2.2 for coef = 0.01
        assert param.abs().max() < 2.6
    else:
        assert param.mean() > 3.2  # still growing, ever slower as tanh saturates


def test_maddpg_writes_the_preactivation(tmp_path: Path) -> None:
    from mapets_rl.recipes.maddpg import MADDPG, MADDPGConfig

    config = MADDPGConfig(
        env="freeway",
        env_config={"n_vehicles": 4, "cav_ratio": 0.5},
        frames_per_batch=10,
        total_frames=10,
        batch_size=8,
        updates_per_batch=1,
        init_random_frames=0,
        progress=False,
    )
    exp = MADDPG(config, tmp_path / "run")
    td = exp.env.reset()
    exp.eval_policy(td)
    logits, action = td.get(("agents", "param")), td.get(("agents", "action"))
    assert logits.shape == action.shape
    torch.testing.assert_close(action.argmax(-1), logits.argmax(-1))


def _episode_batch() -> TensorDict:
    """6 steps of 2 agents, reward ``2t + i``; agent 1 crashes at step 2; an episode ends
    after step 3."""
    steps, agents = 6, 2
    reward = torch.arange(steps * agents, dtype=torch.float).reshape(steps, agents, 1)
    crashed = torch.zeros(steps, agents, 1, dtype=torch.bool)
    crashed[2:, 1] = True
    episode_end = torch.zeros(steps, 1, dtype=torch.bool)
    episode_end[3] = True
    obs = torch.arange(steps * agents, dtype=torch.float).reshape(steps, agents, 1)
    return TensorDict(
        {
            "agents": {"observation": obs},
            "next": {
                "agents": {
                    "observation": obs + 100,
                    "reward": reward,
                    "done": crashed.clone(),
                    "terminated": crashed.clone(),
                },
                "done": episode_end,
            },
        },
        batch_size=[steps],
    )


def test_n_step_returns_stop_at_crashes_episode_ends_and_the_batch_end() -> None:
    out = n_step_transitions(_episode_batch(), gamma=0.5, n_steps=3)
    expected = torch.tensor(
        [
            [0 + 0.5 * 2 + 0.25 * 4, 1 + 0.5 * 3 + 0.25 * 5],  # agent 1 stops at its crash
            [2 + 0.5 * 4 + 0.25 * 6, 3 + 0.5 * 5],
            [4 + 0.5 * 6, 5],  # the episode ends after step 3
            [6, 7],
            [8 + 0.5 * 10, 9],  # the batch ends after step 5
            [10, 11],
        ]
    )
    torch.testing.assert_close(out["next", "agents", "reward"].squeeze(-1), expected)
    steps = out[STEPS_TO_NEXT_OBS].squeeze(-1)
    torch.testing.assert_close(steps[:, 0], torch.tensor([3.0, 3, 2, 1, 2, 1]))
    torch.testing.assert_close(steps[:3, 1], torch.tensor([3.0, 2, 1]))
    # the joint next observation is that of the last included step (common to the agents)
    next_obs = out["next", "agents", "observation"][:, 0, 0]
    torch.testing.assert_close(next_obs, torch.tensor([104.0, 106, 106, 106, 110, 110]))
    assert out["next", "agents", "terminated"][:, 1].all()
    assert not out["next", "agents", "terminated"][:, 0].any()
    # observations and actions stay those of row t
    torch.testing.assert_close(
        out["agents", "observation"], _episode_batch()["agents", "observation"]
    )


def test_one_step_is_the_identity() -> None:
    batch = _episode_batch()
    out = n_step_transitions(batch, gamma=0.9, n_steps=1)
    torch.testing.assert_close(out["next", "agents", "reward"], batch["next", "agents", "reward"])
    assert (out[STEPS_TO_NEXT_OBS] == 1).all()


def test_td0_bootstrap_is_discounted_by_the_steps_taken() -> None:
    """torchrl's TD(0) estimator discounts by ``gamma ** steps_to_next_obs``."""
    actor, critic = _networks(obs_dim=1)
    loss = DDPGLoss(actor, critic, delay_actor=False, delay_value=False)
    loss.make_value_estimator(gamma=0.5)
    loss.value_estimator.set_keys(
        reward=("agents", "reward"),
        done=("agents", "done"),
        terminated=("agents", "terminated"),
        steps_to_next_obs=STEPS_TO_NEXT_OBS,
    )
    batch = n_step_transitions(_episode_batch(), gamma=0.5, n_steps=3)
    batch = batch.rename_key_(("agents", "observation"), "obs")
    batch["next"].rename_key_(("agents", "observation"), "obs")
    with torch.no_grad():
        q_next = critic(actor(batch["next"].clone()))["state_action_value"]
        target = loss.value_estimator.value_estimate(batch.clone())
    reward = batch["next", "agents", "reward"]
    alive = ~batch["next", "agents", "terminated"]
    expected = reward + alive * 0.5 ** batch[STEPS_TO_NEXT_OBS] * q_next
    torch.testing.assert_close(target, expected)
