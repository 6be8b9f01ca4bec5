"""Characteristic-function critic ``v(s, a, C)`` (Han et al., sec. V-VI, Algorithm 1 line 11)."""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from tensordict.utils import NestedKey
from torch import nn
from torchrl.modules import MLP

from mapets_rl.modules.arguments import hidden_sizes, is_positive_int, require_positive_ints
from mapets_rl.modules.tensor_checks import as_mask, check_finite_many, check_real, get_tensor
from mapets_rl.shapley.game import coalition_masks

__all__ = ["CoalitionCritic"]


class CoalitionCritic(TensorDictModuleBase):
    """Neural characteristic function ``v(s, a, C)`` of the TU game over ``n`` agents.

    Mathematically this is an MLP on ``[s^C, a^C, 1_C]``: the joint state and action with the
    entries of agents outside ``C`` set to zero (paper sec. VI, "we simply set the missing input
    of the neural network to be zero") and the ``n``-bit coalition indicator. Because zeroed
    inputs contribute nothing to the first (linear) layer, that layer is computed per agent,
    ``h_j = W_j [s_j, a_j] + u_j`` (``u_j`` is the weight of the indicator bit ``j``), and a
    coalition's pre-activation is ``z_C = sum_{j in C} h_j + b`` -- a ``[K, n] @ [n, H]`` matrix
    product. Evaluating all ``2**n`` coalitions for a batch of states is therefore one call that
    never materialises ``2**n`` copies of the joint input. ``v(empty) = 0`` holds exactly
    (paper sec. IV).

    Args:
        n_agents: number of agents ``n``.
        observation_dim: per-agent observation size.
        action_dim: per-agent action size (one-hot width for discrete actions).
        num_cells: hidden sizes; the first is the width of the per-agent layer.
        embed_cells: hidden sizes of a nonlinear per-agent network before that layer (each
            agent's own weights; empty: none, the paper's MLP). With it ``h_j = W_j
            f_j(s_j, a_j) + u_j`` and the coalition is still the sum of its members'
            ``h_j``, so every fast path here and in the Shapley loss stays valid; what changes
            is that the head receives a feature of each member's state and action together
            (after ``f_j``'s nonlinearity), not their linear terms pooled over the coalition.
        member_heads: the head ends in one output per agent, ``q_j(z_C)``, and ``v(C) =
            sum_{j in C} q_j(z_C)``: the coalition's value as the sum of its members' returns
            (eq. 10), each of which can be fitted to its own member's reward
            (``coalition_values(..., per_member=True)``). ``False``: one output, ``v(C)``
            directly (the paper's).
        activation_class: hidden activation.
        observation_key, action_key, coalition_key, out_key: keys used by :meth:`forward`:
            ``observation [*, n, obs]``, ``action [*, n, act]``, ``coalition [*, n]`` (bool)
            -> ``out_key [*, 1]``.
        device: parameter device.
    """

    def __init__(
        self,
        n_agents: int,
        observation_dim: int,
        action_dim: int,
        *,
        num_cells: Sequence[int] = (128, 128),
        embed_cells: Sequence[int] = (),
        member_heads: bool = False,
        activation_class: type[nn.Module] = nn.ReLU,
        observation_key: NestedKey = ("agents", "observation"),
        action_key: NestedKey = ("agents", "action"),
        coalition_key: NestedKey = ("agents", "coalition"),
        out_key: NestedKey = "coalition_value",
        device: torch.device | str | None = None,
    ) -> None:
        require_positive_ints(
            n_agents=n_agents, observation_dim=observation_dim, action_dim=action_dim
        )
        num_cells = hidden_sizes(num_cells)
        super().__init__()
        self.n_agents = n_agents
        self.member_heads = bool(member_heads)
        self.observation_dim = observation_dim
        self.action_dim = action_dim
        self.observation_key = observation_key
        self.action_key = action_key
        self.coalition_key = coalition_key
        self.in_keys = [observation_key, action_key, coalition_key]
        self.out_keys = [out_key]
        in_dim = observation_dim + action_dim
        embed_cells = list(embed_cells)
        if not all(is_positive_int(c) for c in embed_cells):
            raise ValueError(
                f"embed_cells must be a list of ints >= 1 (empty: none), got {embed_cells}"
            )
        self.embed_weights = nn.ParameterList()
        self.embed_biases = nn.ParameterList()
        self.embed_activation = activation_class()
        for width in embed_cells:  # per agent, as nn.Linear(in_dim, width) initialises
            low = 1.0 / math.sqrt(in_dim)
            self.embed_weights.append(
                nn.Parameter(
                    torch.empty(n_agents, in_dim, width, device=device).uniform_(-low, low)
                )
            )
            self.embed_biases.append(
                nn.Parameter(torch.empty(n_agents, width, device=device).uniform_(-low, low))
            )
            in_dim = width
        hidden = num_cells[0]
        # Same initialisation as nn.Linear on the concatenated [s^C, a^C, 1_C] input.
        bound = 1.0 / math.sqrt(n_agents * (in_dim + 1))
        self.agent_weight = nn.Parameter(
            torch.empty(n_agents, in_dim, hidden, device=device).uniform_(-bound, bound)
        )
        self.membership = nn.Parameter(
            torch.empty(n_agents, hidden, device=device).uniform_(-bound, bound)
        )
        self.bias = nn.Parameter(torch.empty(hidden, device=device).uniform_(-bound, bound))
        self.head = nn.Sequential(
            activation_class(),
            MLP(
                in_features=hidden,
                out_features=n_agents if self.member_heads else 1,
                num_cells=num_cells[1:],
                activation_class=activation_class,
                device=device,
            ),
        )

    def _check_masks(self, masks: torch.Tensor) -> None:
        if masks.shape[-1] != self.n_agents or masks.ndim < 2:
            raise ValueError(
                f"masks must have shape [..., K, n_agents={self.n_agents}], "
                f"got {tuple(masks.shape)}"
            )

    def head_values(
        self, z: torch.Tensor, masks: torch.Tensor, *, per_member: bool = False
    ) -> torch.Tensor:
        """The head on coalition pre-activations: ``z [..., K, H]``, bool or 0/1 ``masks [..., K,
        n]`` (broadcast) -> ``v(C) [..., K]`` (zero for the empty coalition), or with
        ``per_member`` each member's term ``[..., K, n]`` (zero outside ``C``; needs
        ``member_heads``)."""
        if per_member and not self.member_heads:
            raise ValueError("per_member values need a critic built with member_heads=True")
        out = self.head(z).to(z.dtype)
        if self.member_heads:
            terms = out * masks.to(out.dtype)
            return terms if per_member else terms.sum(-1)
        return out.squeeze(-1) * masks.any(-1).to(out.dtype)

    def embed(self, observation: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        """Per-agent first-layer terms ``h_j``: ``[..., n, obs], [..., n, act] -> [..., n, H]``."""
        n = self.n_agents
        if observation.shape[-2:] != (n, self.observation_dim):
            raise ValueError(
                f"observation must have shape [..., {n}, {self.observation_dim}], "
                f"got {tuple(observation.shape)}"
            )
        if action.shape[-2:] != (n, self.action_dim):
            raise ValueError(
                f"action must have shape [..., {n}, {self.action_dim}], got {tuple(action.shape)}"
            )
        shape = torch.broadcast_shapes(observation.shape[:-1], action.shape[:-1])
        observation, action = observation.expand(*shape, -1), action.expand(*shape, -1)
        x = torch.cat([observation, action.to(observation.dtype)], dim=-1)
        for weight, bias in zip(self.embed_weights, self.embed_biases, strict=True):
            x = self.embed_activation(torch.einsum("...ni,nih->...nh", x, weight) + bias)
        return torch.einsum("...ni,nih->...nh", x, self.agent_weight) + self.membership

    def values_from_embedding(
        self,
        h: torch.Tensor,
        masks: torch.Tensor,
        *,
        chunk_states: int | None = None,
        autocast_dtype: torch.dtype | None = None,
        per_member: bool = False,
    ) -> torch.Tensor:
        """``v(s, a, C)`` from the per-agent first-layer terms ``h`` of :meth:`embed`.

        Args:
            h: ``[..., n, H]``; masks: bool ``[..., K, n]`` (broadcast against the leading dims).
            chunk_states: evaluate at most this many states (leading elements of the broadcast
                batch) per pass, so that the ``[chunk, K, H]`` intermediates stay in cache;
                ``None``: one pass. The result does not depend on it.
            autocast_dtype: run the hidden layers under ``torch.autocast`` in this dtype (e.g.
                ``torch.bfloat16``); the values come back in ``h``'s dtype. ``None``: no autocast.
            per_member: return each member's term (see :meth:`head_values`).

        Returns:
            ``[..., K]``; zero for the empty coalition (``[..., K, n]`` with ``per_member``).
        """
        self._check_masks(masks)
        if chunk_states is not None and (
            isinstance(chunk_states, bool) or not isinstance(chunk_states, int) or chunk_states < 1
        ):
            raise ValueError(f"chunk_states must be None or an int >= 1, got {chunk_states!r}")
        batch = torch.broadcast_shapes(h.shape[:-2], masks.shape[:-2])
        k = masks.shape[-2]
        h = h.expand(*batch, *h.shape[-2:]).reshape(-1, *h.shape[-2:])  # [S, n, H]
        shared_masks = masks.ndim == 2  # one set of coalitions for every state: not copied
        m = masks if shared_masks else masks.expand(*batch, *masks.shape[-2:]).flatten(0, -3)
        size = h.shape[0] if chunk_states is None else chunk_states
        parts = []
        for start in range(0, h.shape[0], size):
            hc = h[start : start + size]
            mc = m if shared_masks else m[start : start + size]
            z = mc.to(hc.dtype) @ hc + self.bias  # [S_c, K, H]
            with torch.autocast(
                hc.device.type, dtype=autocast_dtype or torch.bfloat16, enabled=bool(autocast_dtype)
            ):
                value = self.head_values(z, mc, per_member=per_member)
            parts.append(value.to(h.dtype))
        return torch.cat(parts).reshape(*batch, k, *parts[0].shape[2:])

    def coalition_values(
        self,
        observation: torch.Tensor,
        action: torch.Tensor,
        masks: torch.Tensor,
        *,
        chunk_states: int | None = None,
        autocast_dtype: torch.dtype | None = None,
        per_member: bool = False,
    ) -> torch.Tensor:
        """``v(s, a, C)`` for ``K`` coalitions per state.

        Args:
            observation: ``[..., n, obs]``; action: ``[..., n, act]``.
            masks: bool ``[..., K, n]`` (broadcast against the leading dims).
            chunk_states, autocast_dtype, per_member: see :meth:`values_from_embedding`.

        Returns:
            ``[..., K]``; zero for the empty coalition (``[..., K, n]`` with ``per_member``).
        """
        self._check_masks(masks)
        h = self.embed(observation, action)  # [..., n, H]
        return self.values_from_embedding(
            h,
            masks,
            chunk_states=chunk_states,
            autocast_dtype=autocast_dtype,
            per_member=per_member,
        )

    def all_coalition_values(
        self,
        observation: torch.Tensor,
        action: torch.Tensor,
        *,
        chunk_states: int | None = None,
        autocast_dtype: torch.dtype | None = None,
    ) -> torch.Tensor:
        """``v(s, a, C_k)`` for all ``2**n`` coalitions: ``-> [..., 2**n]`` (encoding of
        :func:`~mapets_rl.shapley.coalition_masks`), one batched call (or one per chunk of
        ``chunk_states`` states; see :meth:`values_from_embedding`)."""
        masks = coalition_masks(self.n_agents, device=self.bias.device)
        return self.coalition_values(
            observation, action, masks, chunk_states=chunk_states, autocast_dtype=autocast_dtype
        )

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        """Reads observation ``[*, n, obs]`` (real), action ``[*, n, act]`` (both finite) and
        coalition ``[*, n]`` (bool, or 0/1); writes ``out_key [*, 1]``. The inputs are checked
        here, once per call."""
        n, owner = self.n_agents, type(self).__name__
        obs_shape, act_shape = f"[*, {n}, {self.observation_dim}]", f"[*, {n}, {self.action_dim}]"
        observation = get_tensor(tensordict, self.observation_key, obs_shape, owner)
        action = get_tensor(tensordict, self.action_key, act_shape, owner)
        coalition = get_tensor(tensordict, self.coalition_key, f"[*, n_agents={n}] bool", owner)
        if coalition.ndim < 1 or coalition.shape[-1] != n:
            raise ValueError(
                f"coalition ({self.coalition_key}) must have shape [*, n_agents={n}], "
                f"got {tuple(coalition.shape)}"
            )
        coalition = as_mask(repr(self.coalition_key), coalition, f"[*, {n}]")
        check_real(repr(self.observation_key), observation, obs_shape)
        check_finite_many(
            {repr(self.observation_key): observation, repr(self.action_key): action}, agent_dim=-2
        )
        value = self.coalition_values(observation, action, coalition.unsqueeze(-2))
        tensordict.set(self.out_keys[0], value)
        return tensordict
