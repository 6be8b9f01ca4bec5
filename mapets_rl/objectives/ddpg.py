"""MADDPG's actor-critic loss: torchrl's ``DDPGLoss`` plus the actor pre-activation penalty of
the MADDPG reference implementation (Lowe et al. 2017).

The deterministic policy gradient pushes an actor's pre-activation (the input of the ``tanh``
that bounds a continuous action, or the logits of a one-hot action) along ``dQ/da`` without
limit. Once it is far outside the ``tanh``'s linear range the action sits at a bound and its
gradient vanishes, so the actor cannot leave the bound even after the critic has learnt that
the bound is bad. The reference implementation adds ``coef * mean(preactivation^2)`` to the
actor loss (``coef = 1e-3``), which keeps the pre-activation where gradients flow.
"""

from __future__ import annotations

import torch
from tensordict import NestedKey, TensorDictBase
from tensordict.nn import TensorDictModule
from torch import nn
from torchrl.objectives import DDPGLoss


class PreactivationRegularisedDDPGLoss(DDPGLoss):
    """``DDPGLoss`` whose actor loss adds ``preactivation_coef * mean(p^2)``, ``p`` being the
    actor's pre-activation that it writes under ``preactivation_key``.

    The penalty is a separate output, ``"loss_actor_reg"``; sum it with ``"loss_actor"`` and
    ``"loss_value"`` (the actor loss already sees detached critic parameters, so one backward
    pass over the sum trains both networks).

    Args:
        actor_network: the actor; it must write ``preactivation_key`` (``[*, I, d]``).
        value_network: the critic ``Q(o, a)``.
        preactivation_key: where the actor writes its pre-activation.
        preactivation_coef: penalty weight (>= 0; 0 turns the penalty off).
        **kwargs: passed to ``DDPGLoss`` (``delay_actor``, ``delay_value``, ``loss_function``).
    """

    def __init__(
        self,
        actor_network: TensorDictModule,
        value_network: TensorDictModule,
        *,
        preactivation_key: NestedKey,
        preactivation_coef: float = 1e-3,
        **kwargs,
    ) -> None:
        if preactivation_coef < 0:
            raise ValueError(f"preactivation_coef must be >= 0, got {preactivation_coef}")
        super().__init__(actor_network, value_network, **kwargs)
        self.preactivation_key = preactivation_key
        self.preactivation_coef = preactivation_coef

    def loss_actor(self, tensordict: TensorDictBase) -> tuple[torch.Tensor, dict]:
        """DDPG's actor loss, with the penalty ``loss_actor_reg`` of the same actor pass in its
        metadata: the pre-activation is read as the actor writes it (a forward hook), so one
        actor forward and one backward serve both terms."""
        written: list[torch.Tensor] = []

        def keep(_module: nn.Module, _args: object, out: TensorDictBase) -> None:
            written.append(out.get(self.preactivation_key))

        handle = self.actor_network.register_forward_hook(keep)
        try:
            loss, metadata = super().loss_actor(tensordict)
        finally:
            handle.remove()
        (preactivation,) = written
        return loss, {
            **metadata,
            "loss_actor_reg": self.preactivation_coef * preactivation.pow(2).mean(),
        }

    @staticmethod
    def total(out: TensorDictBase) -> torch.Tensor:
        """The scalar to back-propagate: actor loss + its penalty + value loss."""
        return out["loss_actor"] + out["loss_actor_reg"] + out["loss_value"]
