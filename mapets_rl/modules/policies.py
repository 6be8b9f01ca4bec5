"""Building blocks of the baselines' policies and critics."""

from __future__ import annotations

import torch
from tensordict.nn import NormalParamExtractor, TensorDictModule, TensorDictSequential
from tensordict.utils import NestedKey
from torch import nn
from torchrl.modules import MultiAgentMLP, OneHotCategorical, ProbabilisticActor, TanhNormal

from mapets_rl.modules.agents import AgentGroupSpec
from mapets_rl.modules.keys import ACTION, GROUP, LOG_PROB, OBS, OBS_ACTION, OBS_NORM, Q_VALUE


def concat_last(*tensors: torch.Tensor) -> torch.Tensor:
    """Concatenate along the last dim ([*, I, obs] + [*, I, act] -> [*, I, obs + act])."""
    return torch.cat(tensors, dim=-1)


def make_stochastic_policy(
    spec: AgentGroupSpec,
    num_cells: list[int],
    share_params: bool,
    return_log_prob: bool = True,
    obs_norm: TensorDictModule | None = None,
) -> ProbabilisticActor:
    """Decentralised stochastic policy: ``("agents","observation")`` [*, I, obs] (through
    ``obs_norm`` when given) -> ``("agents","action")`` [*, I, act] (TanhNormal within the
    action bounds, or one-hot categorical [*, I, n]) and its log-probability
    ``("agents","action_log_prob")`` [*, I]."""
    obs_key = OBS if obs_norm is None else OBS_NORM
    n_out = spec.action_dim if spec.discrete else 2 * spec.action_dim
    mlp = make_decentralised_mlp(spec, num_cells, share_params, n_out, nn.Tanh)
    if spec.discrete:
        module = TensorDictModule(mlp, in_keys=[obs_key], out_keys=[(GROUP, "logits")])
        dist_keys, dist_cls, dist_kwargs = [(GROUP, "logits")], OneHotCategorical, {}
    else:
        module = TensorDictModule(
            nn.Sequential(mlp, NormalParamExtractor()),
            in_keys=[obs_key],
            out_keys=[(GROUP, "loc"), (GROUP, "scale")],
        )
        dist_keys, dist_cls = [(GROUP, "loc"), (GROUP, "scale")], TanhNormal
        dist_kwargs = {"low": spec.action_spec.space.low, "high": spec.action_spec.space.high}
    if obs_norm is not None:
        module = TensorDictSequential(obs_norm, module)
    return ProbabilisticActor(
        module,
        in_keys=dist_keys,
        out_keys=[ACTION],
        spec=spec.action_spec,
        distribution_class=dist_cls,
        distribution_kwargs=dist_kwargs,
        return_log_prob=return_log_prob,
        log_prob_key=LOG_PROB,
    )


def make_value_mlp(
    spec: AgentGroupSpec,
    num_cells: list[int],
    *,
    centralized: bool,
    share_params: bool,
    activation: type[nn.Module] = nn.ReLU,
    n_inputs: int | None = None,
) -> MultiAgentMLP:
    """One scalar per agent: inputs ``[*, I, n_inputs]`` (default the observation,
    ``spec.obs_dim``: a state value ``V(o)``; with the action appended, a ``Q(o, a)``) ->
    ``[*, I, 1]``, a ``MultiAgentMLP`` with ``activation``; ``centralized``: every agent's
    output reads all agents' inputs, else only its own."""
    return MultiAgentMLP(
        n_agent_inputs=spec.obs_dim if n_inputs is None else n_inputs,
        n_agent_outputs=1,
        n_agents=spec.n_agents,
        centralized=centralized,
        share_params=share_params,
        depth=len(num_cells),
        num_cells=num_cells,
        activation_class=activation,
    )


