"""A planner whose agents share their plans: :class:`PlanSharingPlanner` (MA-PETS
``comm.share_plans``).

Each step every agent plans with the neighbours' plans of the step before
(:mod:`mapets_rl.comm.plans`) as known speeds in its predicted states, then broadcasts the
speeds its own chosen plan predicts. All agents still plan in one batched call and nobody
waits for anybody: a plan is received one step after it was made.
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from tensordict.utils import NestedKey

from mapets_rl.comm.plans import plan_schedule
from mapets_rl.planning.mpc import TrajectorySamplingCEM

__all__ = ["PlanSharingPlanner", "PLAN_VALUE_BYTES"]

PLAN_VALUE_BYTES = 4
"""Bytes per broadcast speed (float32)."""


class PlanSharingPlanner(TensorDictModuleBase):
    """Wraps a :class:`TrajectorySamplingCEM` so that its agents share plans.

    Reads the observation ``[*, I, S]``, the communication graph ``neighbors_key`` ``[*, I,
    I]`` (:class:`~mapets_rl.comm.CommunicationRange`), which CAV each observed vehicle is
    (``neighbour_key`` ``[*, I, K]``) and, when present, ``mask_key`` ``[*, I]`` (agents still
    driving); writes the action.

    Args:
        planner: the batched planner (its warm start and the broadcast plans are reset by
            :meth:`reset`).
        columns: the ``K`` observation columns that hold the observed vehicles' speeds (in the
            order of ``neighbour_key``'s slots).
        own_column: the column of the agent's own speed (what it broadcasts).
        fallback: ``(obs [*, I, S], action [*, I, A]) -> action`` that overrules the planner
            where the scenario says the plans cannot be told apart
            (:attr:`~mapets_rl.envs.PlannerReward.fallback`); an overruled agent broadcasts what
            repeating the fallback's action over the horizon leads to, not the plan it did not
            follow. ``None``: the planner's actions stand.
        neighbors_key / neighbour_key / mask_key: TensorDict keys.

    Attributes:
        broadcasts: plans sent since :meth:`reset_counts` (one per driving agent and step
            with at least one agent in range), each ``horizon * PLAN_VALUE_BYTES`` bytes.
        plans_used: neighbour slots filled from a received plan since :meth:`reset_counts`.
        steps: decisions since :meth:`reset_counts`.
    """

    def __init__(
        self,
        planner: TrajectorySamplingCEM,
        columns: tuple[int, ...],
        own_column: int = 0,
        *,
        fallback: Callable[[torch.Tensor, torch.Tensor], torch.Tensor] | None = None,
        neighbors_key: NestedKey = ("agents", "neighbors"),
        neighbour_key: NestedKey = ("agents", "info", "neighbour_cav"),
        mask_key: NestedKey = ("agents", "mask"),
    ) -> None:
        super().__init__()
        obs_dim = planner.model.obs_dim
        if not columns or any(not 0 <= c < obs_dim for c in (*columns, own_column)):
            raise ValueError(
                f"columns and own_column must be observation columns in [0, {obs_dim - 1}], "
                f"got columns={columns}, own_column={own_column}"
            )
        self.planner = planner
        self.columns = tuple(int(c) for c in columns)
        self.own_column = int(own_column)
        self.fallback = fallback
        self.neighbors_key = neighbors_key
        self.neighbour_key = neighbour_key
        self.mask_key = mask_key
        self.in_keys = [*planner.in_keys, neighbors_key, neighbour_key]
        self.out_keys = list(planner.out_keys)
        self._plans: torch.Tensor | None = None  # [*, I, H] last step's broadcasts
        self.reset_counts()

    def reset(self) -> None:
        """Forget the warm start and the broadcast plans (call at episode start)."""
        self.planner.reset()
        self._plans = None

    def reset_counts(self) -> None:
        """Zero :attr:`broadcasts`, :attr:`plans_used` and :attr:`steps`."""
        self.broadcasts = 0
        self.plans_used = 0
        self.steps = 0

    @property
    def bytes_per_broadcast(self) -> int:
        """One plan: ``horizon`` speeds."""
        return self.planner.config.horizon * PLAN_VALUE_BYTES

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        planner = self.planner
        obs = tensordict.get(planner.in_keys[0])
        links = tensordict.get(self.neighbors_key).to(torch.bool)
        neighbour = tensordict.get(self.neighbour_key)
        driving = tensordict.get(self.mask_key, None)
        horizon = planner.config.horizon
        if self._plans is None or self._plans.shape[:-1] != obs.shape[:-1]:
            self._plans = torch.full((*obs.shape[:-1], horizon), float("nan"), device=obs.device)
        if driving is not None:  # the env's rows of CAVs that no longer drive say nothing
            driving = driving.to(torch.bool).reshape(obs.shape[:-1])
            neighbour = torch.where(driving.unsqueeze(-1), neighbour, -1)
        schedule, used = plan_schedule(
            self._plans, neighbour, links, self.columns, planner.model.obs_dim
        )
        is_init = tensordict.get(planner.is_init_key, None)
        action = planner.plan(obs, is_init=is_init, schedule=schedule)
        sequences = None
        if self.fallback is not None:
            overruled = self.fallback(obs, action)
            changed = (overruled != action).any(-1, keepdim=True)  # [*, I, 1]
            action = overruled
            if bool(changed.any()):
                sequences = torch.where(
                    changed.unsqueeze(-1), action.unsqueeze(-2), planner.last_solution
                )
        states = planner.expected_states(obs, schedule, sequences)
        plans = states[..., self.own_column]  # [*, I, H]
        if driving is not None:
            plans = torch.where(driving.unsqueeze(-1), plans, float("nan"))
        self._plans = plans
        sending = links.any(-1) if driving is None else links.any(-1) & driving
        self.broadcasts += int(sending.sum())
        self.plans_used += int(used.sum())
        self.steps += 1
        return tensordict.set(planner.out_keys[0], action)
