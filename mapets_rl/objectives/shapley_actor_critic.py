"""Shapley-value reward reallocation actor-critic loss (Han et al., Algorithm 1)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from tensordict import TensorDict, TensorDictBase, TensorDictParams
from tensordict.nn import TensorDictModule
from tensordict.utils import NestedKey
from torchrl.objectives import LossModule
from torchrl.objectives.utils import distance_loss

from mapets_rl.modules.arguments import finite_number
from mapets_rl.modules.heads import gumbel_one_hot, one_hot_argmax
from mapets_rl.modules.tensor_checks import as_mask, check_finite_many, check_real, get_tensor
from mapets_rl.shapley.critic import CoalitionCritic
from mapets_rl.shapley.game import (
    coalition_masks,
    permutation_prefix_masks,
    sample_permutations,
    shapley_matrix,
)

__all__ = ["ShapleyActorCriticLoss"]


def _as_tuple(key: NestedKey) -> tuple[str, ...]:
    return (key,) if isinstance(key, str) else tuple(key)


class ShapleyActorCriticLoss(LossModule):
    """Characteristic-function TD loss + Shapley deterministic policy gradient.

    Critic (Algorithm 1 lines 10-11): ``v(s, a, C)`` regresses onto
    ``y = R(C) + gamma * v'(s', a', C')`` with ``R(C) = sum_{i in C} r_i`` (paper eq. 10 and
    Proposition 2), ``a' = pi'(s'^C)`` from the target actors, ``v'`` the target critic and
    ``C' = C`` minus the agents terminated at ``s'`` (a terminated agent earns no future reward;
    ``v(empty) = 0``). Target parameters are refreshed with ``torchrl.objectives.SoftUpdate``.

    With a critic built with ``member_heads`` (``v(C) = sum_{j in C} q_j``), each member's term
    regresses onto its own ``r_j + gamma * q'_j(s', a', C')`` (zero outside ``C``, and for
    members terminated at ``s'``): the same targets summed over ``C``, with the members'
    rewards kept apart instead of pooled.

    Actor (lines 12-13): ``loss_actor = -mean_i phi_i(s, a)`` where ``phi_i`` is the Shapley value
    (eq. 3) of the critic's game at the sampled state, with ``a_i = pi_i(s^C)`` and the other
    agents' actions taken from the batch. The gradient reaches agent ``i``'s policy only through
    ``a_i`` in ``phi_i``: coalitions without ``i`` do not depend on ``a_i`` (its inputs are zeroed)
    and are evaluated without gradient, coalitions with ``i`` are evaluated with agent ``i``'s own
    action substituted, ``n`` joint actions per state in one batched critic call. Discrete actions
    are relaxed with straight-through Gumbel-softmax.

    ``phi`` is exact for ``n <= exact_max_agents`` (``n * 2**(n-1) + 2**n`` coalition values per
    state) and otherwise a permutation estimate with ``num_permutations`` antithetic orderings
    shared by the whole minibatch (``2 * n * num_permutations`` values per state); the actor
    loss then reports the estimate's standard error (``shapley_stderr``, over the antithetic
    pair means). Both paths share the critic's first layer between the with-``i`` and
    without-``i`` coalitions, evaluate the states in chunks of ``chunk_states`` and take the
    actor gradient chunk by chunk, so the ``[states, n, K, H]`` intermediates are never held
    for a backward pass.

    Args:
        actor_network: deterministic per-agent policy reading the observation and coalition keys
            and writing ``logits`` (discrete) or ``action`` (continuous), e.g.
            :func:`mapets_rl.shapley.make_coalition_actor`.
        critic_network: a :class:`~mapets_rl.shapley.CoalitionCritic`.
        action_space: ``"discrete"`` (one-hot actions) or ``"continuous"``.
        gamma: discount in ``[0, 1]``.
        exact_max_agents: largest ``n`` computed exactly (``1..20``, default 10).
        num_permutations: orderings per update on the sampled path (even, ``>= 4``: at least
            two antithetic pairs for the standard error).
        gumbel_temperature: Gumbel-softmax temperature (``> 0``).
        logits_reg: weight of the mean squared actor logits added to the actor loss (discrete;
            ``>= 0``). As in the original MADDPG code, it keeps the logits from saturating, where
            the softmax gradient vanishes and a deterministic policy stops exploring.
        loss_function: ``"l2"``, ``"l1"`` or ``"smooth_l1"`` for the TD loss.
        delay_actor, delay_value: keep target copies of the actor / critic parameters.
        chunk_states: states per pass of the Shapley computation (``None``: all at once); the
            result does not depend on it, the memory traffic does.
        reward_scale: multiplies ``R(C)`` in the critic target (``> 0``): the characteristic
            function, and so ``phi``, is learnt in units of ``reward_scale`` rewards.
        value_states: on the sampled path, the states of a minibatch (the first ones) whose
            Shapley values the actor loss computes in full, for its reported value and the
            logged ``shapley_value`` / ``shapley_stderr`` (``None``: all). The actor's gradient
            uses every state either way: it does not depend on the coalitions without the
            agent (their values are the baseline ``E[v(P)]`` of ``phi_i``), so their critic
            passes are skipped beyond these states. ``shapley_values`` always computes all.
        autocast_bf16: evaluate the critic's hidden layers for the Shapley value under bf16
            autocast (fast where the CPU has AVX512-BF16/AMX or on a GPU; slower on AVX2-only
            CPUs). Error: see ``benchmarks/shapley.py``.

    Keys (``set_keys``): ``observation`` ``[*, n, obs]``, ``action`` ``[*, n, act]``, ``logits``
    ``[*, n, act]`` (actor output, discrete), ``coalition`` ``[*, n]`` bool, ``reward``
    ``("next", reward) [*, n, 1]``, ``terminated`` ``("next", terminated) [*, n, 1]`` or
    ``[*, 1]``, optional ``mask`` ``[*, n]`` (alive agents).
    """

    @dataclass
    class _AcceptedKeys:
        """Configurable tensordict keys (see class docstring for shapes).

        Attributes:
            observation: per-agent observations. Defaults to ``("agents", "observation")``.
            action: per-agent actions (one-hot if discrete). Defaults to ``("agents", "action")``.
            logits: actor logits for discrete actions. Defaults to ``("agents", "logits")``.
            coalition: coalition membership mask. Defaults to ``("agents", "coalition")``.
            reward: per-agent reward, read under ``"next"``. Defaults to ``("agents", "reward")``.
            terminated: termination flag, read under ``"next"``. Defaults to
                ``("agents", "terminated")``.
            mask: optional alive mask ``[*, n]``; when present, the actor loss averages
                ``phi_i`` over alive agents only. Defaults to ``("agents", "mask")``.
        """

        observation: NestedKey = ("agents", "observation")
        action: NestedKey = ("agents", "action")
        logits: NestedKey = ("agents", "logits")
        coalition: NestedKey = ("agents", "coalition")
        reward: NestedKey = ("agents", "reward")
        terminated: NestedKey = ("agents", "terminated")
        mask: NestedKey = ("agents", "mask")

    tensor_keys: _AcceptedKeys
    default_keys = _AcceptedKeys
    default_value_estimator = None
    out_keys = [
        "loss_actor",
        "loss_value",
        "pred_value",
        "target_value",
        "td_error",
        "shapley_value",
        "shapley_stderr",
    ]

    actor_network: TensorDictModule
    critic_network: CoalitionCritic
    actor_network_params: TensorDictParams
    critic_network_params: TensorDictParams
    target_actor_network_params: TensorDictParams
    target_critic_network_params: TensorDictParams

    def __init__(
        self,
        actor_network: TensorDictModule,
        critic_network: CoalitionCritic,
        *,
        action_space: str = "discrete",
        gamma: float = 0.99,
        exact_max_agents: int = 10,
        num_permutations: int = 32,
        gumbel_temperature: float = 1.0,
        logits_reg: float = 1e-3,
        loss_function: str = "l2",
        delay_actor: bool = True,
        delay_value: bool = True,
        chunk_states: int | None = None,
        autocast_bf16: bool = False,
        reward_scale: float = 1.0,
        value_states: int | None = None,
    ) -> None:
        if not isinstance(critic_network, CoalitionCritic):
            raise ValueError(
                f"critic_network must be a CoalitionCritic, got {type(critic_network).__name__}"
            )
        if action_space not in ("discrete", "continuous"):
            raise ValueError(
                f"action_space must be 'discrete' or 'continuous', got {action_space!r}"
            )
        if not 0.0 <= gamma <= 1.0:
            raise ValueError(f"gamma must be in [0, 1], got {gamma}")
        if not isinstance(exact_max_agents, int) or not 1 <= exact_max_agents <= 20:
            raise ValueError(f"exact_max_agents must be an int in [1, 20], got {exact_max_agents}")
        if not isinstance(num_permutations, int) or num_permutations < 4 or num_permutations % 2:
            raise ValueError(f"num_permutations must be an even int >= 4, got {num_permutations!r}")
        if chunk_states is not None and (
            isinstance(chunk_states, bool) or not isinstance(chunk_states, int) or chunk_states < 1
        ):
            raise ValueError(f"chunk_states must be None or an int >= 1, got {chunk_states!r}")
        if value_states is not None and (
            isinstance(value_states, bool) or not isinstance(value_states, int) or value_states < 1
        ):
            raise ValueError(f"value_states must be None or an int >= 1, got {value_states!r}")
        gumbel_temperature = finite_number(
            "gumbel_temperature", gumbel_temperature, minimum=0, strict=True
        )
        reward_scale = finite_number("reward_scale", reward_scale, minimum=0, strict=True)
        logits_reg = finite_number("logits_reg", logits_reg, minimum=0)
        if loss_function not in ("l2", "l1", "smooth_l1"):
            raise ValueError(
                f"loss_function must be 'l2', 'l1' or 'smooth_l1', got {loss_function!r}"
            )
        super().__init__()
        self.n_agents = critic_network.n_agents
        self.action_space = action_space
        self.gamma = gamma
        self.exact_max_agents = exact_max_agents
        self.num_permutations = num_permutations
        self.gumbel_temperature = gumbel_temperature
        self.logits_reg = logits_reg
        self.loss_function = loss_function
        self.delay_actor = delay_actor
        self.delay_value = delay_value
        self.chunk_states = chunk_states
        self.value_states = value_states
        self.autocast_bf16 = bool(autocast_bf16)
        self.reward_scale = reward_scale
        self.convert_to_functional(actor_network, "actor_network", create_target_params=delay_actor)
        self.convert_to_functional(
            critic_network, "critic_network", create_target_params=delay_value
        )
        n = self.n_agents
        if n <= exact_max_agents:
            # Coalitions containing each agent i, [n, 2**(n-1), n], and their eq. 3 weights.
            masks = coalition_masks(n)
            m = shapley_matrix(n, dtype=torch.float32)
            with_i = masks.T.nonzero()[:, 1].view(n, 2 ** (n - 1))  # coalition ids with bit i
            self.register_buffer("_masks_with", masks[with_i], persistent=False)
            self.register_buffer("_weights_with", m.T.gather(1, with_i), persistent=False)
            self.register_buffer("_m_without", m.clamp(max=0.0), persistent=False)
            self.register_buffer("_masks_all", masks, persistent=False)

    @property
    def in_keys(self) -> list[NestedKey]:
        keys = self.tensor_keys
        return [
            keys.observation,
            keys.action,
            keys.coalition,
            ("next", keys.observation),
            ("next", keys.reward),
            ("next", keys.terminated),
        ]

    def _forward_value_estimator_keys(self, **kwargs) -> None:
        """The coalition TD target is computed in place; there is no value estimator to update."""

    def make_value_estimator(self, value_type=None, **hyperparams) -> ShapleyActorCriticLoss:
        """Only ``gamma`` can be set: the TD(0) coalition target is built into the loss."""
        if value_type is not None:
            raise ValueError(
                "value_type must be None: ShapleyActorCriticLoss uses its own TD(0) target "
                "y = R(C) + gamma * v'(s', a', C')"
            )
        unknown = set(hyperparams) - {"gamma"}
        if unknown:
            raise ValueError(f"hyperparams may only contain 'gamma', got {sorted(unknown)}")
        if "gamma" in hyperparams:
            gamma = float(hyperparams["gamma"])
            if not 0.0 <= gamma <= 1.0:
                raise ValueError(f"gamma must be in [0, 1], got {gamma}")
            self.gamma = gamma
        return self

    def _inputs(self, tensordict: TensorDictBase, *, target: bool) -> dict[str, torch.Tensor]:
        """The loss's inputs, checked once per call: present, real (float/int) and finite,
        ``coalition`` (and ``terminated``) bool or 0/1, shapes as in the class docstring.
        ``target``: also the ``"next"`` entries of the TD target. One host sync."""
        keys, n, owner = self.tensor_keys, self.n_agents, type(self).__name__
        obs = get_tensor(tensordict, keys.observation, f"[*, n_agents={n}, obs]", owner)
        check_real(repr(keys.observation), obs, f"[*, n_agents={n}, obs]")
        if obs.ndim < 2 or obs.shape[-2] != n:
            raise ValueError(
                f"observation must have shape [*, n_agents={n}, obs], got {tuple(obs.shape)}"
            )
        coalition = get_tensor(tensordict, keys.coalition, f"[*, n_agents={n}] bool", owner)
        if coalition.shape[-1:] != (n,):
            raise ValueError(
                f"coalition must have shape [*, n_agents={n}], got {tuple(coalition.shape)}"
            )
        lead = list(coalition.shape)
        out = {
            "observation": obs,
            "coalition": as_mask(repr(keys.coalition), coalition, f"{lead}"),
            "action": get_tensor(tensordict, keys.action, f"[*, n_agents={n}, act]", owner),
        }
        if target:
            next_obs = ("next", *_as_tuple(keys.observation))
            reward = ("next", *_as_tuple(keys.reward))
            terminated = ("next", *_as_tuple(keys.terminated))
            out["next_observation"] = get_tensor(
                tensordict, next_obs, f"[*, n_agents={n}, obs]", owner
            )
            out["reward"] = get_tensor(tensordict, reward, f"{[*lead, 1]}", owner)
            if tuple(out["reward"].shape) not in (tuple(lead), (*lead, 1)):
                raise ValueError(
                    f"{reward!r} must have shape {[*lead, 1]}, got {list(out['reward'].shape)}"
                )
            flags = get_tensor(tensordict, terminated, f"{[*lead, 1]} or {[*lead[:-1], 1]}", owner)
            out["terminated"] = as_mask(repr(terminated), flags, f"{[*lead, 1]}")
        names = {"observation": keys.observation, "action": keys.action}
        if target:
            names.update(next_observation=next_obs, reward=reward)
            for name in ("next_observation", "reward"):  # actions may be one-hot bools
                check_real(repr(names[name]), out[name])
        check_finite_many({repr(key): out[name] for name, key in names.items()})
        return out

    def policy_action(
        self, params: TensorDictBase, obs: torch.Tensor, coalition: torch.Tensor, greedy: bool
    ) -> tuple[torch.Tensor, torch.Tensor | None]:
        """``pi(s^C)`` under ``params``: action ``[*, n, act]`` (one-hot if discrete) and the
        logits (``None`` if continuous)."""
        keys = self.tensor_keys
        td = TensorDict(
            {keys.observation: obs, keys.coalition: coalition}, batch_size=obs.shape[:-2]
        )
        with params.to_module(self.actor_network, preserve_module_state=False):
            td = self.actor_network(td)
        if self.action_space == "continuous":
            return td.get(keys.action), None
        logits = td.get(keys.logits)
        if greedy:
            return one_hot_argmax(logits), logits
        return gumbel_one_hot(logits, self.gumbel_temperature), logits

    def loss_value(self, tensordict: TensorDictBase) -> tuple[torch.Tensor, dict]:
        """TD loss of the characteristic function (Algorithm 1 lines 10-11)."""
        inputs = self._inputs(tensordict, target=True)
        obs, coalition = inputs["observation"], inputs["coalition"]
        action = inputs["action"].to(obs.dtype)
        # member heads: one TD target per member, r_j + gamma q'_j (zero outside C); their sum
        # is the paper's target for v(C)
        per_member = self.critic_network.member_heads
        with self.critic_network_params.to_module(self.critic_network, preserve_module_state=False):
            pred = self.critic_network.coalition_values(
                obs, action, coalition.unsqueeze(-2), per_member=per_member
            )
        pred = pred.squeeze(-2) if per_member else pred.squeeze(-1)  # [*, n] or [*]
        with torch.no_grad():
            next_obs = inputs["next_observation"]
            reward = inputs["reward"].reshape(*coalition.shape)
            terminated = inputs["terminated"]
            terminated = terminated.reshape(*terminated.shape[: coalition.ndim - 1], -1)
            next_coalition = coalition & ~terminated.expand_as(coalition)
            member_reward = reward * coalition.to(reward.dtype) * self.reward_scale  # [*, n]
            # R(C), eq. 10
            coalition_reward = member_reward if per_member else member_reward.sum(-1)
            next_action, _ = self.policy_action(
                self.target_actor_network_params, next_obs, coalition, greedy=True
            )
            with self.target_critic_network_params.to_module(
                self.critic_network, preserve_module_state=False
            ):
                next_value = self.critic_network.coalition_values(
                    next_obs, next_action, next_coalition.unsqueeze(-2), per_member=per_member
                )
            next_value = next_value.squeeze(-2) if per_member else next_value.squeeze(-1)
            target = coalition_reward.to(pred.dtype) + self.gamma * next_value
        loss = distance_loss(pred, target, loss_function=self.loss_function)
        if per_member:  # outside C both are zero; sum the members' terms per sample
            pred, target, loss = pred.sum(-1), target.sum(-1), loss.sum(-1)
        loss = loss.mean()
        td_error = (pred - target).detach().pow(2)
        meta = {
            "pred_value": pred.detach().mean(),
            "target_value": target.mean(),
            "td_error": td_error.mean(),
        }
        return loss, meta

    def shapley_values(
        self, tensordict: TensorDictBase, *, return_stderr: bool = False
    ) -> torch.Tensor | tuple[torch.Tensor, torch.Tensor]:
        """``phi_i(s, a)`` with ``a_i = pi_i(s^C)``, differentiable through ``a_i`` only.

        Returns ``[*, n]`` (and, with ``return_stderr``, its standard error ``[*, n]``: zero on
        the exact path, over the antithetic pair means on the sampled path). Gradients reach
        the actor parameters, not the critic's.
        """
        phi, stderr, _, _ = self._shapley_and_logits(tensordict, None)
        return (phi, stderr) if return_stderr else phi

    def _shapley_and_logits(
        self, tensordict: TensorDictBase, value_states: int | None
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None, int]:
        """``(phi [*, n], stderr [*, n], logits, valued)``: ``phi`` and ``stderr`` hold the
        Shapley values of the first ``valued`` (flattened) states, at least ``value_states``
        (:meth:`_shapley_from_embeddings`); ``stderr`` is zero on the exact path."""
        inputs = self._inputs(tensordict, target=False)
        obs, coalition = inputs["observation"], inputs["coalition"]
        a_batch = inputs["action"].to(obs.dtype)
        a_pol, logits = self.policy_action(self.actor_network_params, obs, coalition, greedy=False)
        critic = self.critic_network
        with self.critic_network_params.detach().to_module(critic, preserve_module_state=False):
            # First-layer factorisation: a coalition's pre-activation is masks @ h + bias, and
            # substituting agent i's own action adds delta_i = h_i(a_pol) - h_i(a_batch) to the
            # coalitions that contain i. Only delta carries the actor's gradient.
            with torch.no_grad():
                h_batch = critic.embed(obs, a_batch)  # [*, n, H]
            delta = critic.embed(obs, a_pol) - h_batch  # [*, n, H]
            lead = h_batch.shape[:-2]
            phi, stderr, valued = self._shapley_from_embeddings(
                critic,
                h_batch.reshape(-1, *h_batch.shape[-2:]),
                delta.reshape(-1, *delta.shape[-2:]),
                value_states,
            )
        return phi.reshape(*lead, -1), stderr.reshape(*lead, -1), logits, valued

    def _shapley_from_embeddings(
        self,
        critic: CoalitionCritic,
        h_batch: torch.Tensor,
        delta: torch.Tensor,
        value_states: int | None,
    ) -> tuple[torch.Tensor, torch.Tensor, int]:
        """``h_batch, delta [S, n, H] -> (phi, stderr [S, n], valued)``, chunked over the
        ``S`` states.

        On the sampled path with ``value_states``, only the chunks that hold the first
        ``value_states`` states (``valued`` states, whole chunks) evaluate the coalitions
        without ``i``; the rest return ``mean_P v(P + i)`` in place of ``phi_i`` (the same
        gradient: the dropped ``mean_P v(P)`` does not depend on the actor) and NaN errors.

        The heavy part runs without building a graph over the actor: per chunk, the gradient
        ``g_i = d phi_i / d delta_i`` (``phi_i`` depends on ``delta_i`` only) is taken at once
        and ``phi_i`` is returned as ``phi_i + <delta_i - stop_grad(delta_i), g_i>``, whose value
        is ``phi_i`` and whose gradient with respect to the actor is exactly that of ``phi_i``.
        """
        n = self.n_agents
        exact = n <= self.exact_max_agents
        if exact:
            masks = self._masks_with.to(h_batch.dtype)  # [n, K, n]
            weights = self._weights_with.to(h_batch.dtype)  # [n, K]
            masks_with = masks
        else:
            # one set of orderings for the whole minibatch (antithetic pairs: rows 2q, 2q+1)
            perms = sample_permutations(
                self.num_permutations, n, antithetic=True, device=h_batch.device
            )
            before = permutation_prefix_masks(perms).transpose(0, 1)  # [n, P, n]
            masks = before.to(h_batch.dtype)
            own_bit = torch.eye(n, dtype=torch.bool, device=before.device).unsqueeze(-2)
            masks_with = before | own_bit  # [n, P, n]: the prefix before i, plus i
        need_grad = torch.is_grad_enabled() and delta.requires_grad
        size = h_batch.shape[0] if self.chunk_states is None else self.chunk_states
        states = h_batch.shape[0]
        wanted = states if exact or value_states is None else min(value_states, states)
        valued = min(-(-wanted // size) * size, states)
        autocast = dict(
            device_type=h_batch.device.type,
            dtype=torch.bfloat16,
            enabled=self.autocast_bf16,
        )

        def head(z: torch.Tensor, members: torch.Tensor) -> torch.Tensor:
            with torch.autocast(**autocast):
                return critic.head_values(z, members).to(h_batch.dtype)

        phis, grads, stderrs = [], [], []
        for start in range(0, h_batch.shape[0], size):
            hb = h_batch[start : start + size]
            d = delta[start : start + size].detach().requires_grad_(need_grad)
            with torch.no_grad():  # one [n K, n] @ [n, H] product per state: hb is not copied
                flat = masks.flatten(0, 1) @ hb  # [S_c, n K, H]
                base = flat.unflatten(-2, masks.shape[:2]) + critic.bias  # [S_c, n, K, H]
            with torch.enable_grad() if need_grad else torch.no_grad():
                # exact: the coalitions already hold h_i(a_batch), add delta_i; sampled: the
                # prefixes before i do not hold i, add h_i(a_pol) = h_i(a_batch) + delta_i
                own = d if exact else hb + d
                v_with = head(base + own.unsqueeze(-2), masks_with)  # [S_c, n, K]: with i
                if exact:
                    phi_with = (v_with * weights).sum(-1)
                else:
                    phi_with = v_with.mean(-1)
            if need_grad:
                grads.append(torch.autograd.grad(phi_with.sum(), d)[0])
            with torch.no_grad():
                if exact:
                    v_all = critic.values_from_embedding(hb, self._masks_all)  # [S_c, 2**n]
                    phis.append(phi_with.detach() + v_all @ self._m_without.to(v_all.dtype))
                    stderrs.append(torch.zeros_like(phi_with))
                elif start < valued:
                    marginal = v_with.detach() - head(base, before)  # [S_c, n, P]
                    pairs = marginal.unflatten(-1, (-1, 2)).mean(-1)  # [S_c, n, P/2]
                    phis.append(pairs.mean(-1))
                    stderrs.append(pairs.std(-1, correction=1) / math.sqrt(pairs.shape[-1]))
                else:
                    phis.append(phi_with.detach())
                    stderrs.append(torch.full_like(phi_with, math.nan))
        phi, stderr = torch.cat(phis), torch.cat(stderrs)
        if need_grad:
            grad = torch.cat(grads)
            phi = phi + ((delta - delta.detach()) * grad).sum(-1)
        return phi, stderr, valued

    def loss_actor(self, tensordict: TensorDictBase) -> tuple[torch.Tensor, dict]:
        """Shapley deterministic policy gradient (Algorithm 1 lines 12-13), plus
        ``logits_reg * mean(logits**2)`` for discrete actions."""
        phi, stderr, logits, valued = self._shapley_and_logits(tensordict, self.value_states)
        mask = tensordict.get(self.tensor_keys.mask, None)
        if mask is None:
            weight = torch.ones_like(phi)
        else:
            if mask.numel() != phi.numel():
                raise ValueError(
                    f"{self.tensor_keys.mask!r} must have shape {list(phi.shape)}, "
                    f"got {list(mask.shape)}"
                )
            mask = as_mask(repr(self.tensor_keys.mask), mask, f"{list(phi.shape)}")
            weight = mask.reshape(phi.shape).to(phi.dtype)
        n = self.n_agents
        phi_flat, weight_flat = phi.reshape(-1, n), weight.reshape(-1, n)

        def weighted_mean(values: torch.Tensor, weights: torch.Tensor) -> torch.Tensor:
            return (values * weights).sum() / weights.sum().clamp_min(1.0)

        surrogate = -weighted_mean(phi_flat, weight_flat)  # the gradient of every state
        value = -weighted_mean(phi_flat[:valued], weight_flat[:valued]).detach()
        loss = surrogate - surrogate.detach() + value  # value: the valued states' -mean phi
        if logits is not None and self.logits_reg > 0:
            loss = loss + self.logits_reg * logits.pow(2).mean()
        meta = {"shapley_value": phi_flat[:valued].detach().mean()}
        if n > self.exact_max_agents:
            meta["shapley_stderr"] = stderr.reshape(-1, n)[:valued].mean()
        return loss, meta

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        """``tensordict [*B]`` from the replay buffer -> TensorDict with ``loss_value``,
        ``loss_actor`` and detached diagnostics (scalars)."""
        loss_value, meta = self.loss_value(tensordict)
        loss_actor, meta_actor = self.loss_actor(tensordict)
        return TensorDict(
            {"loss_actor": loss_actor, "loss_value": loss_value, **meta, **meta_actor},
            batch_size=[],
        )
