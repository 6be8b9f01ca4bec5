"""Epsilon-greedy exploration over a subset of the discrete actions (MADDPG and the Shapley
actor-critic share it): e.g. lane changes but no random emergency stop on the freeways."""

from __future__ import annotations

from collections.abc import Sequence

import torch
from tensordict.utils import NestedKey
from torchrl.data import TensorSpec
from torchrl.modules import EGreedyModule

from mapets_rl.modules.keys import ACTION


def restricted_epsilon_greedy(
    action_spec: TensorSpec,
    actions: Sequence[int],
    *,
    eps_init: float,
    eps_end: float,
    annealing_num_steps: int,
    action_key: NestedKey = ACTION,
) -> EGreedyModule:
    """torchrl's ``EGreedyModule`` whose random actions are uniform over ``actions``.

    Args:
        action_spec: the one-hot action spec of the agent group, ``[n_agents, action_dim]``
            (unbatched); it is cloned, not changed.
        actions: the action indices a random draw picks from (empty: all of them).
        eps_init, eps_end: the probability of a random action per agent, annealed linearly
            from ``eps_init`` to ``eps_end`` over ``annealing_num_steps`` frames (the module's
            ``step(frames)``).
        action_key: where the greedy action is read and the explored one written.

    Raises:
        ValueError: an index outside ``[0, action_dim)``, named with the allowed range.
    """
    action_dim = action_spec.shape[-1]
    allowed = list(actions) or list(range(action_dim))
    if min(allowed) < 0 or max(allowed) >= action_dim:
        raise ValueError(
            f"exploration_actions must be action indices in [0, {action_dim - 1}], got {allowed}"
        )
    spec = action_spec.clone()
    mask = torch.zeros(action_dim, dtype=torch.bool)
    mask[allowed] = True
    spec.update_mask(mask.expand(spec.shape))
    return EGreedyModule(
        spec,
        eps_init=eps_init,
        eps_end=eps_end,
        annealing_num_steps=annealing_num_steps,
        action_key=action_key,
    )
