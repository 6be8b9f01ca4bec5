"""M3DDPG (Li et al. 2019): the one-step adversarial perturbation on critics whose gradients are
known in closed form, the minimax target and actor loss against MADDPG's, epsilon = 0 being
MADDPG exactly, the recipe on the freeway's discrete actions (train, checkpoint, resume), and
config validation."""

from __future__ import annotations

import copy
import json
from pathlib import Path

import pytest
import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModule, TensorDictSequential
from torch import nn
from torchrl.objectives import ValueEstimators

from mapets_rl.experiment import ConfigError
from mapets_rl.experiment.checkpoint import list_checkpoints
from mapets_rl.experiment.results import RESULTS_FILE
from mapets_rl.modules import AgentGroupSpec
from mapets_rl.objectives import (
    M3DDPGLoss,
    MinimaxCritic,
    PreactivationRegularisedDDPGLoss,
    minimax_action_perturbation,
)
from mapets_rl.recipes.maddpg import M3DDPG, M3DDPGConfig

B, N, OBS_DIM, D = 6, 3, 4, 2
OBS, ACTION, Q = ("agents", "observation"), ("agents", "action"), ("agents", "q")
PARAM = ("agents", "param")
LOSS_KEYS = {
    "reward": ("agents", "reward"),
    "done": ("agents", "done"),
    "terminated": ("agents", "terminated"),
}
GAMMA = 0.9


