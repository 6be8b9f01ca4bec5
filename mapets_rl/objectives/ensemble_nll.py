"""Gaussian NLL loss for the per-agent probabilistic ensembles (MA-PETS eq. 9)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.utils import NestedKey
from torchrl.objectives import LossModule

from mapets_rl.models.ensemble import ProbabilisticEnsemble
from mapets_rl.modules.arguments import finite_number
from mapets_rl.modules.tensor_checks import as_mask, get_tensor

__all__ = ["EnsembleNLLLoss", "ensemble_optimizer", "read_transitions", "train_ensemble"]


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
        logvar_bound_coef = finite_number("logvar_bound_coef", logvar_bound_coef, minimum=0)
        super().__init__()
        self.model = model
        self.bootstrap = bootstrap
        self.logvar_bound_coef = logvar_bound_coef
        self.generator = generator

    def _forward_value_estimator_keys(self, **kwargs) -> None:
        """No value estimator: key changes only affect what :meth:`forward` reads."""

    @property
    def in_keys(self) -> list[NestedKey]:
        keys = self.tensor_keys
        return [keys.observation, keys.action, keys.next_observation, keys.mask]

    def read_batch(
        self, tensordict: TensorDictBase
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor | None]:
        """Read and flatten the batch to ``[N, I, *]`` tensors, validating shape and values
        (:func:`read_transitions` on this loss's keys)."""
        return read_transitions(tensordict, self.model, self.tensor_keys, type(self).__name__)

    def fit_normalizer(self, tensordict: TensorDictBase) -> None:
        """Fit the model's per-agent normalisation on the loss's keys of ``tensordict``."""
        self.model.fit_normalizer(*self.read_batch(tensordict))

    def normalized_data(
        self,
        obs: torch.Tensor,
        action: torch.Tensor,
        next_obs: torch.Tensor,
        mask: torch.Tensor | None = None,
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Agent-major normalised inputs ``[I, N, obs + act]``, targets ``[I, N, obs]`` and
        row weights ``[I, N]`` (``0`` for masked rows) of ``[N, I, *]`` tensors as returned by
        :meth:`read_batch`."""
        model = self.model
        x = model.normalize_inputs(obs.transpose(0, 1), action.transpose(0, 1))
        y = ((next_obs - obs).transpose(0, 1) - model.output_mean[:, 0]) / model.output_std[:, 0]
        if mask is None:
            weight = torch.ones(x.shape[:2], dtype=x.dtype, device=x.device)
        else:
            weight = mask.transpose(0, 1).to(x.dtype)
        return x, y, weight

    def member_losses(
        self,
        x: torch.Tensor,
        y: torch.Tensor,
        weight: torch.Tensor,
        rows: torch.Tensor | None = None,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Loss of a minibatch of :meth:`normalized_data` rows, without building TensorDicts.

        Args:
            x / y / weight: ``[I, N, in]``, ``[I, N, obs]``, ``[I, N]`` (see
                :meth:`normalized_data`).
            rows: optional ``[n]`` long, the minibatch's rows (default: all ``N``). Each
                member resamples them with replacement when ``bootstrap`` is on (one
                ``[I, B, n]`` draw from ``generator``), composed into a single gather.

        Returns:
            ``(nll, bounds)``: the per-member NLL ``[I, B]`` and the scalar log-variance bound
            penalty (both with grad); the loss to minimise is ``nll.sum() + bounds``.
        """
        model = self.model
        n_agents, members = model.n_agents, model.ensemble_size
        count = x.shape[1] if rows is None else rows.shape[0]
        if self.bootstrap:
            index = torch.randint(
                count, (n_agents, members, count), generator=self.generator, device=x.device
            )
            if rows is not None:
                index = rows[index]
        elif rows is None:
            index = torch.arange(count, device=x.device).expand(n_agents, members, -1)
        else:
            index = rows.expand(n_agents, members, -1)
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
        mean, logvar = model.normalized_forward(x_b)
        # Eq. 9 with diagonal covariance: Mahalanobis term + log-determinant, per row.
        nll_rows = ((mean - y_b).pow(2) * torch.exp(-logvar) + logvar).sum(-1)  # [I, B, n]
        nll = (nll_rows * w_b).sum(-1) / w_b.sum(-1).clamp_min(1.0)  # [I, B]
        bounds = self.logvar_bound_coef * (model.max_logvar.sum() - model.min_logvar.sum())
        return nll, bounds

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        x, y, weight = self.normalized_data(*self.read_batch(tensordict))
        nll, bounds = self.member_losses(x, y, weight)
        return TensorDict(
            {
                "loss_nll": nll.sum(),
                "loss_logvar_bounds": bounds,
                "nll_per_member": nll.detach(),
            },
            batch_size=[],
        )


def ensemble_optimizer(loss_module: LossModule, lr: float = 1e-3) -> torch.optim.Optimizer:
    """Adam over the loss module's parameters, fused (one kernel for all parameters) where
    torch supports it on their device, else the multi-tensor ``foreach`` implementation."""
    params = list(loss_module.parameters())
    try:
        return torch.optim.Adam(params, lr=lr, fused=True)
    except RuntimeError:
        return torch.optim.Adam(params, lr=lr, foreach=True)


def read_transitions(
    tensordict: TensorDictBase,
    model: ProbabilisticEnsemble,
    keys: object = None,
    owner: str = "train_ensemble",
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor | None]:
    """The transitions of ``tensordict`` as ``(obs, action, next_obs, mask)`` ``[N, I, *]``
    (``mask`` ``[N, I]`` or ``None``), validated against ``model``'s sizes and finiteness;
    masked-out rows are zeroed.

    Args:
        tensordict: batch ``[*]`` with ``[*, I, *]`` entries.
        model: the ensemble the transitions are for (its ``n_agents``, ``obs_dim``,
            ``action_dim``).
        keys: an object with ``observation``, ``action``, ``next_observation`` and ``mask``
            key attributes (default: :class:`EnsembleNLLLoss`'s, the ``"agents"`` layout:
            ``("agents", "observation")``, ``("agents", "action")``,
            ``("next", "agents", "observation")``, ``("agents", "mask")``).
        owner: who reads them, named in the error messages.
    """
    keys = EnsembleNLLLoss.default_keys() if keys is None else keys
    n = model.n_agents
    obs = get_tensor(tensordict, keys.observation, f"[*, {n}, {model.obs_dim}]", owner)
    action = get_tensor(tensordict, keys.action, f"[*, {n}, {model.action_dim}]", owner)
    next_obs = get_tensor(tensordict, keys.next_observation, f"[*, {n}, {model.obs_dim}]", owner)
    mask = tensordict.get(keys.mask, None)
    if obs.ndim < 2:
        raise ValueError(f"{keys.observation} must be [*, I, obs], got {tuple(obs.shape)}.")
    batch = obs.shape[:-2]
    obs = obs.reshape(-1, *obs.shape[-2:])
    action = action.reshape(-1, *action.shape[-2:]) if action.ndim >= 2 else action
    next_obs = next_obs.reshape(-1, *next_obs.shape[-2:]) if next_obs.ndim >= 2 else next_obs
    if mask is not None:
        expected = (*batch, n)
        if tuple(mask.shape) not in (expected, (*expected, 1)):
            raise ValueError(
                f"{keys.mask} must have shape {list(expected)} (or {[*expected, 1]}), "
                f"got {list(mask.shape)}"
            )
        mask = as_mask(repr(keys.mask), mask, f"{list(expected)}").reshape(-1, n)
    model.check_batch(obs, action, next_obs, mask)
    if mask is not None:
        # Masked rows may hold anything (e.g. NaN of removed agents): zero them out.
        keep = mask.unsqueeze(-1)
        obs, action, next_obs = (
            torch.where(keep, v, torch.zeros_like(v)) for v in (obs, action, next_obs)
        )
    return obs, action, next_obs, mask


def train_ensemble(
    loss_module: LossModule,
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
    with :class:`~mapets_rl.objectives.EnsembleNLLLoss` each member sees its own bootstrap
    resample of every minibatch.

    Any other ``LossModule`` trains the ensemble it holds as ``loss_module.model`` through its
    ``forward`` on TensorDict minibatches of ``data`` (the ``"agents"`` keys, see
    :func:`read_transitions`), minimising the sum of its ``loss_*`` outputs; its optional
    ``nll_per_member`` ``[I, B]`` output is what the returned history records (without it,
    the summed loss over ``I * B``, for every member).

    Args:
        loss_module: an ``EnsembleNLLLoss`` (keys as set on it), or any ``LossModule`` with
            the ensemble as ``.model`` that reads the ``"agents"`` keys.
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
    model = getattr(loss_module, "model", None)
    if not isinstance(model, ProbabilisticEnsemble):
        raise ValueError(
            f"loss_module must hold the ProbabilisticEnsemble it trains as .model, got "
            f"{type(model).__name__} on {type(loss_module).__name__}."
        )
    # Validates shapes and finiteness of the whole dataset once, before any update.
    if isinstance(loss_module, EnsembleNLLLoss):
        batch = loss_module.read_batch(data)
    else:
        batch = read_transitions(data, model, owner=type(loss_module).__name__)
    if fit_normalizer:
        model.fit_normalizer(*batch)
    rows = data.batch_size[0]
    # A subclass that redefines ``forward`` (another loss) is trained through it, on TensorDict
    # minibatches, summing its ``loss_*`` outputs. Otherwise the normalisation is fixed during
    # training, so the dataset is normalised once and the steps only index it (no TensorDict,
    # validation or host sync per step).
    custom = type(loss_module).forward is not EnsembleNLLLoss.forward
    members = (model.n_agents, model.ensemble_size)
    if not custom:
        x, y, weight = loss_module.normalized_data(*batch)
    history = []
    device = next(model.parameters()).device  # a TensorDict built without one has device None
    for _ in range(epochs):
        order = torch.randperm(rows, generator=generator, device=device)
        per_member = []
        for start in range(0, rows, batch_size):
            index = order[start : start + batch_size]
            if custom:
                losses = loss_module(data[index])
                total = sum(v for k, v in losses.items() if k.startswith("loss_"))
                member = losses.get("nll_per_member", None)
                if member is None:
                    member = (total.detach() / math.prod(members)).expand(members)
            else:
                nll, bounds = loss_module.member_losses(x, y, weight, index)
                total, member = nll.sum() + bounds, nll.detach()
            optimizer.zero_grad(set_to_none=True)
            total.backward()
            optimizer.step()
            per_member.append(member)
        history.append(torch.stack(per_member).mean(0))
    return torch.stack(history)
