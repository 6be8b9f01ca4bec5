"""What a learned Q critic says one agent's move is worth: ``Q_i(o, a') - Q_i(o, a)``, where
``a'`` is the joint action ``a`` with agent ``i``'s entry replaced.

Set beside the exact effect of the same move (the batched freeway's counterfactual branches,
:func:`mapets_rl.envs.torch_freeway.counterfactuals.branches`), it separates a learner that
never learns what a move is worth (the critic's advantage is off) from one whose actor does not
follow its critic (the advantage is right, the greedy action is not)."""

from __future__ import annotations

import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModuleBase

from .keys import ACTION, OBS, Q_VALUE


@torch.no_grad()
def critic_advantages(
    critic: TensorDictModuleBase,
    observation: torch.Tensor,
    action: torch.Tensor,
    road: torch.Tensor,
    agent: torch.Tensor,
    replacement: torch.Tensor,
    n_actions: int,
) -> torch.Tensor:
    """Agent ``agent[k]``'s critic on road ``road[k]``: its Q with its action replaced by
    ``replacement[k]`` minus its Q with the joint action as played.

    Args:
        critic: reads ``("agents","observation")`` ``[*, I, obs]`` and one-hot
            ``("agents","action")`` ``[*, I, n_actions]``, writes ``("agents",
            "state_action_value")`` ``[*, I, 1]`` (the Q critics of ``make_q_critic``, with
            their observation normaliser).
        observation: ``[R, I, obs]``, the agents' observations on every road.
        action: ``[R, I]`` action indices as played.
        road, agent, replacement: ``[K]`` long, one entry per question.
        n_actions: width of the one-hot action.

    Returns:
        ``[K]``: ``Q_agent(o_road, a_road with a_agent := replacement) - Q_agent(o_road,
        a_road)``.
    """
    if not (road.shape == agent.shape == replacement.shape and road.dim() == 1):
        raise ValueError(
            "road, agent and replacement must be 1-d and of one length; got shapes "
            f"{tuple(road.shape)}, {tuple(agent.shape)}, {tuple(replacement.shape)}"
        )
    if observation.dim() != 3 or action.shape != observation.shape[:2]:
        raise ValueError(
            f"observation must be [R, I, obs] and action [R, I]; got {tuple(observation.shape)} "
            f"and {tuple(action.shape)}"
        )
    played = action[road]
    moved = played.clone()
    moved[torch.arange(len(road)), agent] = replacement
    joint = torch.cat([played, moved])
    td = TensorDict(
        {
            OBS: observation[road].repeat(2, 1, 1),
            ACTION: torch.nn.functional.one_hot(joint, n_actions).to(observation.dtype),
        },
        batch_size=[2 * len(road)],
    )
    q = critic(td).get(Q_VALUE)[..., 0]
    own = q[torch.arange(2 * len(road)), agent.repeat(2)]
    return own[len(road) :] - own[: len(road)]
