"""Coalition-aware actors: agent ``i`` acts on ``s^C`` (Han et al., Algorithm 1 line 7)."""

from __future__ import annotations

from collections.abc import Sequence

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModule, TensorDictModuleBase, TensorDictSequential
from tensordict.utils import NestedKey
from torch import nn
from torchrl.modules import MultiAgentMLP, TanhModule

from mapets_rl.modules.arguments import require_positive_ints
from mapets_rl.modules.heads import one_hot_argmax

__all__ = ["CoalitionObservation", "make_coalition_actor"]


class CoalitionObservation(TensorDictModuleBase):
    """Builds every agent's view ``s^C`` of the joint state.

    Agent ``i`` in coalition ``C`` sees the observations of all members of ``C``; an agent outside
    ``C`` sees only its own. Unseen observations are zeroed (paper sec. VI) and the visibility bits
    are appended so that a zero observation and an unseen one differ.

    Reads ``observation [*, n, obs]`` and ``coalition [*, n]`` (bool); writes
    ``out_key [*, n, n * (obs + 1)]`` (row ``i`` = agent ``i``'s flattened view). With
    ``ego_first`` row ``i`` lists the agents in the order ``i, i+1, ..., i-1`` (its own
    observation first), so that one network shared by all agents knows which slot is its own;
    without it every row lists agents ``0..n-1``.
    """

    def __init__(
        self,
        n_agents: int,
        *,
        observation_key: NestedKey = ("agents", "observation"),
        coalition_key: NestedKey = ("agents", "coalition"),
        out_key: NestedKey = ("agents", "coalition_observation"),
        ego_first: bool = False,
    ) -> None:
        require_positive_ints(n_agents=n_agents)
        super().__init__()
        self.n_agents = n_agents
        self.ego_first = bool(ego_first)
        self.in_keys = [observation_key, coalition_key]
        self.out_keys = [out_key]
        self.register_buffer("_eye", torch.eye(n_agents, dtype=torch.bool), persistent=False)
        # order[i, k] = (i + k) mod n: the k-th agent in agent i's ego-first view
        order = (torch.arange(n_agents).unsqueeze(-1) + torch.arange(n_agents)) % n_agents
        self.register_buffer("_order", order, persistent=False)

    def view(self, observation: torch.Tensor, coalition: torch.Tensor) -> torch.Tensor:
        """``[..., n, obs], [..., n] -> [..., n, n * (obs + 1)]``."""
        n = self.n_agents
        if observation.shape[-2] != n:
            raise ValueError(
                f"observation must have shape [..., n_agents={n}, obs], "
                f"got {tuple(observation.shape)}"
            )
        if coalition.shape[-1] != n:
            raise ValueError(
                f"coalition must have shape [..., n_agents={n}], got {tuple(coalition.shape)}"
            )
        coalition = coalition.bool()
        if self.ego_first:
            # row i lists agents (i + k) mod n: windows of the doubled agents axis, a view
            doubled = torch.cat([observation, observation], dim=-2)  # [..., 2n, obs]
            rows = doubled.unfold(-2, n, 1)[..., :n, :, :].transpose(-1, -2)  # [..., n, n, obs]
            visible = (coalition.unsqueeze(-1) & coalition[..., self._order]) | self._eye[0]
        else:
            rows = observation.unsqueeze(-3).expand(
                *observation.shape[:-2], n, *observation.shape[-2:]
            )
            visible = (coalition.unsqueeze(-1) & coalition.unsqueeze(-2)) | self._eye
        bits = visible.unsqueeze(-1).to(observation.dtype)  # [..., n, n, 1]
        view = torch.cat([rows * bits, bits], dim=-1)
        return view.flatten(-2)

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        obs_key, coalition_key = self.in_keys
        tensordict.set(
            self.out_keys[0], self.view(tensordict.get(obs_key), tensordict.get(coalition_key))
        )
        return tensordict


def make_coalition_actor(
    n_agents: int,
    observation_dim: int,
    action_dim: int,
    *,
    discrete: bool,
    num_cells: Sequence[int] = (64, 64),
    activation_class: type[nn.Module] = nn.Tanh,
    share_params: bool = False,
    ego_first: bool = False,
    action_head: nn.Module | None = None,
    action_low: float = -1.0,
    action_high: float = 1.0,
    observation_key: NestedKey = ("agents", "observation"),
    coalition_key: NestedKey = ("agents", "coalition"),
    action_key: NestedKey = ("agents", "action"),
    logits_key: NestedKey = ("agents", "logits"),
    device: torch.device | str | None = None,
) -> TensorDictSequential:
    """Deterministic per-agent actors ``pi_i(s^C)`` (torchrl ``MultiAgentMLP``, one set of
    parameters per agent unless ``share_params``).

    ``ego_first``: each agent's view lists its own observation first (see
    :class:`CoalitionObservation`; use it with ``share_params``).

    Discrete: writes ``logits_key [*, n, act]`` and ``action_key [*, n, act]``, the one-hot image
    of the logits by ``action_head`` (default: greedy ``argmax``; pass e.g. a Gumbel-softmax
    sampler for exploration). Freeway order: KL, CL, CR, ES.
    Continuous: writes ``action_key [*, n, act]`` squashed into ``[action_low, action_high]``
    with ``TanhModule``.
    """
    require_positive_ints(n_agents=n_agents, observation_dim=observation_dim, action_dim=action_dim)
    if not discrete and not action_low < action_high:
        raise ValueError(f"action_low must be < action_high, got {action_low}, {action_high}")
    view_key = ("agents", "coalition_observation")
    view = CoalitionObservation(
        n_agents,
        observation_key=observation_key,
        coalition_key=coalition_key,
        out_key=view_key,
        ego_first=ego_first,
    )
    net = MultiAgentMLP(
        n_agent_inputs=n_agents * (observation_dim + 1),
        n_agent_outputs=action_dim,
        n_agents=n_agents,
        centralized=False,
        share_params=share_params,
        num_cells=list(num_cells),
        activation_class=activation_class,
        device=device,
    )
    if discrete:
        head = TensorDictModule(net, in_keys=[view_key], out_keys=[logits_key])
        to_action = action_head if action_head is not None else one_hot_argmax
        greedy = TensorDictModule(to_action, in_keys=[logits_key], out_keys=[action_key])
        return TensorDictSequential(view, head, greedy)
    param_key = ("agents", "param")
    head = TensorDictModule(net, in_keys=[view_key], out_keys=[param_key])
    squash = TanhModule(
        in_keys=[param_key], out_keys=[action_key], low=action_low, high=action_high
    )
    return TensorDictSequential(view, head, squash)
