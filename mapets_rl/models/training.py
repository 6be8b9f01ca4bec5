"""One-call training of all agents' ensembles (MA-PETS Algorithm 1, model-learning phase)."""

from __future__ import annotations

from typing import TYPE_CHECKING

import torch
from tensordict import TensorDictBase

if TYPE_CHECKING:
    from mapets_rl.objectives.ensemble_nll import EnsembleNLLLoss

__all__ = ["train_ensemble"]


def train_ensemble(
    loss_module: EnsembleNLLLoss,
    optimizer: torch.optim.Optimizer,
    data: TensorDictBase,
    *,
    epochs: int = 5,
    batch_size: int = 128,
    fit_normalizer: bool = True,
    generator: torch.Generator | None = None,
) -> torch.Tensor:
    """Train every agent's ensemble for ``epochs`` passes over ``data`` (paper: 5 x 128, Adam).

    All ``I * B`` members take each optimisation step together (one batched forward/backward);
    each member sees its own bootstrap resample of every minibatch (see
    :class:`~mapets_rl.objectives.EnsembleNLLLoss`).

    Args:
        loss_module: an ``EnsembleNLLLoss`` wrapping the ensemble.
        optimizer: optimiser over ``loss_module.parameters()`` (paper: Adam, lr 1e-3).
        data: transitions with batch shape ``[N]`` and the loss's keys shaped ``[N, I, *]``
            (agents with fewer transitions pad with ``mask=False`` rows).
        epochs: passes over the data (> 0).
        batch_size: rows per optimisation step (> 0).
        fit_normalizer: refit the per-agent input/output normalisation on ``data`` first.
        generator: optional generator for the shuffling.

    Returns:
        ``[epochs, I, B]`` mean per-member NLL of each epoch.
    """
    if not isinstance(epochs, int) or epochs <= 0:
        raise ValueError(f"epochs must be a positive integer, got {epochs!r}.")
    if not isinstance(batch_size, int) or batch_size <= 0:
        raise ValueError(f"batch_size must be a positive integer, got {batch_size!r}.")
    if data.batch_dims != 1 or data.batch_size[0] == 0:
        raise ValueError(
            f"data must have a non-empty batch shape [N], got {tuple(data.batch_size)}."
        )
    # Validates shapes and finiteness of the whole dataset before any update.
    if fit_normalizer:
        loss_module.fit_normalizer(data)
    else:
        loss_module._read(data)
    rows = data.batch_size[0]
    history = []
    for _ in range(epochs):
        order = torch.randperm(rows, generator=generator, device=data.device)
        per_member = []
        for start in range(0, rows, batch_size):
            losses = loss_module(data[order[start : start + batch_size]])
            total = sum(v for k, v in losses.items() if k.startswith("loss_"))
            optimizer.zero_grad(set_to_none=True)
            total.backward()
            optimizer.step()
            per_member.append(losses["nll_per_member"])
        history.append(torch.stack(per_member).mean(0))
    return torch.stack(history)
