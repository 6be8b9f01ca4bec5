"""M3DDPG's loss (Li et al. 2019, "Robust Multi-Agent Reinforcement Learning via Minimax Deep
Deterministic Policy Gradient"): MADDPG whose critic target and actor objective evaluate agent
``i``'s critic at the worst case of the *other* agents' actions, approximated by one gradient
step on ``Q_i`` (multi-agent adversarial learning, MAAL).

For agent ``i`` at joint action ``a = (a_1, .., a_N)`` the perturbation of agent ``j``'s action is

    delta_ij = -eps * normalize(grad_{a_j} Q_i(x, a))   for j != i,   delta_ii = 0,

``normalize`` being the l2 normalisation over the action features (``tf.nn.l2_normalize`` in
the authors' code; a zero gradient gives a zero step). ``delta_ij`` is a constant (no gradient
flows through it), and agent ``i``'s critic reads ``Q_i(x, a + delta_i)``:

* critic target (``eps = epsilon_critic``):
  ``y_i = r_i + gamma * (1 - d_i) * Q'_i(x', a' + delta'_i)`` with ``a'_j = mu'_j(o'_j)`` the
  target actors' actions and ``delta'_i`` computed on the target critic ``Q'_i``;
* actor (``eps = epsilon_actor``): the loss ``-mean_i Q_i(x, a + delta_i)`` with
  ``a_j = mu_j(o_j)``, differentiated through ``a`` only (the critic's parameters are detached,
  as in ``DDPGLoss``). Like this library's MADDPG (torchrl's ``DDPGLoss``), every agent's action
  is the current policy's, so agent ``j``'s actor also receives ``Q_i``'s gradient at the
  perturbed point; the authors' code instead feeds the replayed actions of the other agents.
  This is the paper's actor gradient (its Eq. for ``grad J`` at ``a_j + delta_j``); the
  authors' released code builds the perturbed ``Q`` for the actor but then minimises the
  unperturbed one, so there only the critic target is minimax. The actor's and the critic's
  ``epsilon`` are separate parameters (the authors' code: ``adv_eps`` in the target,
  ``adv_eps_s`` for teammates in the actor).

Every agent's action is perturbed, crashed CAVs' too (the critic reads them all, as in
MADDPG). Perturbed actions are not clipped to the action bounds (nor one-hot vectors
re-projected), as in the paper.

``epsilon = 0`` is MADDPG exactly (the critic is then called unchanged). Every agent's
perturbation comes from one backward pass: the joint action is replicated once per agent
(``[*, I, I, d]``, replica ``i`` for ``Q_i``), the critic evaluated on all replicas in one
batched call, and ``sum_i Q_i(replica_i)`` differentiated w.r.t. the replicas.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from contextlib import contextmanager

import torch
import torch.nn.functional as F
from tensordict import NestedKey, TensorDictBase
from tensordict.nn import TensorDictModule, TensorDictModuleBase
from torchrl.modules import ActorCriticWrapper

from mapets_rl.modules.arguments import finite_number
from mapets_rl.objectives.ddpg import PreactivationRegularisedDDPGLoss


def minimax_action_perturbation(
    critic: Callable[[torch.Tensor], torch.Tensor], actions: torch.Tensor, epsilon: float
) -> torch.Tensor:
    """One-step worst-case perturbation of the other agents' actions for every agent's critic.

    Args:
        critic: maps replicated joint actions ``[*, I, I, d]`` (``[..., i, j, :]``: agent
            ``j``'s action in the joint action that ``Q_i`` reads) to ``Q_i`` of replica ``i``,
            ``[*, I]``. It must treat the replicas independently (it is differentiated once for
            all of them).
        actions: the joint action ``[*, I, d]``.
        epsilon: step size (>= 0).

    Returns:
        ``delta`` ``[*, I, I, d]``: ``delta[..., i, j, :] = -epsilon * grad_{a_j} Q_i /
        ||grad_{a_j} Q_i||`` for ``j != i`` and ``0`` for ``j == i``; detached.
    """
    epsilon = finite_number("epsilon", epsilon, minimum=0)
    if not bool(torch.isfinite(actions).all()):
        raise ValueError(
            "actions must be finite (no NaN or inf): the perturbation follows Q's gradient at them"
        )
    n = actions.shape[-2]
    with torch.enable_grad():
        replicas = (
            actions.detach().unsqueeze(-3).expand(*actions.shape[:-2], n, *actions.shape[-2:])
        )
        replicas = replicas.clone().requires_grad_(True)
        (grad,) = torch.autograd.grad(critic(replicas).sum(), replicas)
    others = ~torch.eye(n, dtype=torch.bool, device=actions.device)  # [I, I], False on i == j
    return (-epsilon * F.normalize(grad, dim=-1) * others.unsqueeze(-1)).detach()


class MinimaxCritic(TensorDictModuleBase):
    """A critic ``Q_i(x, a)`` that, while :meth:`perturbing` with ``epsilon > 0``, writes
    ``Q_i(x, a + delta_i)`` (:func:`minimax_action_perturbation`) instead of ``Q_i(x, a)``.

    Outside :meth:`perturbing` (or with ``epsilon = 0``) it is ``critic`` unchanged.

    Args:
        critic: the centralised critic; reads the group's ``[*, I, ...]`` entries, among them
            ``action_key`` ``[*, I, d]``, and writes ``value_key`` ``[*, I, 1]``. Its agent
            dimension must be the last batch dimension of the group (it is called on inputs
            with one more leading dimension, the replicas).
        action_key: the joint action the perturbation moves.
        value_key: the critic's output ``Q_i``.
    """

    def __init__(
        self, critic: TensorDictModule, *, action_key: NestedKey, value_key: NestedKey
    ) -> None:
        super().__init__()
        self.critic = critic
        self.action_key = action_key
        self.value_key = value_key
        self.in_keys = list(critic.in_keys)
        self.out_keys = list(critic.out_keys)
        self.epsilon = 0.0

    @contextmanager
    def perturbing(self, epsilon: float) -> Iterator[None]:
        """Within the block, calls perturb the other agents' actions by ``epsilon``."""
        previous, self.epsilon = self.epsilon, epsilon
        try:
            yield
        finally:
            self.epsilon = previous

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        """Writes ``value_key`` ``[*, I, 1]`` into ``tensordict`` (batch ``[*]``)."""
        if self.epsilon == 0:
            return self.critic(tensordict)
        actions = tensordict.get(self.action_key)  # [*, I, d]
        n = actions.shape[-2]
        inputs = tensordict.select(*self.in_keys, strict=False)
        replicated = inputs.unsqueeze(-1).expand(*inputs.batch_size, n)  # group: [*, I, I]

        def q_own(joint: torch.Tensor) -> torch.Tensor:  # [*, I, I, d] -> Q_i of replica i [*, I]
            td = replicated.clone(False).set(self.action_key, joint)
            q = self.critic(td).get(self.value_key)  # [*, I, I, 1]
            return q.squeeze(-1).diagonal(dim1=-2, dim2=-1)

        delta = minimax_action_perturbation(q_own, actions, self.epsilon)
        q = q_own(actions.unsqueeze(-3) + delta)  # gradients flow through `actions`
        tensordict.set(self.value_key, q.unsqueeze(-1))
        return tensordict


class _MinimaxTargetActorCritic(ActorCriticWrapper):
    """The target actor then the critic perturbed by ``epsilon``: the ``value_network`` of the
    loss's value estimator (same parameter layout as the ``ActorCriticWrapper`` it replaces)."""

    def __init__(self, actor: TensorDictModule, critic: MinimaxCritic, epsilon: float) -> None:
        super().__init__(actor, critic)
        self.epsilon = epsilon

    def forward(self, tensordict: TensorDictBase, *args, **kwargs) -> TensorDictBase:
        with self.module[1].perturbing(self.epsilon):
            return super().forward(tensordict, *args, **kwargs)


class M3DDPGLoss(PreactivationRegularisedDDPGLoss):
    """MADDPG's loss (:class:`PreactivationRegularisedDDPGLoss`) with M3DDPG's minimax critic
    target and actor objective (see the module docstring for the equations).

    Outputs ``loss_actor``, ``loss_actor_reg`` and ``loss_value`` as the MADDPG loss does (sum
    them with :meth:`total`); ``target_value`` is the minimax target ``y_i``.

    Args:
        actor_network: the actors ``o_i -> a_i``; writes ``action_key`` ``[*, I, d]`` and the
            pre-activation (see :class:`PreactivationRegularisedDDPGLoss`).
        value_network: the centralised critic ``Q_i(x, a)``, reads ``action_key`` and writes
            ``value_key`` ``[*, I, 1]``; it is wrapped in a :class:`MinimaxCritic`.
        action_key: the joint action ``[*, I, d]``.
        value_key: the critic's output (also set as the loss's ``state_action_value`` key).
        epsilon_critic: perturbation size in the critic's target (>= 0).
        epsilon_actor: perturbation size in the actor's objective (>= 0).
        **kwargs: passed to :class:`PreactivationRegularisedDDPGLoss` (``preactivation_key``,
            ``preactivation_coef``, ``delay_actor``, ``delay_value``, ``loss_function``).
    """

    def __init__(
        self,
        actor_network: TensorDictModule,
        value_network: TensorDictModule,
        *,
        action_key: NestedKey,
        value_key: NestedKey,
        epsilon_critic: float,
        epsilon_actor: float,
        **kwargs,
    ) -> None:
        epsilon_critic = finite_number("epsilon_critic", epsilon_critic, minimum=0)
        epsilon_actor = finite_number("epsilon_actor", epsilon_actor, minimum=0)
        critic = MinimaxCritic(value_network, action_key=action_key, value_key=value_key)
        super().__init__(actor_network, critic, **kwargs)
        self.epsilon_actor = float(epsilon_actor)
        self.set_keys(state_action_value=value_key)
        # the value estimator computes y_i through this (the target parameters loaded into it)
        self.__dict__["actor_critic"] = _MinimaxTargetActorCritic(
            self.actor_network, self.value_network, float(epsilon_critic)
        )

    @property
    def epsilon_critic(self) -> float:
        """Perturbation size in the critic's target."""
        return self.actor_critic.epsilon

    def loss_actor(self, tensordict: TensorDictBase) -> tuple[torch.Tensor, dict]:
        """``-mean_i Q_i(x, a + delta_i)`` with ``a = mu(o)`` and ``eps = epsilon_actor``."""
        with self.value_network.perturbing(self.epsilon_actor):
            return super().loss_actor(tensordict)