def make_q_critic(
    spec: AgentGroupSpec,
    num_cells: list[int],
    *,
    centralized: bool,
    share_params: bool,
    obs_norm: TensorDictModule | None = None,
) -> TensorDictSequential:
    """Critic ``Q(o, a)`` of continuous or one-hot actions: (``obs_norm`` ->) the observation
    ``[*, I, obs]`` and ``("agents","action")`` ``[*, I, act]`` concatenated into
    ``("agents","obs_action")``, then a ReLU ``MultiAgentMLP`` writing
    ``("agents","state_action_value")`` ``[*, I, 1]``; ``centralized``: every agent's Q reads
    all agents' observations and actions (MADDPG), else only its own (SAC)."""
    obs_key = OBS if obs_norm is None else OBS_NORM
    front = [] if obs_norm is None else [obs_norm]
    return TensorDictSequential(
        *front,
        TensorDictModule(concat_last, in_keys=[obs_key, ACTION], out_keys=[OBS_ACTION]),
        TensorDictModule(
            make_value_mlp(
                spec,
                num_cells,
                centralized=centralized,
                share_params=share_params,
                n_inputs=spec.obs_dim + spec.action_dim,
            ),
            in_keys=[OBS_ACTION],
            out_keys=[Q_VALUE],
        ),
    )


def make_decentralised_mlp(
    spec: AgentGroupSpec,
    num_cells: list[int],
    share_params: bool,
    n_out: int | None = None,
    activation: type[nn.Module] = nn.ReLU,
) -> MultiAgentMLP:
    """Each agent's own observation ``[*, I, obs]`` -> ``n_out`` outputs ``[*, I, n_out]``
    (default one per action), a ``MultiAgentMLP`` with ``activation`` (ReLU: MADDPG's actors,
    SAC's discrete Q(o, .); Tanh: the stochastic policies)."""
    return MultiAgentMLP(
        n_agent_inputs=spec.obs_dim,
        n_agent_outputs=spec.action_dim if n_out is None else n_out,
        n_agents=spec.n_agents,
        centralized=False,
        share_params=share_params,
        depth=len(num_cells),
        num_cells=num_cells,
        activation_class=activation,
    )


def make_discrete_actor(
    spec: AgentGroupSpec,
    num_cells: list[int],
    share_params: bool,
    head: nn.Module,
    *,
    logits_key: NestedKey,
    obs_norm: TensorDictModule | None = None,
    initial_logits: list[float] | None = None,
) -> TensorDictSequential:
    """Decentralised deterministic actor of one-hot actions (MADDPG's): (``obs_norm`` ->) each
    agent's own observation ``[*, I, obs]`` -> a ReLU ``MultiAgentMLP`` -> logits
    ``logits_key [*, I, n]`` -> ``head`` (logits -> ``(logits, action)``, e.g.
    :class:`~mapets_rl.modules.heads.GumbelSoftmaxHead` with ``return_logits=True``) ->
    ``("agents","action")`` ``[*, I, n]``.

    ``initial_logits`` (``n`` values, every agent's): the bias of the MLP's output layer at
    construction, in place of its random one, so a greedy choice starts where the biases
    point (e.g. ``[3, 0, 0, 0]``: Keep Lane in every state on the freeways, the keep-lane
    reference, on standardised observations, where the random weights' logits are smaller
    than the margin; raw observations of 100 m can outweigh it)."""
    obs_key = OBS if obs_norm is None else OBS_NORM
    front = [] if obs_norm is None else [obs_norm]
    mlp = make_decentralised_mlp(spec, num_cells, share_params)
    if initial_logits:
        if len(initial_logits) != spec.action_dim:
            raise ValueError(
                f"initial_logits must hold one value per action ({spec.action_dim}), "
                f"got {len(initial_logits)}: {initial_logits}"
            )
        output_bias = mlp.params[str(2 * len(num_cells)), "bias"]  # [(I,) n]
        with torch.no_grad():
            output_bias.copy_(torch.as_tensor(initial_logits, dtype=output_bias.dtype))
    return TensorDictSequential(
        *front,
        TensorDictModule(
            nn.Sequential(mlp, head), in_keys=[obs_key], out_keys=[logits_key, ACTION]
        ),
    )
