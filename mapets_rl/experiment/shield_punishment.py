"""The replay data of a learner under the shield, with a punishment for a replaced move.

With ``shield=True`` the batched freeway stores the move that ran (Keep Lane where the shield
replaced the proposal) and keeps the proposal under ``("agents", "proposed_action")``
(:data:`~mapets_rl.envs.torch_freeway.env.PROPOSED_ACTION`). Fitted to that, a critic credits
Keep Lane with the returns of the dangerous states where the shield stepped in, so every move
looks better than Keep Lane (issue 50: ``docs/results/shapley.md``, "Can a critic resolve one
CAV's move?"); fitted to the proposal with Keep Lane's reward (the data before the rewrite), a
replaced move looks harmless. Post-posed shielding with punishment (Alshiekh et al. 2018, "Safe
Reinforcement Learning via Shielding", sec. 5) updates the learner with the unsafe proposal and
a punishment instead: :func:`punish_shielded_moves` rewrites a collected batch so that where an
agent's move was replaced, its transition holds the proposal and its reward minus the penalty;
the next state is the one Keep Lane reached, and the other agents' rows are unchanged.
"""

from __future__ import annotations

import torch
from tensordict import TensorDictBase

from mapets_rl.envs.torch_freeway.env import PROPOSED_ACTION
from mapets_rl.modules.keys import ACTION, REWARD


@torch.no_grad()
def punish_shielded_moves(batch: TensorDictBase, penalty: float) -> TensorDictBase:
    """``batch [*]`` of shielded transitions -> the same with every replaced move restored.

    An agent's move counts as replaced where the stored action ``("agents", "action")``
    ``[*, I, n]`` (one-hot, or indices ``[*, I]``) differs from the proposal
    ``("agents", "proposed_action")`` of the same form. There the action becomes the proposal
    and ``("next", "agents", "reward")`` ``[*, I, 1]`` drops by ``penalty`` (>= 0); everything
    else, the next state included, is kept. Returns a new tensordict; ``batch`` is unchanged.

    Raises:
        ValueError: ``penalty`` < 0, or the batch has no proposal (the env ran without the
            shield, or a wrapper stepped a copy: see the freeway env's docstring).
    """
    if penalty < 0:
        raise ValueError(f"shield_penalty must be >= 0, got {penalty}")
    if PROPOSED_ACTION not in batch.keys(include_nested=True):
        raise ValueError(
            "shield_penalty needs the shield's proposals under ('agents', 'proposed_action'): "
            "run the torch freeway with shield=True, stepped by the experiment's collector"
        )
    action, proposed = batch.get(ACTION), batch.get(PROPOSED_ACTION)
    replaced = action != proposed  # [*, I, n] or [*, I]
    if action.dim() == batch.get(("next", *REWARD)).dim():  # one-hot: reduce over actions
        replaced = replaced.any(-1)
    out = batch.clone(False)
    out.set(ACTION, proposed.clone())
    reward = batch.get(("next", *REWARD))
    out.set(("next", *REWARD), reward - penalty * replaced.unsqueeze(-1).to(reward.dtype))
    return out
