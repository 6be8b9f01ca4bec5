"""Gaussian NLL loss for the per-agent probabilistic ensembles (MA-PETS eq. 9)."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.utils import NestedKey
from torchrl.objectives import LossModule

from mapets_rl.models.ensemble import ProbabilisticEnsemble

__all__ = ["EnsembleNLLLoss"]


class EnsembleNLLLoss(LossModule):
    """Gaussian NLL of the next-state delta, each member on its own bootstrap resample.

    For agent ``i`` and member ``b`` with bootstrap resample ``D_b^(i)`` of the batch (paper
    sec. IV-A), in normalised delta space:

        nll_{i,b} = mean_{(s,a,s') in D_b^(i)} [ (mu - y)^T Sigma^{-1} (mu - y) + log det Sigma ]

    (eq. 9, ``y = (s' - s - mean) / std``, diagonal ``Sigma = exp(logvar)``). The total loss is
    ``sum_{i,b} nll_{i,b}`` (members train independently) plus the PETS penalty
    ``logvar_bound_coef * (sum max_logvar - sum min_logvar)`` that keeps the learned
    log-variance bounds tight.

    Input TensorDict, batch shape ``[*]``: ``observation`` ``[*, I, obs]``, ``action``
    ``[*, I, act]``, ``next_observation`` ``[*, I, obs]``, optional ``mask`` ``[*, I]``
    (``False`` rows are ignored, e.g. crashed agents or padding of agents with smaller
    datasets).

    Output: ``loss_nll`` and ``loss_logvar_bounds`` (scalars, summed by trainers) and the
    per-member diagnostics ``nll_per_member`` ``[I, B]`` (detached).

    Args:
        model: the :class:`~mapets_rl.models.ProbabilisticEnsemble` to train.
        bootstrap: resample each member's rows with replacement (``False``: every member sees
            the whole batch).
        logvar_bound_coef: weight of the log-variance bound penalty (PETS: 0.01), >= 0.
        generator: optional ``torch.Generator`` for reproducible bootstrap indices.
    """

    @dataclass
    class _AcceptedKeys:
        """Configurable input keys (set with :meth:`set_keys`).

        Attributes:
            observation: ``("agents", "observation")``.
            action: ``("agents", "action")``.
            next_observation: ``("next", "agents", "observation")``.
            mask: ``("agents", "mask")``; optional in the input.
        """

        observation: NestedKey = ("agents", "observation")
        action: NestedKey = ("agents", "action")
        next_observation: NestedKey = ("next", "agents", "observation")
        mask: NestedKey = ("agents", "mask")

    tensor_keys: _AcceptedKeys
    default_keys = _AcceptedKeys
    out_keys = ["loss_nll", "loss_logvar_bounds", "nll_per_member"]

    def __init__(
        self,
        model: ProbabilisticEnsemble,
        *,
        bootstrap: bool = True,
        logvar_bound_coef: float = 0.01,
        generator: torch.Generator | None = None,
    ) -> None:
        if not isinstance(model, ProbabilisticEnsemble):
            raise ValueError(f"model must be a ProbabilisticEnsemble, got {type(model).__name__}.")
        if logvar_bound_coef < 0:
            raise ValueError(f"logvar_bound_coef must be >= 0, got {logvar_bound_coef}.")
        super().__init__()
        self.model = model
        self.bootstrap = bootstrap
        self.logvar_bound_coef = float(logvar_bound_coef)
        self.generator = generator

    def _forward_value_estimator_keys(self, **kwargs) -> None:
        """No value estimator: key changes only affect what :meth:`forward` reads."""

    @property
    def in_keys(self) -> list[NestedKey]:
        keys = self.tensor_keys
        return [keys.observation, keys.action, keys.next_observation, keys.mask]

    def _read(
        self, tensordict: TensorDictBase
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor | None]:
        """Read and flatten the batch to ``[N, I, *]`` tensors, validating shape and values."""
        keys = self.tensor_keys
        model = self.model
        obs = tensordict.get(keys.observation)
        action = tensordict.get(keys.action)
        next_obs = tensordict.get(keys.next_observation)
        mask = tensordict.get(keys.mask, None)
        if obs.ndim < 2:
            raise ValueError(f"{keys.observation} must be [*, I, obs], got {tuple(obs.shape)}.")
        batch = obs.shape[:-2]
        obs = obs.reshape(-1, *obs.shape[-2:])
        action = action.reshape(-1, *action.shape[-2:]) if action.ndim >= 2 else action
        next_obs = next_obs.reshape(-1, *next_obs.shape[-2:]) if next_obs.ndim >= 2 else next_obs
        if mask is not None:
            mask = mask.reshape(*batch, model.n_agents).reshape(-1, model.n_agents).bool()
        model._check_batch(obs, action, next_obs, mask)
        if mask is not None:
            # Masked rows may hold anything (e.g. NaN of removed agents): zero them out.
            keep = mask.unsqueeze(-1)
            obs, action, next_obs = (
                torch.where(keep, v, torch.zeros_like(v)) for v in (obs, action, next_obs)
            )
        return obs, action, next_obs, mask

    def fit_normalizer(self, tensordict: TensorDictBase) -> None:
        """Fit the model's per-agent normalisation on the loss's keys of ``tensordict``."""
        self.model.fit_normalizer(*self._read(tensordict))

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        obs, action, next_obs, mask = self._read(tensordict)
        model = self.model
        rows = obs.shape[0]
        n_agents, members = model.n_agents, model.ensemble_size
        # [N, I, d] -> [I, N, d], normalised inputs and targets.
        x = model.normalize_inputs(obs.transpose(0, 1), action.transpose(0, 1))
        y = ((next_obs - obs).transpose(0, 1) - model.output_mean[:, 0]) / model.output_std[:, 0]
        weight = (
            torch.ones(n_agents, rows, dtype=x.dtype, device=x.device)
            if mask is None
            else mask.transpose(0, 1).to(x.dtype)
        )
        if self.bootstrap:
            index = torch.randint(
                rows, (n_agents, members, rows), generator=self.generator, device=x.device
            )
            x_b = torch.gather(
                x.unsqueeze(1).expand(-1, members, -1, -1),
                2,
                index.unsqueeze(-1).expand(-1, -1, -1, x.shape[-1]),
            )
            y_b = torch.gather(
                y.unsqueeze(1).expand(-1, members, -1, -1),
                2,
                index.unsqueeze(-1).expand(-1, -1, -1, y.shape[-1]),
            )
            w_b = torch.gather(weight.unsqueeze(1).expand(-1, members, -1), 2, index)
        else:
            x_b = x.unsqueeze(1).expand(-1, members, -1, -1)
            y_b = y.unsqueeze(1)
            w_b = weight.unsqueeze(1).expand(-1, members, -1)
        mean, logvar = model.normalized_forward(x_b)
        # Eq. 9 with diagonal covariance: Mahalanobis term + log-determinant, per row.
        nll_rows = ((mean - y_b).pow(2) * torch.exp(-logvar) + logvar).sum(-1)  # [I, B, N]
        nll = (nll_rows * w_b).sum(-1) / w_b.sum(-1).clamp_min(1.0)  # [I, B]
        bounds = self.logvar_bound_coef * (model.max_logvar.sum() - model.min_logvar.sum())
        return TensorDict(
            {
                "loss_nll": nll.sum(),
                "loss_logvar_bounds": bounds,
                "nll_per_member": nll.detach(),
            },
            batch_size=[],
        )
