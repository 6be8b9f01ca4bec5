"""Action heads for discrete (one-hot) actions: greedy one-hot and Gumbel-softmax, the one
implementation that MADDPG, the Shapley actors and the Shapley actor-critic loss share."""

from __future__ import annotations

import torch
from torch import nn
from torchrl.envs.utils import ExplorationType, exploration_type


def one_hot_argmax(scores: torch.Tensor) -> torch.Tensor:
    """Scores [..., n] -> the one-hot of their argmax [..., n] (in ``scores``' dtype; no
    gradient)."""
    return nn.functional.one_hot(scores.argmax(-1), scores.shape[-1]).to(scores.dtype)


def gumbel_one_hot(logits: torch.Tensor, tau: float) -> torch.Tensor:
    """A hard Gumbel-softmax sample of ``logits`` [..., n] at temperature ``tau``: one-hot
    [..., n] whose gradient is that of the soft sample (straight-through)."""
    return nn.functional.gumbel_softmax(logits, tau=tau, hard=True)


class GumbelSoftmaxHead(nn.Module):
    """Logits [..., n] -> one-hot action [..., n] that carries gradients (MADDPG, Lowe et al.
    2017, discrete actions).

    Under ``ExplorationType.RANDOM`` (collection) it draws a hard Gumbel-softmax sample at
    temperature ``tau`` (:func:`gumbel_one_hot`); otherwise (evaluation and the loss's actor
    update) the greedy one-hot ``argmax`` with the straight-through softmax gradient.

    With ``return_logits=True`` it returns ``(logits, action)``, so that a ``TensorDictModule``
    can also write the logits (MADDPG's actor penalty reads them). With ``sample=False`` it is
    greedy while collecting too (the exploration is then another module's, e.g. epsilon-greedy).
    """

    def __init__(self, tau: float = 1.0, return_logits: bool = False, sample: bool = True) -> None:
        super().__init__()
        if tau <= 0:
            raise ValueError(f"tau must be > 0, got {tau}")
        self.tau = tau
        self.return_logits = return_logits
        self.sample = sample

    def forward(self, logits: torch.Tensor) -> torch.Tensor | tuple[torch.Tensor, torch.Tensor]:
        if self.sample and exploration_type() is ExplorationType.RANDOM:
            action = gumbel_one_hot(logits, self.tau)
        else:
            soft = logits.softmax(-1)
            action = one_hot_argmax(soft) + soft - soft.detach()
        return (logits, action) if self.return_logits else action
