"""COMA: the counterfactual baseline on constructed batches, gradient routing, TD targets and a
tiny freeway run of the recipe."""

import json
from pathlib import Path

import pytest
import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModule
from torch import nn

from mapets_rl.experiment import ConfigError
from mapets_rl.objectives import COMACritic, COMALoss, counterfactual_advantage
from mapets_rl.recipes.coma import COMA, COMAConfig

OBS = ("agents", "observation")
ACTION = ("agents", "action")
LOGITS = ("agents", "logits")
N, OBS_DIM, A = 3, 4, 3


def test_counterfactual_advantage_known_answer() -> None:
    q = torch.tensor([[1.0, 2.0, 3.0], [-1.0, 0.0, 4.0]])
    pi = torch.tensor([[0.2, 0.3, 0.5], [0.5, 0.25, 0.25]])
    u = torch.tensor([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0]])
    adv, q_taken, baseline = counterfactual_advantage(q, pi, u)
    # 0.2*1 + 0.3*2 + 0.5*3 = 2.3; 0.5*-1 + 0 + 0.25*4 = 0.5
    torch.testing.assert_close(baseline, torch.tensor([2.3, 0.5]))
    torch.testing.assert_close(q_taken, torch.tensor([3.0, -1.0]))
    torch.testing.assert_close(adv, torch.tensor([0.7, -1.5]))
    with pytest.raises(ValueError, match="same shape"):
        counterfactual_advantage(q, pi[:, :2], u)


def _actor() -> TensorDictModule:
    return TensorDictModule(nn.Linear(OBS_DIM, A), in_keys=[OBS], out_keys=[LOGITS])


def _critic() -> TensorDictModule:
    return TensorDictModule(
        COMACritic(N, OBS_DIM, A, num_cells=[16]),
        in_keys=[OBS, ACTION],
        out_keys=[("agents", "action_value")],
    )


def _batch(t: int = 5) -> TensorDict:
    g = torch.Generator().manual_seed(0)
    action = nn.functional.one_hot(torch.randint(A, (t, N), generator=g), A).float()
    done = torch.zeros(t, 1, dtype=torch.bool)
    return TensorDict(
        {
            OBS: torch.randn(t, N, OBS_DIM, generator=g),
            ACTION: action,
            "next": {
                OBS: torch.randn(t, N, OBS_DIM, generator=g),
                ("agents", "reward"): torch.randn(t, N, 1, generator=g),
                "done": done,
                "terminated": done.clone(),
            },
        },
        batch_size=[t],
    )


def test_critic_row_ignores_own_action() -> None:
    """Row a of Q(s, u^{-a}, a, .) does not depend on agent a's own action, and does on the
    others'."""
    torch.manual_seed(0)
    critic = COMACritic(N, OBS_DIM, A, num_cells=[16])
    obs = torch.randn(2, N, OBS_DIM)
    u = nn.functional.one_hot(torch.tensor([[0, 1, 2], [2, 2, 0]]), A).float()
    u_changed = u.clone()
    u_changed[:, 0] = u_changed[:, 0].roll(1, -1)  # agent 0 acts differently
    q, q_changed = critic(obs, u), critic(obs, u_changed)
    torch.testing.assert_close(q[:, 0], q_changed[:, 0])
    assert not torch.allclose(q[:, 1:], q_changed[:, 1:])
    assert q.shape == (2, N, A)


def test_loss_advantage_equals_hand_computed_expectation() -> None:
    """The loss's actor term is -mean_a log pi^a(u^a) (Q(s,u) - sum_u' pi^a(u') Q(s,(u^-a,u'))),
    with each counterfactual Q(s,(u^-a,u')) evaluated by its own critic call."""
    torch.manual_seed(1)
    loss = COMALoss(_actor(), _critic(), entropy_coeff=0.0)
    batch = _batch()
    batch.set(("agents", "coma_target"), torch.zeros(5, N))
    out = loss(batch)
    actor, critic = loss.actor_network, loss.critic_network
    obs, u = batch.get(OBS), batch.get(ACTION)
    with loss.actor_network_params.to_module(actor), loss.critic_network_params.to_module(critic):
        log_pi = actor(batch.select(OBS).clone()).get(LOGITS).log_softmax(-1)
        total = 0.0
        for t in range(5):
            for a in range(N):
                q_cf = []
                for alt in range(A):
                    joint = u[t].clone()
                    joint[a] = nn.functional.one_hot(torch.tensor(alt), A).float()
                    td = TensorDict({OBS: obs[t], ACTION: joint}, [])
                    q_cf.append(critic(td).get(("agents", "action_value"))[a, alt])
                q_cf = torch.stack(q_cf)
                taken = int(u[t, a].argmax())
                baseline = (log_pi[t, a].exp() * q_cf).sum()
                total += log_pi[t, a, taken] * (q_cf[taken] - baseline)
    torch.testing.assert_close(out["loss_actor"], -total / (5 * N), rtol=1e-5, atol=1e-6)


