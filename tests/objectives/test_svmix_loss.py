"""SVMIXLoss on constructed batches: GAE of the team reward on the mixed value, the critic
loss and the clipped policy objective against hand-computed numbers; bad input refused."""

from __future__ import annotations

import math

import pytest
import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModule
from torch import nn
from torchrl.modules import ProbabilisticActor, TanhNormal

from mapets_rl.objectives.svmix import SVMIXLoss

T, N = 3, 2
TEAM_REWARD = [1.0, 2.0, 4.0]


class ConstantValue(nn.Module):
    """``V_tot = c`` for every step: ``observation [*, I, obs] -> [*, 1]``."""

    def __init__(self, value: float) -> None:
        super().__init__()
        self.value = nn.Parameter(torch.tensor(value))

    def forward(self, observation: torch.Tensor) -> torch.Tensor:
        return self.value.expand(*observation.shape[:-2], 1)


class Gaussian(nn.Module):
    """``loc = w * observation``, ``scale = 0.5``: ``[*, I, 1] -> ([*, I, 1], [*, I, 1])``."""

    def __init__(self) -> None:
        super().__init__()
        self.weight = nn.Parameter(torch.tensor(0.3))

    def forward(self, observation: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        return self.weight * observation, torch.full_like(observation, 0.5)


def _loss(value: float, **kwargs) -> SVMIXLoss:
    actor = ProbabilisticActor(
        TensorDictModule(
            Gaussian(),
            in_keys=[("agents", "observation")],
            out_keys=[("agents", "loc"), ("agents", "scale")],
        ),
        in_keys=[("agents", "loc"), ("agents", "scale")],
        out_keys=[("agents", "action")],
        distribution_class=TanhNormal,
        distribution_kwargs={"low": -1.0, "high": 1.0},
    )
    critic = TensorDictModule(
        ConstantValue(value), in_keys=[("agents", "observation")], out_keys=["joint_value"]
    )
    defaults = {"gamma": 0.5, "lmbda": 1.0, "reward_scale": 1.0, "normalize_advantage": False}
    return SVMIXLoss(actor, critic, **{**defaults, **kwargs})


def _batch(terminated: bool, log_prob_shift: float = 0.0) -> TensorDict:
    """3 steps of 2 agents whose rewards sum to 1, 2, 4; the episode ends at the last step
    (terminated or truncated); ``action_log_prob`` is the policy's own minus the shift."""
    obs = torch.linspace(-1, 1, T * N).reshape(T, N, 1)
    action = torch.tensor([[0.2, -0.4], [0.1, 0.5], [-0.3, 0.0]]).reshape(T, N, 1)
    reward = torch.tensor([[0.5, 0.5], [1.5, 0.5], [3.0, 1.0]]).reshape(T, N, 1)
    done = torch.tensor([False, False, True]).reshape(T, 1)
    dist = TanhNormal(0.3 * obs, torch.full_like(obs, 0.5), low=-1.0, high=1.0)
    log_prob = dist.log_prob(action) - log_prob_shift
    return TensorDict(
        {
            "agents": {"observation": obs, "action": action, "action_log_prob": log_prob},
            "next": {
                "agents": {"observation": obs + 0.1, "reward": reward},
                "done": done,
                "terminated": done & terminated,
            },
        },
        batch_size=[T],
    )


def test_the_targets_of_a_terminated_episode_are_the_discounted_team_returns() -> None:
    """V = 0, gamma 0.5, lambda 1: A_t = G_t = sum_k 0.5^k r_{t+k} = 3, 4, 4; the critic loss
    is the mean of G^2, 41/3; ratio 1, so the objective is -mean(A) = -11/3."""
    loss = _loss(0.0)
    batch = loss.value_targets(_batch(terminated=True))
    expected = torch.tensor([[3.0], [4.0], [4.0]])
    assert torch.allclose(batch["advantage"], expected)
    assert torch.allclose(batch["value_target"], expected)
    out = loss(batch)
    assert out["loss_critic"].item() == pytest.approx(41 / 3, rel=1e-6)
    assert out["loss_objective"].item() == pytest.approx(-11 / 3, rel=1e-6)
    assert out["pred_value"].item() == 0.0


def test_a_truncated_episode_bootstraps_from_the_mixed_value() -> None:
    """V = 1, done but not terminated at the last step: delta = r - 0.5 = 0.5, 1.5, 3.5 and
    A = 2.125, 3.25, 3.5; the targets A + V = 3.125, 4.25, 4.5 (G_0 = 1 + 1 + 1 + 0.125)."""
    loss = _loss(1.0)
    batch = loss.value_targets(_batch(terminated=False))
    assert torch.allclose(batch["advantage"], torch.tensor([[2.125], [3.25], [3.5]]))
    assert torch.allclose(batch["value_target"], torch.tensor([[3.125], [4.25], [4.5]]))
    out = loss(batch)
    expected = ((1 - 3.125) ** 2 + (1 - 4.25) ** 2 + (1 - 4.5) ** 2) / 3
    assert out["loss_critic"].item() == pytest.approx(expected, rel=1e-6)


def test_the_ratio_is_clipped_and_the_mean_is_over_the_agents_alive() -> None:
    """The collecting policy's log-probability lower by log 2: ratio 2, clipped at 1.2 for the
    positive advantages 3, 4, 4; agent 1 crashed at step 1, so the mean over alive agents is
    1.2 * (2 * 3 + 4 + 2 * 4) / 5."""
    loss = _loss(0.0, clip_epsilon=0.2)
    batch = _batch(terminated=True, log_prob_shift=math.log(2.0))
    batch["agents", "mask"] = torch.tensor([[True, True], [True, False], [True, True]])
    out = loss(batch)
    assert out["loss_objective"].item() == pytest.approx(-1.2 * 18 / 5, rel=1e-5)


def test_the_gradient_reaches_actor_and_critic() -> None:
    loss = _loss(0.5, entropy_coeff=0.1)
    out = loss(_batch(terminated=True))
    (out["loss_objective"] + out["loss_critic"] + out["loss_entropy"]).backward()
    grads = [p.grad for p in loss.parameters()]
    assert len(grads) == 2 and all(g is not None and g.abs() > 0 for g in grads)


def test_the_team_reward_is_scaled() -> None:
    batch = _loss(0.0, reward_scale=0.5).value_targets(_batch(terminated=True))
    assert torch.allclose(batch["value_target"], torch.tensor([[1.5], [2.0], [2.0]]))


@pytest.mark.parametrize(
    "kwargs, needle",
    [
        ({"gamma": 1.5}, "gamma must be in"),
        ({"lmbda": -0.1}, "lmbda must be in"),
        ({"clip_epsilon": 0.0}, "clip_epsilon must be a finite number > 0"),
        ({"entropy_coeff": -1.0}, "entropy_coeff must be a finite number >= 0"),
        ({"critic_coeff": float("nan")}, "critic_coeff must be a finite number > 0"),
        ({"reward_scale": 0}, "reward_scale must be a finite number > 0"),
        ({"loss_function": "huber"}, "loss_function must be"),
    ],
)
def test_bad_arguments_are_refused(kwargs: dict, needle: str) -> None:
    with pytest.raises(ValueError, match=needle):
        _loss(0.0, **kwargs)


def test_a_missing_key_is_named() -> None:
    batch = _batch(terminated=True).exclude(("next", "agents", "reward"))
    with pytest.raises(ValueError, match="reward"):
        _loss(0.0)(batch)
