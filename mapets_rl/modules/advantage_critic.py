"""A Q critic that keeps one agent's move apart from the state's value:
``Q_i(o, a) = V_i(o) + A_i(o_i, a_i) - A_i(o_i, b)``, one-hot actions, ``b`` a baseline action
(Keep Lane on the freeways).

A plain critic ``Q_i(o, a)`` (:func:`mapets_rl.modules.policies.make_q_critic`) must resolve a
move worth a fraction of a percent of the returns it fits through interactions of its inputs;
in the freeway dilemma study every such critic priced all moves alike (``docs/results/
shapley.md``). Here the move enters only through the advantage head, which reads the mover's own
observation and action, so its contrast ``A_i(o_i, a) - A_i(o_i, b)`` is what the critic says
agent ``i``'s move is worth, whatever error the state value ``V_i`` makes (under randomised
exploration that error is independent of the move). The dueling architecture (Wang et al. 2016)
with the advantage anchored at a baseline action instead of the mean, per agent."""

from __future__ import annotations

import torch
from tensordict.nn import TensorDictModule, TensorDictSequential
from torch import nn

from mapets_rl.modules.agents import AgentGroupSpec
from mapets_rl.modules.keys import ACTION, OBS, OBS_NORM, Q_VALUE, VALUE
from mapets_rl.modules.policies import make_decentralised_mlp, make_value_mlp

ADVANTAGE = ("agents", "action_advantage")
"""``A_i(o_i, .) - A_i(o_i, b)`` over the discrete actions [*, I, n] (zero at ``b``)."""


class AnchoredAdvantage(nn.Module):
    """``mlp(o_i) - mlp(o_i)[b]``: ``[*, I, obs] -> [*, I, n]``, zero at action ``b``."""

    def __init__(self, mlp: nn.Module, baseline_action: int) -> None:
        super().__init__()
        self.mlp, self.baseline_action = mlp, baseline_action

    def forward(self, observation: torch.Tensor) -> torch.Tensor:
        out = self.mlp(observation)
        return out - out[..., self.baseline_action : self.baseline_action + 1]


def value_plus_advantage(
    value: torch.Tensor, advantage: torch.Tensor, action: torch.Tensor
) -> torch.Tensor:
    """``V [*, I, 1] + sum_a A [*, I, n] * onehot [*, I, n]`` -> ``[*, I, 1]``."""
    return value + (advantage * action).sum(-1, keepdim=True)


def make_advantage_q_critic(
    spec: AgentGroupSpec,
    num_cells: list[int],
    *,
    centralized: bool,
    share_params: bool,
    baseline_action: int,
    obs_norm: TensorDictModule | None = None,
) -> TensorDictSequential:
    """The critic of this module's docstring, reading ``("agents","observation")`` [*, I, obs]
    (through ``obs_norm`` when given) and one-hot ``("agents","action")`` [*, I, n], writing
    ``("agents","state_value")`` and ``("agents","state_action_value")`` [*, I, 1] and the
    advantages ``("agents","action_advantage")`` [*, I, n].

    Args:
        spec: the agent group (discrete actions only).
        num_cells: hidden sizes of both heads.
        centralized: the value head reads every agent's observation (MADDPG), else its own.
        share_params: one network per head for all agents, else one per agent.
        baseline_action: the action whose advantage is zero, in ``[0, n)``.
        obs_norm: the observation normaliser module (writes ``("agents",
            "observation_normalized")``).
    """
    if not spec.discrete:
        raise ValueError("make_advantage_q_critic needs one-hot (discrete) actions")
    if not 0 <= baseline_action < spec.action_dim:
        raise ValueError(
            f"baseline_action must be in [0, {spec.action_dim}), got {baseline_action}"
        )
    obs_key = OBS if obs_norm is None else OBS_NORM

    value = make_value_mlp(spec, num_cells, centralized=centralized, share_params=share_params)
    advantage = make_decentralised_mlp(spec, num_cells, share_params, n_out=spec.action_dim)
    front = [] if obs_norm is None else [obs_norm]
    return TensorDictSequential(
        *front,
        TensorDictModule(value, in_keys=[obs_key], out_keys=[VALUE]),
        TensorDictModule(
            AnchoredAdvantage(advantage, baseline_action), in_keys=[obs_key], out_keys=[ADVANTAGE]
        ),
        TensorDictModule(
            value_plus_advantage, in_keys=[VALUE, ADVANTAGE, ACTION], out_keys=[Q_VALUE]
        ),
    )
