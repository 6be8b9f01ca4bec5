"""SVMIX's loss (Xiao et al. 2023): a value-decomposition actor-critic whose critic is the mixed
joint value ``V_tot(s) = mix(V_1(o_1), ..., V_I(o_I); graph)`` of
:class:`~mapets_rl.modules.graph_mixer.GraphValueMixer`, trained on the team reward; every
agent's policy is improved with the one team advantage (VDAC-mix's scheme, Su et al. 2021,
read into SVMIX: see :mod:`mapets_rl.recipes.svmix`).

    r_t       = reward_scale * sum_i r_t^i                                   (team reward)
    A_t       = GAE_{gamma, lambda}(r, V_tot)          (Schulman et al. 2016, eq. 16)
    G_t       = A_t + V_tot(s_t)                                             (value target)
    loss_critic    = critic_coeff * mean_t (V_tot(s_t) - G_t)^2
    loss_objective = -mean_{t, i alive} min(rho_t^i A_t, clip(rho_t^i, 1 +- eps) A_t),
                     rho_t^i = pi_i(a_t^i | o_t^i) / pi_old_i(a_t^i | o_t^i)
    loss_entropy   = -entropy_coeff * mean_{t, i alive} H(pi_i(. | o_t^i))

The targets are computed once per collected batch (:meth:`SVMIXLoss.value_targets`), before
the minibatch passes; the critic's graph (with its link failures) is drawn again at each call
of the critic.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from tensordict import TensorDict, TensorDictBase, TensorDictParams
from tensordict.nn import ProbabilisticTensorDictSequential, TensorDictModule
from tensordict.utils import NestedKey, unravel_key
from torchrl.objectives import LossModule
from torchrl.objectives.utils import distance_loss
from torchrl.objectives.value.functional import generalized_advantage_estimate

from mapets_rl.modules.arguments import finite_number
from mapets_rl.modules.tensor_checks import as_mask, check_finite_many
from mapets_rl.objectives._tensor_reads import CheckedReads

__all__ = ["SVMIXLoss"]


class SVMIXLoss(CheckedReads, LossModule):
    """SVMIX's actor and mixed-critic losses (equations in the module docstring).

    Args:
        actor_network: a stochastic policy (e.g.
            :func:`~mapets_rl.modules.make_stochastic_policy`) whose ``get_dist`` gives
            ``pi_i(. | o_i)`` over the action ``[*, I, act]``.
        critic_network: reads a step's observation, positions and mask and writes the mixed
            joint value ``value [*, 1]`` (the recipe's graph -> per-agent values -> mixer).
        gamma: discount in ``[0, 1]``; lmbda: GAE's lambda in ``[0, 1]``.
        clip_epsilon: the ratio clip ``eps`` (> 0).
        entropy_coeff: entropy bonus weight (>= 0).
        critic_coeff: critic loss weight (> 0).
        reward_scale: multiplies the team reward (> 0).
        normalize_advantage: standardise the advantage over each minibatch.
        loss_function: ``"l2"``, ``"l1"`` or ``"smooth_l1"`` for the critic loss.

    Keys (``set_keys``): ``action [*, I, act]``, ``sample_log_prob [*, I]`` (the collecting
    policy's), ``reward`` ``("next", ·) [*, I, 1]``, ``done`` / ``terminated`` ``("next", ·)
    [*, 1]``, ``mask [*, I]`` (optional: agents still driving), ``value [*, 1]``,
    ``advantage [*, 1]`` and ``value_target [*, 1]`` (written by :meth:`value_targets`).
    """

    @dataclass
    class _AcceptedKeys:
        """Configurable tensordict keys (see the class docstring for shapes).

        Attributes:
            action: per-agent action. Defaults to ``("agents", "action")``.
            sample_log_prob: log-probability of the action under the collecting policy.
                Defaults to ``("agents", "action_log_prob")``.
            reward: per-agent reward under ``"next"``. Defaults to ``("agents", "reward")``.
            done: episode end under ``"next"``. Defaults to ``"done"``.
            terminated: episode termination under ``"next"``. Defaults to ``"terminated"``.
            mask: agents still driving. Defaults to ``("agents", "mask")``.
            value: the mixed joint value. Defaults to ``"joint_value"``.
            advantage: the team advantage. Defaults to ``"advantage"``.
            value_target: the critic's target. Defaults to ``"value_target"``.
        """

        action: NestedKey = ("agents", "action")
        sample_log_prob: NestedKey = ("agents", "action_log_prob")
        reward: NestedKey = ("agents", "reward")
        done: NestedKey = "done"
        terminated: NestedKey = "terminated"
        mask: NestedKey = ("agents", "mask")
        value: NestedKey = "joint_value"
        advantage: NestedKey = "advantage"
        value_target: NestedKey = "value_target"

    tensor_keys: _AcceptedKeys
    default_keys = _AcceptedKeys
    default_value_estimator = None
    out_keys = ["loss_objective", "loss_critic", "loss_entropy", "entropy", "pred_value"]

    actor_network: ProbabilisticTensorDictSequential
    critic_network: TensorDictModule
    actor_network_params: TensorDictParams
    critic_network_params: TensorDictParams
    target_actor_network_params: None
    target_critic_network_params: None

    def __init__(
        self,
        actor_network: ProbabilisticTensorDictSequential,
        critic_network: TensorDictModule,
        *,
        gamma: float = 0.99,
        lmbda: float = 0.95,
        clip_epsilon: float = 0.2,
        entropy_coeff: float = 0.01,
        critic_coeff: float = 1.0,
        reward_scale: float = 1.0,
        normalize_advantage: bool = True,
        loss_function: str = "l2",
    ) -> None:
        if not 0.0 <= gamma <= 1.0:
            raise ValueError(f"gamma must be in [0, 1], got {gamma}")
        if not 0.0 <= lmbda <= 1.0:
            raise ValueError(f"lmbda must be in [0, 1], got {lmbda}")
        clip_epsilon = finite_number("clip_epsilon", clip_epsilon, minimum=0, strict=True)
        entropy_coeff = finite_number("entropy_coeff", entropy_coeff, minimum=0)
        critic_coeff = finite_number("critic_coeff", critic_coeff, minimum=0, strict=True)
        reward_scale = finite_number("reward_scale", reward_scale, minimum=0, strict=True)
        if loss_function not in ("l2", "l1", "smooth_l1"):
            raise ValueError(
                f"loss_function must be 'l2', 'l1' or 'smooth_l1', got {loss_function!r}"
            )
        super().__init__()
        self.gamma = gamma
        self.lmbda = lmbda
        self.clip_epsilon = clip_epsilon
        self.entropy_coeff = entropy_coeff
        self.critic_coeff = critic_coeff
        self.reward_scale = reward_scale
        self.normalize_advantage = bool(normalize_advantage)
        self.loss_function = loss_function
        self.convert_to_functional(actor_network, "actor_network", create_target_params=False)
        self.convert_to_functional(critic_network, "critic_network", create_target_params=False)

    @property
    def in_keys(self) -> list[NestedKey]:
        keys = self.tensor_keys
        return [
            keys.action,
            keys.sample_log_prob,
            ("next", keys.reward),
            ("next", keys.done),
            ("next", keys.terminated),
        ]

    def _forward_value_estimator_keys(self, **kwargs) -> None:
        """GAE is built into the loss (:meth:`value_targets`); there is no value estimator."""

    def joint_value(self, tensordict: TensorDictBase) -> torch.Tensor:
        """The critic's mixed value ``V_tot [*, 1]`` of the steps of ``tensordict [*]`` (its
        graph's link failures drawn anew)."""
        with self.critic_network_params.to_module(self.critic_network, preserve_module_state=False):
            out = self.critic_network(tensordict.copy())
        return out.get(self.tensor_keys.value)

    @torch.no_grad()
    def value_targets(self, tensordict: TensorDictBase) -> TensorDictBase:
        """Writes ``advantage [*, T, 1]`` and ``value_target [*, T, 1]`` (module docstring's
        ``A_t`` and ``G_t``) into ``tensordict [*, T]``, whose last batch dimension is time (a
        collected trajectory batch, split at ``("next", done)``)."""
        keys = self.tensor_keys
        if tensordict.batch_dims < 1:
            raise ValueError("value_targets needs a time dimension: tensordict [*, T]")
        reward = self._get(tensordict, ("next", keys.reward), "[*, T, I, 1]")
        done = self._flags(tensordict, ("next", keys.done), "[*, T, 1]")
        terminated = self._flags(tensordict, ("next", keys.terminated), "[*, T, 1]")
        check_finite_many({repr(unravel_key(("next", keys.reward))): reward})
        value = self.joint_value(tensordict)
        next_value = self.joint_value(tensordict.get("next"))
        batch = tensordict.batch_size
        team = reward.to(value.dtype).reshape(*batch, -1).sum(-1, keepdim=True) * self.reward_scale
        advantage, target = generalized_advantage_estimate(
            self.gamma,
            self.lmbda,
            value,
            next_value,
            team,
            done.reshape(*batch, 1),
            terminated.reshape(*batch, 1),
            time_dim=-2,
        )
        tensordict.set(keys.advantage, advantage)
        tensordict.set(keys.value_target, target)
        return tensordict

    def _masked_mean(self, value: torch.Tensor, mask: torch.Tensor | None) -> torch.Tensor:
        """Mean of ``value [*, I]`` over the agents ``mask [*, I]`` keeps (all without one)."""
        if mask is None:
            return value.mean()
        weight = mask.reshape(value.shape).to(value.dtype)
        return (value * weight).sum() / weight.sum().clamp_min(1.0)

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        """``tensordict [*B]`` -> TensorDict of scalar ``loss_objective``, ``loss_critic``,
        ``loss_entropy`` and the detached ``entropy`` and ``pred_value``. Without
        ``advantage`` the targets are computed first (the last batch dimension must then be
        time)."""
        keys = self.tensor_keys
        if keys.advantage not in tensordict.keys(include_nested=True):
            tensordict = self.value_targets(tensordict.copy())
        action = self._get(tensordict, keys.action, "[*, I, act]")
        old_log_prob = self._get(tensordict, keys.sample_log_prob, "[*, I]")
        advantage = self._get(tensordict, keys.advantage, "[*, 1]")
        target = self._get(tensordict, keys.value_target, "[*, 1]")
        mask = tensordict.get(keys.mask, None)
        if mask is not None:
            mask = as_mask(repr(keys.mask), mask, "[*, I]")
        check_finite_many({repr(keys.advantage): advantage, repr(keys.value_target): target})
        if self.normalize_advantage and advantage.numel() > 1:
            advantage = (advantage - advantage.mean()) / advantage.std().clamp_min(1e-6)

        with self.actor_network_params.to_module(self.actor_network, preserve_module_state=False):
            dist = self.actor_network.get_dist(tensordict.copy())
        log_prob = dist.log_prob(action)  # [*, I]
        ratio = (log_prob - old_log_prob.reshape(log_prob.shape)).exp()
        gain = advantage.reshape(*advantage.shape[:-1], 1).expand_as(ratio)
        clipped = ratio.clamp(1.0 - self.clip_epsilon, 1.0 + self.clip_epsilon)
        loss_objective = -self._masked_mean(torch.minimum(ratio * gain, clipped * gain), mask)
        try:
            entropy = dist.entropy()
        except NotImplementedError:  # TanhNormal: a one-sample estimate, as torchrl's PPO
            entropy = -dist.log_prob(dist.rsample())
        entropy = self._masked_mean(entropy, mask)

        value = self.joint_value(tensordict)
        loss_critic = (
            self.critic_coeff
            * distance_loss(value, target.to(value.dtype), self.loss_function).mean()
        )
        return TensorDict(
            {
                "loss_objective": loss_objective,
                "loss_critic": loss_critic,
                "loss_entropy": -self.entropy_coeff * entropy,
                "entropy": entropy.detach(),
                "pred_value": value.detach().mean(),
            },
            batch_size=[],
        )
