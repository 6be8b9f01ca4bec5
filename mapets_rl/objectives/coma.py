"""COMA: counterfactual multi-agent policy gradients (Foerster et al., AAAI 2018).

The comparator of Han et al.'s Table I. A centralised critic ``Q(s, u^{-a}, a, .)`` returns, for
every agent ``a``, the value of each of ``a``'s discrete actions with the other agents' actions
held fixed, so the counterfactual baseline ``b^a = sum_{u'} pi^a(u' | tau^a) Q(s, (u^{-a}, u'))``
is one dot product per agent, and the actor ascends ``log pi^a(u^a) A^a`` with the advantage
``A^a = Q(s, u)_a - b^a``.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import torch
from tensordict import TensorDict, TensorDictBase, TensorDictParams
from tensordict.nn import TensorDictModule
from tensordict.utils import NestedKey, unravel_key
from torch import nn
from torchrl.modules import MLP
from torchrl.objectives import LossModule
from torchrl.objectives.utils import distance_loss
from torchrl.objectives.value.functional import td_lambda_return_estimate

from mapets_rl.modules.arguments import finite_number, hidden_sizes, require_positive_ints
from mapets_rl.modules.tensor_checks import as_mask, check_finite_many
from mapets_rl.objectives._tensor_reads import CheckedReads

__all__ = ["COMACritic", "COMALoss", "counterfactual_advantage"]


def counterfactual_advantage(
    q_values: torch.Tensor, probs: torch.Tensor, action: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """COMA's counterfactual advantage (Foerster et al. eq. 4).

    Args:
        q_values: ``[..., n, A]``, ``Q(s, (u^{-a}, u'))`` for every action ``u'`` of agent ``a``.
        probs: ``[..., n, A]``, ``pi^a(u' | tau^a)``.
        action: ``[..., n, A]``, the one-hot joint action ``u`` taken.

    Returns:
        ``(advantage, q_taken, baseline)``, each ``[..., n]``: ``q_taken = Q(s, u)`` read at
        agent ``a``'s action, ``baseline = sum_{u'} pi^a(u') Q(s, (u^{-a}, u'))`` and
        ``advantage = q_taken - baseline``.
    """
    if not q_values.shape == probs.shape == action.shape:
        raise ValueError(
            "q_values, probs and action must have the same shape [..., n, A], got "
            f"{tuple(q_values.shape)}, {tuple(probs.shape)}, {tuple(action.shape)}"
        )
    q_taken = (q_values * action.to(q_values.dtype)).sum(-1)
    baseline = (q_values * probs.to(q_values.dtype)).sum(-1)
    return q_taken - baseline, q_taken, baseline


class COMACritic(nn.Module):
    """Centralised counterfactual critic ``Q(s, u^{-a}, a, .)``: ``[*, n, obs], [*, n, A] ->
    [*, n, A]``.

    Agent ``a``'s input is the joint observation (``n * obs``; the paper's global state), the
    other agents' one-hot actions with ``a``'s own entry zeroed (``n * A``) and ``a``'s one-hot
    id (``n``); one MLP shared by all agents outputs ``a``'s ``A`` action values. All agents are
    one batch dimension.

    Args:
        n_agents: ``n``; observation_dim: per-agent observation size; n_actions: ``A``.
        num_cells: hidden sizes of the MLP; activation_class: hidden activation.
        device: parameter device.
    """

    def __init__(
        self,
        n_agents: int,
        observation_dim: int,
        n_actions: int,
        *,
        num_cells: Sequence[int] = (128, 128),
        activation_class: type[nn.Module] = nn.ReLU,
        device: torch.device | str | None = None,
    ) -> None:
        require_positive_ints(
            n_agents=n_agents, observation_dim=observation_dim, n_actions=n_actions
        )
        num_cells = hidden_sizes(num_cells)
        super().__init__()
        self.n_agents = n_agents
        self.observation_dim = observation_dim
        self.n_actions = n_actions
        self.mlp = MLP(
            in_features=n_agents * (observation_dim + n_actions + 1),
            out_features=n_actions,
            num_cells=num_cells,
            activation_class=activation_class,
            device=device,
        )

    def forward(self, observation: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        n, obs_dim, n_act = self.n_agents, self.observation_dim, self.n_actions
        if observation.shape[-2:] != (n, obs_dim):
            raise ValueError(
                f"observation must have shape [*, {n}, {obs_dim}], got {tuple(observation.shape)}"
            )
        if action.shape[-2:] != (n, n_act):
            raise ValueError(f"action must have shape [*, {n}, {n_act}], got {tuple(action.shape)}")
        batch = torch.broadcast_shapes(observation.shape[:-2], action.shape[:-2])
        state = observation.expand(*batch, n, obs_dim).flatten(-2)  # [*, n * obs]
        state = state.unsqueeze(-2).expand(*batch, n, n * obs_dim)
        eye = torch.eye(n, dtype=observation.dtype, device=observation.device)
        others = action.to(observation.dtype).expand(*batch, n, n_act)
        others = others.unsqueeze(-3) * (1 - eye).unsqueeze(-1)  # [*, n(a), n, A]
        agent_id = eye.expand(*batch, n, n)
        return self.mlp(torch.cat([state, others.flatten(-2), agent_id], dim=-1))


class COMALoss(CheckedReads, LossModule):
    """COMA actor and critic losses.

    Critic: ``Q(s, u)_a`` (read at agent ``a``'s taken action) regresses onto the TD(lambda)
    return of the team reward ``r = sum_a r_a`` bootstrapped with the target critic at
    ``(s', u')``, ``u' ~ pi(. | s')`` drawn from the current policy (see :meth:`value_targets`;
    targets are computed once per collected trajectory batch, as in the paper).
    Actor: ``loss_actor = -mean_a log pi^a(u^a) A^a`` with the counterfactual advantage
    (:func:`counterfactual_advantage`, no gradient through the critic), minus
    ``entropy_coeff`` times the mean policy entropy. Means are over alive agents when the
    ``mask`` key is present.

    Args:
        actor_network: stochastic policy writing ``logits [*, n, A]`` (and, when collecting,
            the one-hot ``action``), e.g. :func:`mapets_rl.modules.make_stochastic_policy`.
        critic_network: a :class:`COMACritic` wrapped so that it reads ``observation`` and
            ``action`` and writes ``action_value [*, n, A]``.
        gamma: discount in ``[0, 1]``; lmbda: TD(lambda) parameter in ``[0, 1]``.
        entropy_coeff: entropy bonus weight (``>= 0``).
        reward_scale: multiplies the team reward in the critic target (``> 0``).
        loss_function: ``"l2"``, ``"l1"`` or ``"smooth_l1"`` for the critic loss.

    Keys (``set_keys``): ``observation [*, n, obs]``, ``action [*, n, A]`` one-hot, ``logits
    [*, n, A]``, ``action_value [*, n, A]``, ``reward`` ``("next", reward) [*, n, 1]``,
    ``done`` / ``terminated`` ``("next", ·) [*, 1]``, ``mask [*, n]`` (optional),
    ``value_target [*, n]`` (written by :meth:`value_targets`).
    """

    @dataclass
    class _AcceptedKeys:
        """Configurable tensordict keys (see the class docstring for shapes).

        Attributes:
            observation: per-agent observation. Defaults to ``("agents", "observation")``.
            action: one-hot joint action. Defaults to ``("agents", "action")``.
            logits: policy logits. Defaults to ``("agents", "logits")``.
            action_value: critic output. Defaults to ``("agents", "action_value")``.
            reward: per-agent reward under ``"next"``. Defaults to ``("agents", "reward")``.
            done: episode end under ``"next"``. Defaults to ``"done"``.
            terminated: episode termination under ``"next"``. Defaults to ``"terminated"``.
            mask: alive agents. Defaults to ``("agents", "mask")``.
            value_target: critic target. Defaults to ``("agents", "coma_target")``.
        """

        observation: NestedKey = ("agents", "observation")
        action: NestedKey = ("agents", "action")
        logits: NestedKey = ("agents", "logits")
        action_value: NestedKey = ("agents", "action_value")
        reward: NestedKey = ("agents", "reward")
        done: NestedKey = "done"
        terminated: NestedKey = "terminated"
        mask: NestedKey = ("agents", "mask")
        value_target: NestedKey = ("agents", "coma_target")

    tensor_keys: _AcceptedKeys
    default_keys = _AcceptedKeys
    default_value_estimator = None
    out_keys = ["loss_actor", "loss_value", "loss_entropy", "advantage", "pred_value"]

    actor_network: TensorDictModule
    critic_network: TensorDictModule
    actor_network_params: TensorDictParams
    critic_network_params: TensorDictParams
    target_actor_network_params: None
    target_critic_network_params: TensorDictParams

    def __init__(
        self,
        actor_network: TensorDictModule,
        critic_network: TensorDictModule,
        *,
        gamma: float = 0.99,
        lmbda: float = 0.8,
        entropy_coeff: float = 0.01,
        reward_scale: float = 1.0,
        loss_function: str = "l2",
    ) -> None:
        if not 0.0 <= gamma <= 1.0:
            raise ValueError(f"gamma must be in [0, 1], got {gamma}")
        if not 0.0 <= lmbda <= 1.0:
            raise ValueError(f"lmbda must be in [0, 1], got {lmbda}")
        entropy_coeff = finite_number("entropy_coeff", entropy_coeff, minimum=0)
        reward_scale = finite_number("reward_scale", reward_scale, minimum=0, strict=True)
        if loss_function not in ("l2", "l1", "smooth_l1"):
            raise ValueError(
                f"loss_function must be 'l2', 'l1' or 'smooth_l1', got {loss_function!r}"
            )
        super().__init__()
        self.gamma = gamma
        self.lmbda = lmbda
        self.entropy_coeff = entropy_coeff
        self.reward_scale = reward_scale
        self.loss_function = loss_function
        self.convert_to_functional(actor_network, "actor_network", create_target_params=False)
        self.convert_to_functional(critic_network, "critic_network", create_target_params=True)

    @property
    def in_keys(self) -> list[NestedKey]:
        keys = self.tensor_keys
        return [
            keys.observation,
            keys.action,
            ("next", keys.observation),
            ("next", keys.reward),
            ("next", keys.done),
            ("next", keys.terminated),
        ]

    def _forward_value_estimator_keys(self, **kwargs) -> None:
        """The TD(lambda) target is built into the loss; there is no value estimator."""

    def _logits(self, observation: torch.Tensor) -> torch.Tensor:
        keys = self.tensor_keys
        td = TensorDict({keys.observation: observation}, batch_size=observation.shape[:-2])
        with self.actor_network_params.to_module(self.actor_network, preserve_module_state=False):
            td = self.actor_network(td)
        return td.get(keys.logits)

    def _q_values(
        self, params: TensorDictBase, observation: torch.Tensor, action: torch.Tensor
    ) -> torch.Tensor:
        keys = self.tensor_keys
        td = TensorDict(
            {keys.observation: observation, keys.action: action},
            batch_size=observation.shape[:-2],
        )
        with params.to_module(self.critic_network, preserve_module_state=False):
            td = self.critic_network(td)
        return td.get(keys.action_value)

    @torch.no_grad()
    def value_targets(self, tensordict: TensorDictBase) -> TensorDictBase:
        """Writes the TD(lambda) critic targets ``value_target [*, T, n]``.

        The last batch dimension of ``tensordict`` is time (a collected trajectory batch, split
        at ``("next", done)``). The bootstrap at ``s'`` is the target critic at a joint action
        drawn from the current policy, read at each agent's drawn action.
        """
        keys = self.tensor_keys
        next_obs = self._get(tensordict, ("next", keys.observation), "[*, T, n, obs]")
        reward = self._get(tensordict, ("next", keys.reward), "[*, T, n, 1]")
        done = self._flags(tensordict, ("next", keys.done), "[*, T, 1]")
        terminated = self._flags(tensordict, ("next", keys.terminated), "[*, T, 1]")
        names = (repr(unravel_key(("next", key))) for key in (keys.observation, keys.reward))
        check_finite_many(dict(zip(names, (next_obs, reward), strict=True)), agent_dim=-2)
        logits = self._logits(next_obs)
        next_action = torch.distributions.OneHotCategorical(logits=logits).sample()
        q_next = self._q_values(self.target_critic_network_params, next_obs, next_action)
        next_value = (q_next * next_action).sum(-1)  # [*, T, n]
        reward = reward.to(next_value.dtype)
        team = reward.reshape(next_value.shape).sum(-1, keepdim=True) * self.reward_scale
        done = done.reshape(*next_value.shape[:-1], 1)
        terminated = terminated.reshape(*next_value.shape[:-1], 1)
        target = td_lambda_return_estimate(
            self.gamma,
            self.lmbda,
            next_value,
            team.expand_as(next_value),
            done.expand_as(next_value),
            terminated.expand_as(next_value),
            time_dim=-2,
        )
        tensordict.set(keys.value_target, target)
        return tensordict

    def _masked_mean(self, value: torch.Tensor, mask: torch.Tensor | None) -> torch.Tensor:
        if mask is None:
            return value.mean()
        weight = mask.reshape(value.shape).to(value.dtype)
        return (value * weight).sum() / weight.sum().clamp_min(1.0)

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        """``tensordict [*B]`` -> TensorDict of scalar ``loss_actor``, ``loss_value``,
        ``loss_entropy`` and detached diagnostics. Without ``value_target`` the targets are
        computed first (the last batch dimension must then be time)."""
        keys = self.tensor_keys
        if keys.value_target not in tensordict.keys(include_nested=True):
            tensordict = self.value_targets(tensordict.copy())
        obs = self._get(tensordict, keys.observation, "[*, n, obs]")
        action = self._get(tensordict, keys.action, "[*, n, A] one-hot").to(obs.dtype)
        mask = tensordict.get(keys.mask, None)
        if mask is not None:
            mask = as_mask(repr(keys.mask), mask, "[*, n]")
        target = self._get(tensordict, keys.value_target, "[*, n]")
        check_finite_many({repr(keys.observation): obs, repr(keys.value_target): target})

        q_values = self._q_values(self.critic_network_params, obs, action)  # [*, n, A]
        logits = self._logits(obs)
        log_probs = logits.log_softmax(-1)
        probs = log_probs.exp()
        advantage, _, _ = counterfactual_advantage(q_values.detach(), probs.detach(), action)
        q_taken = (q_values * action).sum(-1)  # [*, n], with gradient to the critic
        loss_value = self._masked_mean(
            distance_loss(q_taken, target.to(q_taken.dtype), self.loss_function), mask
        )
        log_prob_taken = (log_probs * action).sum(-1)
        loss_actor = -self._masked_mean(log_prob_taken * advantage, mask)
        entropy = -(probs * log_probs).sum(-1)
        loss_entropy = -self.entropy_coeff * self._masked_mean(entropy, mask)
        return TensorDict(
            {
                "loss_actor": loss_actor,
                "loss_value": loss_value,
                "loss_entropy": loss_entropy,
                "advantage": self._masked_mean(advantage, mask).detach(),
                "pred_value": q_taken.detach().mean(),
            },
            batch_size=[],
        )
