"""The planner reward a scenario may bring: a config section whose fields are its settings.

A model-based planner (MA-PETS) scores predicted trajectories with a known reward and may end
them with a known termination. A scenario that provides them registers a :class:`PlannerReward`
subclass (:func:`~mapets_rl.envs.registry.register_builtin`): its fields (margins, penalties)
are declared, defaulted and validated there, once, and a recipe's config holds an instance as
its nested ``planner_reward`` section (``planner_reward.headway=0.5`` on the command line).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

import torch

from mapets_rl.config import ConfigSection

__all__ = ["PlannerReward"]


@dataclasses.dataclass(frozen=True)
class PlannerReward(ConfigSection):
    """Base of a scenario's planner reward: a frozen, validated config section whose
    :meth:`reward` (and optional :attr:`termination_fn`) a planner calls on batches of
    predicted transitions."""

    def reward(
        self, obs: torch.Tensor, action: torch.Tensor, next_obs: torch.Tensor
    ) -> torch.Tensor:
        """The reward ``[...]`` of transitions ``obs [..., S]``, ``action [..., A]``,
        ``next_obs [..., S]``."""
        raise NotImplementedError(f"{type(self).__name__} must implement reward")

    @property
    def termination_fn(
        self,
    ) -> Callable[[torch.Tensor, torch.Tensor, torch.Tensor], torch.Tensor] | None:
        """``(obs, action, next_obs) -> done [...]`` bool, a predicted termination that ends a
        planned trajectory; ``None``: trajectories never terminate."""
        return None

    @property
    def fallback(self) -> Callable[[torch.Tensor, torch.Tensor], torch.Tensor] | None:
        """``(obs [..., S], action [..., A]) -> action [..., A]``: the planner's chosen action
        replaced where the scenario knows the plans cannot tell their actions apart (e.g.
        every plan is predicted to crash at its first step); ``None``: the planner's action
        stands."""
        return None
