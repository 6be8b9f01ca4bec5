"""Small pieces the baseline recipes share: the agent group's spec, the multi-agent loss keys,
and a Gumbel-softmax head for deterministic-policy-gradient methods on discrete actions."""

from __future__ import annotations

import dataclasses

import torch
from torch import nn
from torchrl.data import Bounded, OneHot, TensorSpec
from torchrl.envs import EnvBase
from torchrl.envs.utils import ExplorationType, exploration_type

GROUP = "agents"
OBS = (GROUP, "observation")
ACTION = (GROUP, "action")
REWARD = (GROUP, "reward")
DONE = (GROUP, "done")
TERMINATED = (GROUP, "terminated")
MASK = (GROUP, "mask")

LOSS_KEYS = {"reward": REWARD, "done": DONE, "terminated": TERMINATED}
"""Per-agent reward / done / terminated keys for ``loss.set_keys(**LOSS_KEYS)``."""


@dataclasses.dataclass(frozen=True)
class AgentGroupSpec:
    """What the modules of a recipe need to know about the ``"agents"`` group of an env.

    Attributes:
        n_agents: I.
        obs_dim: per-agent observation size.
        action_spec: unbatched per-group action spec, shape [I, act_dim] (continuous, Bounded)
            or [I, n_actions] (discrete, one-hot).
        discrete: True for one-hot actions.
        action_dim: act_dim (continuous) or n_actions (discrete).
    """

    n_agents: int
    obs_dim: int
    action_spec: TensorSpec
    discrete: bool
    action_dim: int

    @classmethod
    def from_env(cls, env: EnvBase) -> AgentGroupSpec:
        obs = env.full_observation_spec_unbatched[OBS]
        action = env.full_action_spec_unbatched[ACTION]
        if obs.ndim != 2:
            raise ValueError(f"env observation {OBS} must be [I, obs_dim], got {obs.shape}")
        if isinstance(action, OneHot):
            discrete = True
        elif isinstance(action, Bounded) and action.domain == "continuous":
            discrete = False
        else:
            raise ValueError(f"env action {ACTION} must be a Bounded continuous or a OneHot "
                             f"spec, got {type(action).__name__}")
        return cls(n_agents=obs.shape[0], obs_dim=obs.shape[-1], action_spec=action,
                   discrete=discrete, action_dim=action.shape[-1])

    @property
    def action_half_range(self) -> torch.Tensor:
        """(high - low) / 2 of a continuous action, [I, act_dim]."""
        return (self.action_spec.space.high - self.action_spec.space.low) / 2


class GumbelSoftmaxHead(nn.Module):
    """Logits [..., n] -> one-hot action [..., n] that carries gradients (MADDPG, Lowe et al.
    2017, discrete actions).

    Under ``ExplorationType.RANDOM`` (collection) it draws a hard Gumbel-softmax sample at
    temperature ``tau`` (straight-through estimator); otherwise (evaluation and the loss's
    actor update) the greedy one-hot ``argmax`` with the straight-through softmax gradient.
    """

    def __init__(self, tau: float = 1.0) -> None:
        super().__init__()
        if tau <= 0:
            raise ValueError(f"tau must be > 0, got {tau}")
        self.tau = tau

    def forward(self, logits: torch.Tensor) -> torch.Tensor:
        if exploration_type() is ExplorationType.RANDOM:
            return nn.functional.gumbel_softmax(logits, tau=self.tau, hard=True)
        soft = logits.softmax(-1)
        hard = nn.functional.one_hot(soft.argmax(-1), soft.shape[-1]).to(soft.dtype)
        return hard + soft - soft.detach()


def masked_mean(value: torch.Tensor, mask: torch.Tensor | None) -> float:
    """Mean of ``value`` [..., I, k] over entries whose agent is alive (``mask`` [..., I])."""
    if mask is None:
        return value.float().mean().item()
    weights = mask.to(value.dtype).reshape(*mask.shape, *([1] * (value.ndim - mask.ndim)))
    weights = weights.expand_as(value)
    return (value * weights).sum().div(weights.sum().clamp_min(1)).item()


class RunningObsNorm(nn.Module):
    """Per-feature observation standardisation with running statistics (Chan et al.'s parallel
    mean/variance update), shared by the agents: ``(obs - mean) / sqrt(var + eps)``, clipped
    to ``[-clip, clip]``. Statistics change only through :meth:`update` (called by the recipe
    on collected data), so the module is a fixed function between updates and its buffers
    travel with checkpoints and policy-weight syncs.

    Args:
        obs_dim: feature size (the last dim of the observation).
        eps: variance floor (> 0).
        clip: output clip (> 0).
    """

    def __init__(self, obs_dim: int, eps: float = 1e-6, clip: float = 10.0) -> None:
        super().__init__()
        if obs_dim < 1:
            raise ValueError(f"obs_dim must be >= 1, got {obs_dim}")
        if eps <= 0 or clip <= 0:
            raise ValueError(f"eps and clip must be > 0, got eps={eps}, clip={clip}")
        self.eps, self.clip = eps, clip
        self.register_buffer("mean", torch.zeros(obs_dim))
        self.register_buffer("var", torch.ones(obs_dim))
        self.register_buffer("count", torch.zeros(()))

    @torch.no_grad()
    def update(self, obs: torch.Tensor, mask: torch.Tensor | None = None) -> None:
        """Fold ``obs`` [..., obs_dim] into the statistics (rows whose ``mask`` [...] is False,
        e.g. crashed agents, are skipped)."""
        x = obs.reshape(-1, obs.shape[-1]).to(self.mean.dtype)
        if mask is not None:
            x = x[mask.reshape(-1)]
        n = x.shape[0]
        if n == 0:
            return
        batch_mean, batch_var = x.mean(0), x.var(0, unbiased=False)
        total = self.count + n
        delta = batch_mean - self.mean
        self.var.copy_((self.var * self.count + batch_var * n
                        + delta.pow(2) * self.count * n / total) / total)
        self.mean.add_(delta * n / total)
        self.count.copy_(total)

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        return ((obs - self.mean) / (self.var + self.eps).sqrt()).clamp(-self.clip, self.clip)