def test_gradients_reach_only_their_network() -> None:
    torch.manual_seed(2)
    loss = COMALoss(_actor(), _critic())
    out = loss(_batch())
    actor_params = [p for p in loss.actor_network_params.values(True, True) if p.requires_grad]
    critic_params = [p for p in loss.critic_network_params.values(True, True) if p.requires_grad]
    grads = torch.autograd.grad(
        out["loss_actor"] + out["loss_entropy"], actor_params + critic_params, allow_unused=True
    )
    assert all(g is not None and g.abs().sum() > 0 for g in grads[: len(actor_params)])
    assert all(g is None or g.abs().sum() == 0 for g in grads[len(actor_params) :])
    grads = torch.autograd.grad(out["loss_value"], actor_params + critic_params, allow_unused=True)
    assert all(g is None or g.abs().sum() == 0 for g in grads[: len(actor_params)])
    assert all(g is not None and g.abs().sum() > 0 for g in grads[len(actor_params) :])


def test_value_targets_bootstrap() -> None:
    """gamma = 0: the target is the scaled team reward; lambda = 0 with one deterministic
    policy: r + gamma * Q'(s', u')[u'_a], cut at a termination."""
    torch.manual_seed(3)
    batch = _batch()
    team = batch.get(("next", "agents", "reward")).sum(-2)  # [T, 1]
    loss = COMALoss(_actor(), _critic(), gamma=0.0, reward_scale=0.5)
    target = loss.value_targets(batch.clone()).get(("agents", "coma_target"))
    torch.testing.assert_close(target, (0.5 * team).expand(5, N))

    loss = COMALoss(_actor(), _critic(), gamma=0.9, lmbda=0.0)
    with torch.no_grad():  # a policy that always picks action 1
        loss.actor_network_params["module", "weight"].zero_()
        loss.actor_network_params["module", "bias"].copy_(torch.tensor([-50.0, 50.0, -50.0]))
    batch.get(("next", "terminated"))[2] = True
    batch.get(("next", "done"))[2] = True
    target = loss.value_targets(batch.clone()).get(("agents", "coma_target"))
    next_u = nn.functional.one_hot(torch.ones(5, N, dtype=torch.long), A).float()
    with loss.target_critic_network_params.to_module(loss.critic_network):
        q = loss.critic_network.module(batch.get(("next", *OBS)), next_u)[..., 1]
    expected = team + 0.9 * q
    expected[2] = team[2].expand(N)
    torch.testing.assert_close(target, expected)


def test_recipe_smoke_run(tmp_path: Path) -> None:
    config = COMAConfig(
        total_frames=20,
        frames_per_batch=10,
        minibatch_size=5,
        eval_interval=20,
        checkpoint_interval=20,
        eval_episodes=1,
        num_cells=[16],
        critic_cells=[16],
        logger="none",
        progress=False,
        env_config={"n_vehicles": 4, "cav_ratio": 0.5, "horizon": 5},
    )
    exp = COMA(config, tmp_path / "run")
    before = [p.detach().clone() for p in exp.policy.parameters()]
    evals = exp.train()
    assert any(not torch.equal(b, p) for b, p in zip(before, exp.policy.parameters(), strict=True))
    results = json.loads((tmp_path / "run" / "results.json").read_text())
    assert results["recipe"] == "coma"
    assert evals[-1]["frames"] == 20
    assert {"system_return", "average_velocity"} <= set(evals[-1]["metrics"])


def test_recipe_refuses_continuous_env_and_bad_config(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="discrete"):
        COMA(
            COMAConfig(env="figure-eight", env_config={}, logger="none", progress=False),
            tmp_path / "fe",
        )
    with pytest.raises(ConfigError, match="reward_scale"):
        COMAConfig(reward_scale=0.0)
    with pytest.raises(ConfigError, match="tau"):
        COMAConfig(tau=1.5)
