"""What a recipe needs to know about an env's ``"agents"`` group, and the masked mean over the
agents still driving."""

from __future__ import annotations

import dataclasses

import torch
from torchrl.data import Bounded, OneHot, TensorSpec
from torchrl.envs import EnvBase

from mapets_rl.modules.keys import ACTION, OBS


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
            raise ValueError(
                f"env action {ACTION} must be a Bounded continuous or a OneHot "
                f"spec, got {type(action).__name__}"
            )
        return cls(
            n_agents=obs.shape[0],
            obs_dim=obs.shape[-1],
            action_spec=action,
            discrete=discrete,
            action_dim=action.shape[-1],
        )

    @property
    def action_half_range(self) -> torch.Tensor:
        """(high - low) / 2 of a continuous action, [I, act_dim]."""
        return (self.action_spec.space.high - self.action_spec.space.low) / 2


def masked_mean(value: torch.Tensor, mask: torch.Tensor | None) -> float:
    """Mean of ``value`` [..., I, k] over entries whose agent is alive (``mask`` [..., I])."""
    if mask is None:
        return value.float().mean().item()
    weights = mask.to(value.dtype).reshape(*mask.shape, *([1] * (value.ndim - mask.ndim)))
    weights = weights.expand_as(value)
    return (value * weights).sum().div(weights.sum().clamp_min(1)).item()