class LinearQ(nn.Module):
    """``Q_i(o, a) = sum_j w_ij . a_j + sum(o_i)``: ``grad_{a_j} Q_i = w_ij``. [*, N, 1]"""

    def __init__(self, w: torch.Tensor) -> None:
        super().__init__()
        self.w = nn.Parameter(w.clone())  # [N, N, D]

    def forward(self, obs: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        q = torch.einsum("ijd,...jd->...i", self.w, action) + obs.sum(-1)
        return q.unsqueeze(-1)


def _linear_critic(w: torch.Tensor) -> TensorDictModule:
    return TensorDictModule(LinearQ(w), in_keys=[OBS, ACTION], out_keys=[Q])


class _Critic(nn.Module):
    """A non-linear centralised critic ``[*, N, obs], [*, N, act] -> [*, N, 1]`` (a head per
    agent)."""

    def __init__(self) -> None:
        super().__init__()
        self.net = nn.Sequential(
            nn.Flatten(-2), nn.Linear(N * (OBS_DIM + D), 16), nn.Tanh(), nn.Linear(16, N)
        )

    def forward(self, obs: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        return self.net(torch.cat([obs, action], -1)).unsqueeze(-1)


def _actor() -> TensorDictSequential:
    """Linear actors writing a pre-activation and its tanh."""
    return TensorDictSequential(
        TensorDictModule(nn.Linear(OBS_DIM, D), in_keys=[OBS], out_keys=[PARAM]),
        TensorDictModule(torch.tanh, in_keys=[PARAM], out_keys=[ACTION]),
    )


def _batch() -> TensorDict:
    terminated = torch.zeros(B, N, 1, dtype=torch.bool)
    terminated[0, 1] = True
    agents = {"observation": torch.randn(B, N, OBS_DIM), "action": torch.rand(B, N, D) * 2 - 1}
    nxt = {
        "observation": torch.randn(B, N, OBS_DIM),
        "reward": torch.randn(B, N, 1),
        "done": terminated.clone(),
        "terminated": terminated,
    }
    return TensorDict(
        {"agents": TensorDict(agents, [B, N]), "next": {"agents": TensorDict(nxt, [B, N])}}, [B]
    )


def _losses(actor, critic, eps_critic: float, eps_actor: float):
    """MADDPG's loss and M3DDPG's on copies of the same actor and critic."""
    common = dict(preactivation_key=PARAM, delay_actor=True, delay_value=True)
    maddpg = PreactivationRegularisedDDPGLoss(copy.deepcopy(actor), copy.deepcopy(critic), **common)
    maddpg.set_keys(**LOSS_KEYS, state_action_value=Q)
    m3ddpg = M3DDPGLoss(
        copy.deepcopy(actor),
        copy.deepcopy(critic),
        action_key=ACTION,
        value_key=Q,
        epsilon_critic=eps_critic,
        epsilon_actor=eps_actor,
        **common,
    )
    m3ddpg.set_keys(**LOSS_KEYS)
    for loss in (maddpg, m3ddpg):
        loss.make_value_estimator(ValueEstimators.TD0, gamma=GAMMA)
    return maddpg, m3ddpg


# ----------------------------------------------------------------------- the perturbation
def test_perturbation_is_the_normalised_descent_direction_of_each_agents_critic() -> None:
    """Quadratic ``Q_i(a) = -sum_j ||a_j - c_ij||^2``: ``grad_{a_j} Q_i = 2 (c_ij - a_j)``, so
    ``delta_ij = -eps (c_ij - a_j) / ||c_ij - a_j||`` (j != i), and ``Q_i`` decreases."""
    torch.manual_seed(0)
    c = torch.randn(N, N, D)
    actions = torch.randn(B, N, D)

    def q_own(joint: torch.Tensor) -> torch.Tensor:  # [*, N, N, D] -> [*, N]
        return -(joint - c).pow(2).sum((-1, -2))

    eps = 1e-2
    delta = minimax_action_perturbation(q_own, actions, eps)
    assert delta.shape == (B, N, N, D) and not delta.requires_grad
    toward = c - actions.unsqueeze(-3)  # [B, N, N, D]
    expected = -eps * toward / toward.norm(dim=-1, keepdim=True)
    expected = expected * (1 - torch.eye(N)).unsqueeze(-1)
    torch.testing.assert_close(delta, expected)
    replicas = actions.unsqueeze(-3).expand(B, N, N, D)
    assert (q_own(replicas + delta) < q_own(replicas)).all()
    # a larger step descends further along the (locally) linear slope
    assert (q_own(replicas + 2 * delta) < q_own(replicas + delta)).all()


def test_own_action_is_not_perturbed() -> None:
    torch.manual_seed(1)
    w = torch.randn(N, N, D)
    td = _batch()
    critic = MinimaxCritic(_linear_critic(w), action_key=ACTION, value_key=Q)
    delta = minimax_action_perturbation(
        lambda joint: torch.einsum("ijd,...ijd->...i", w, joint), td.get(ACTION), 0.5
    )
    assert torch.equal(delta.diagonal(dim1=-3, dim2=-2), torch.zeros(B, D, N))
    assert (delta.norm(dim=-1) > 0).sum() == B * N * (N - 1)
    # a critic of the own action only (w_ij = 0 for j != i) is unchanged by the perturbation
    own_only = MinimaxCritic(
        _linear_critic(w * torch.eye(N).unsqueeze(-1)), action_key=ACTION, value_key=Q
    )
    plain = own_only(td.clone()).get(Q)
    with own_only.perturbing(0.5):
        torch.testing.assert_close(own_only(td.clone()).get(Q), plain)
    with critic.perturbing(0.5):
        assert not torch.allclose(critic(td.clone()).get(Q), plain)


def test_minimax_critic_lowers_a_linear_q_by_eps_times_the_other_gradients_norms() -> None:
    torch.manual_seed(2)
    w = torch.randn(N, N, D)
    td = _batch()
    critic = MinimaxCritic(_linear_critic(w), action_key=ACTION, value_key=Q)
    plain = critic(td.clone()).get(Q)
    with critic.perturbing(0.3):
        perturbed = critic(td.clone()).get(Q)
    others = (w.norm(dim=-1) * (1 - torch.eye(N))).sum(-1)  # [N]: sum_{j != i} ||w_ij||
    torch.testing.assert_close(perturbed, plain - 0.3 * others.unsqueeze(-1))
    assert critic(td.clone()).get(Q).equal(plain)  # back to the plain critic outside the block


# ----------------------------------------------------------------------- the loss
def test_target_and_actor_loss_are_the_minimax_ones_on_a_linear_critic() -> None:
    """``y_i = r_i + gamma (1 - d_i) (Q'_i(x', a') - eps_c sum_{j != i} ||w_ij||)`` and
    ``loss_actor = -mean Q_i(x, mu(o)) + eps_a mean_i sum_{j != i} ||w_ij||``."""
    torch.manual_seed(3)
    w = torch.randn(N, N, D)
    maddpg, m3ddpg = _losses(_actor(), _linear_critic(w), eps_critic=0.2, eps_actor=0.05)
    td = _batch()
    ref, out = maddpg(td.clone()), m3ddpg(td.clone())
    others = (w.norm(dim=-1) * (1 - torch.eye(N))).sum(-1)  # [N]
    alive = (~td.get(("next", "agents", "terminated"))).float().squeeze(-1)  # [B, N]
    torch.testing.assert_close(
        out["target_value"], ref["target_value"] - GAMMA * alive * 0.2 * others
    )
    torch.testing.assert_close(out["pred_value"], ref["pred_value"])
    torch.testing.assert_close(
        out["loss_value"], (out["pred_value"] - out["target_value"]).pow(2).mean()
    )
    torch.testing.assert_close(out["loss_actor"], ref["loss_actor"] + 0.05 * others.mean())
    torch.testing.assert_close(out["loss_actor_reg"], ref["loss_actor_reg"])
    # the perturbation is a constant: the actor's gradient on a linear critic is MADDPG's
    grads = []
    for loss, res in ((maddpg, ref), (m3ddpg, out)):
        loss.zero_grad()
        res["loss_actor"].backward()
        grads.append([p.grad.clone() for p in loss.actor_network_params.values(True, True)])
    for g_ref, g in zip(*grads, strict=True):
        torch.testing.assert_close(g, g_ref)


def test_target_matches_a_hand_computed_minimax_target_on_a_nonlinear_critic() -> None:
    torch.manual_seed(4)
    _, m3ddpg = _losses(_actor(), TensorDictModule(_Critic(), [OBS, ACTION], [Q]), 0.1, 0.0)
    td = _batch()
    out = m3ddpg(td.clone())
    # by hand: target actor at o', its actions perturbed on the target critic, TD(0)
    critic = copy.deepcopy(m3ddpg.value_network.critic.module)  # _Critic
    target = m3ddpg.target_value_network_params["critic", "module"]
    actor = copy.deepcopy(m3ddpg.actor_network.module[0].module)  # nn.Linear
    actor_target = m3ddpg.target_actor_network_params["module", "0", "module"]
    nxt = td["next", "agents"]
    with actor_target.to_module(actor), target.to_module(critic):
        obs = nxt["observation"]
        a = torch.tanh(actor(obs))  # [B, N, D]
        obs_rep = obs.unsqueeze(-3).expand(B, N, N, OBS_DIM)

        def q_own(joint: torch.Tensor) -> torch.Tensor:
            return critic(obs_rep, joint).squeeze(-1).diagonal(dim1=-2, dim2=-1)

        delta = minimax_action_perturbation(q_own, a, 0.1)
        q_next = q_own(a.unsqueeze(-3) + delta)  # [B, N]
    alive = (~nxt["terminated"]).float().squeeze(-1)
    expected = nxt["reward"].squeeze(-1) + GAMMA * alive * q_next
    torch.testing.assert_close(out["target_value"], expected)


def test_epsilon_zero_is_maddpg_exactly() -> None:
    torch.manual_seed(5)
    critic = TensorDictModule(_Critic(), [OBS, ACTION], [Q])
    td = _batch()
    for eps in (0.0, 0.1):
        maddpg, m3ddpg = _losses(_actor(), critic, eps, eps)
        ref, out = maddpg(td.clone()), m3ddpg(td.clone())
        same = all(
            torch.equal(out[k], ref[k])
            for k in ("loss_actor", "loss_actor_reg", "loss_value", "target_value")
        )
        assert same == (eps == 0)


# ----------------------------------------------------------------------- the recipe
TINY = {
    "env": "freeway",
    "env_config": {"n_vehicles": 4, "cav_ratio": 0.5},
    "frames_per_batch": 40,
    "batch_size": 32,
    "updates_per_batch": 2,
    "init_random_frames": 40,
    "epsilon_critic": 0.1,
    "epsilon_actor": 0.05,
    "eval_interval": 160,
    "checkpoint_interval": 160,
    "eval_episodes": 1,
    "progress": False,
    "logger": "none",
}


def test_recipe_trains_on_the_freeway_checkpoints_and_resumes(tmp_path: Path) -> None:
    run = tmp_path / "run"
    exp = M3DDPG(M3DDPGConfig(**TINY, total_frames=160), run)
    assert isinstance(exp.loss, M3DDPGLoss) and exp.loss.epsilon_critic == 0.1
    assert AgentGroupSpec.from_env(exp.env).discrete  # one-hot actions, Gumbel-softmax head
    before = [p.detach().clone() for p in exp.loss.parameters()]
    exp.train()
    assert any(not torch.equal(b, p) for b, p in zip(before, exp.loss.parameters(), strict=True))
    assert [c.name for c in list_checkpoints(run)] == [f"ckpt_{160:012d}.pt"]
    results = json.loads((run / RESULTS_FILE).read_text())
    assert results
    resumed = M3DDPG.from_run_dir(run, overrides=["total_frames=320"])
    assert resumed.frames == 160
    evaluations = resumed.train()
    assert [e["frames"] for e in evaluations] == [160, 320]
    assert all(torch.isfinite(p).all() for p in resumed.loss.parameters())
    # the resumed run is the uninterrupted one
    full = M3DDPG(M3DDPGConfig(**TINY, total_frames=320), tmp_path / "full")
    assert full.train() == evaluations
    for p_full, p_resumed in zip(full.loss.parameters(), resumed.loss.parameters(), strict=True):
        assert torch.equal(p_full, p_resumed)
    assert [c.name for c in list_checkpoints(run)][-1] == f"ckpt_{320:012d}.pt"


def test_recipe_trains_on_the_figure_eights_continuous_actions(tmp_path: Path) -> None:
    config = M3DDPGConfig(
        **{**TINY, "env": "figure-eight", "env_config": {"n_cavs": 3, "n_hvs": 2, "horizon": 40}},
        total_frames=80,
    )
    exp = M3DDPG(config, tmp_path / "run")
    assert not AgentGroupSpec.from_env(exp.env).discrete
    before = [p.detach().clone() for p in exp.loss.parameters()]
    logs = []
    step = exp.train_step
    exp.train_step = lambda batch: logs.append(step(batch)) or logs[-1]
    exp.train()
    losses = [v for log in logs for k, v in log.items() if k.startswith("loss_")]
    assert losses and all(torch.isfinite(torch.tensor(losses)))
    assert any(not torch.equal(b, p) for b, p in zip(before, exp.loss.parameters(), strict=True))


@pytest.mark.parametrize(
    "override, field",
    [
        ("epsilon_critic=-0.1", "epsilon_critic"),
        ("epsilon_actor=-1e-3", "epsilon_actor"),
        ("epsilon_critic=nan", "epsilon_critic"),
        ("epsilon_actor=inf", "epsilon_actor"),
    ],
)
def test_bad_epsilons_are_refused_before_the_run_dir_is_written(
    override: str, field: str, tmp_path: Path
) -> None:
    with pytest.raises(ConfigError, match=rf"^{field} must be a finite number") as err:
        M3DDPGConfig().with_overrides([override])
    assert "\n" not in str(err.value)
    key, value = override.split("=")
    with pytest.raises(ConfigError, match=field):
        M3DDPG(M3DDPGConfig(**{key: float(value)}), tmp_path / "run")
    assert not (tmp_path / "run").exists()
    with pytest.raises(ValueError, match=field):
        _losses(
            _actor(),
            _linear_critic(torch.zeros(N, N, D)),
            *((float(value), 0.0) if key == "epsilon_critic" else (0.0, float(value))),
        )
