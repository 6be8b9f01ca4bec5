"""Gaussian NLL loss for the per-agent probabilistic ensembles (MA-PETS eq. 9)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.utils import NestedKey
from torchrl.objectives import LossModule

from mapets_rl.models.ensemble import ProbabilisticEnsemble
from mapets_rl.modules.arguments import finite_number
from mapets_rl.modules.tensor_checks import as_mask, get_tensor

__all__ = [
    "EnsembleFit",
    "EnsembleNLLLoss",
    "ensemble_optimizer",
    "fit_ensemble",
    "holdout_split",
    "read_transitions",
    "train_ensemble",
]


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
        return _normalized_data(self.model, obs, action, next_obs, mask)

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


def _normalized_data(
    model: ProbabilisticEnsemble,
    obs: torch.Tensor,
    action: torch.Tensor,
    next_obs: torch.Tensor,
    mask: torch.Tensor | None,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """See :meth:`EnsembleNLLLoss.normalized_data`."""
    x = model.normalize_inputs(obs.transpose(0, 1), action.transpose(0, 1))
    y = ((next_obs - obs).transpose(0, 1) - model.output_mean[:, 0]) / model.output_std[:, 0]
    if mask is None:
        weight = torch.ones(x.shape[:2], dtype=x.dtype, device=x.device)
    else:
        weight = mask.transpose(0, 1).to(x.dtype)
    return x, y, weight


class EnsembleFit(NamedTuple):
    """What :func:`fit_ensemble` did.

    Attributes:
        train_nll: ``[E, I, B]`` mean per-member training NLL of each epoch that ran (``E`` <=
            ``epochs``; fewer when it stopped early).
        epochs: ``E``, the epochs that ran.
        holdout_nll: ``[E + 1, I, B]`` held-out NLL of every member on its agent's held-out
            rows, before training (row 0) and after each epoch; ``NaN`` for agents without
            held-out rows. ``None`` without a hold-out.
        best_epoch: ``[G, B]`` the epoch whose weights each member kept (``0``: the weights
            it started with; ``E``: the last epoch's), ``G`` = the model's weight groups
            (``I``, or 1 with ``share_across_agents``). ``None`` without a hold-out.
        final_holdout_nll: ``[I, B]`` held-out NLL of the returned weights (each member's
            score, below, is at most the last epoch's). ``None`` without a hold-out.
    """

    train_nll: torch.Tensor
    epochs: int
    holdout_nll: torch.Tensor | None = None
    best_epoch: torch.Tensor | None = None
    final_holdout_nll: torch.Tensor | None = None


def holdout_split(
    mask: torch.Tensor | None,
    rows: int,
    n_agents: int,
    fraction: float,
    generator: torch.Generator | None = None,
    device: torch.device | str | None = None,
) -> torch.Tensor:
    """Which rows each agent holds out: ``[I, N]`` bool (agent-major).

    Agent ``i`` holds out ``floor(fraction * n_i)`` of its ``n_i`` valid rows (``mask[:, i]``;
    all ``N`` without a mask), drawn uniformly without replacement from one ``[I, N]``
    ``torch.rand`` draw of ``generator``; padding rows are never held out and, as
    ``fraction < 0.5``, every agent keeps at least half of its rows for training.

    Raises:
        ValueError: ``fraction`` is not a finite number in ``[0, 0.5)``, ``rows`` or
            ``n_agents`` is not a positive int, or ``mask`` is not ``[rows, n_agents]``.
    """
    fraction = finite_number("fraction", fraction, minimum=0)
    if not fraction < 0.5:
        raise ValueError(f"fraction must be in [0, 0.5), got {fraction!r}")
    for name, value in (("rows", rows), ("n_agents", n_agents)):
        if not isinstance(value, int) or isinstance(value, bool) or value < 1:
            raise ValueError(f"{name} must be a positive int, got {value!r}")
    if mask is not None and tuple(mask.shape) != (rows, n_agents):
        raise ValueError(
            f"mask must be [rows={rows}, n_agents={n_agents}], got {tuple(mask.shape)}"
        )
    valid = (
        torch.ones(n_agents, rows, dtype=torch.bool, device=device)
        if mask is None
        else mask.transpose(0, 1).to(device=device, dtype=torch.bool)
    )
    keys = torch.rand(n_agents, rows, generator=generator, device=device)
    keys = torch.where(valid, keys, torch.full_like(keys, 2.0))  # padding sorts last
    order = keys.argsort(dim=1, stable=True)
    rank = torch.empty_like(order).scatter_(
        1, order, torch.arange(rows, device=order.device).expand(n_agents, -1)
    )
    count = torch.floor(valid.sum(1) * fraction).long()  # [I]
    return valid & (rank < count[:, None])


def _compact(
    select: torch.Tensor, *tensors: torch.Tensor
) -> tuple[torch.Tensor, list[torch.Tensor]]:
    """The rows ``select`` ``[I, N]`` picks of each agent-major ``[I, N, *]`` tensor, moved to
    the front (original order) and cut to the largest count: ``(weight [I, M], tensors)``
    (``weight`` 0 on the padding of agents with fewer picked rows)."""
    width = int(select.sum(1).max())
    index = (~select).to(torch.uint8).argsort(dim=1, stable=True)[:, :width]  # [I, M]
    out = [t.gather(1, index.unsqueeze(-1).expand(-1, -1, t.shape[-1])) for t in tensors]
    return select.gather(1, index).to(tensors[0].dtype), out


def train_ensemble(
    loss_module: LossModule,
    optimizer: torch.optim.Optimizer,
    data: TensorDictBase,
    *,
    epochs: int = 5,
    batch_size: int = 128,
    fit_normalizer: bool = True,
    generator: torch.Generator | None = None,
    holdout: float = 0.0,
    patience: int = 5,
    min_improvement: float = 0.01,
) -> torch.Tensor:
    """Train every agent's ensemble on ``data`` (paper: 5 x 128, Adam): :func:`fit_ensemble`,
    returning its ``[E, I, B]`` per-epoch training NLL (``E = epochs`` without a hold-out)."""
    return fit_ensemble(
        loss_module,
        optimizer,
        data,
        epochs=epochs,
        batch_size=batch_size,
        fit_normalizer=fit_normalizer,
        generator=generator,
        holdout=holdout,
        patience=patience,
        min_improvement=min_improvement,
    ).train_nll


def fit_ensemble(
    loss_module: LossModule,
    optimizer: torch.optim.Optimizer,
    data: TensorDictBase,
    *,
    epochs: int = 5,
    batch_size: int = 128,
    fit_normalizer: bool = True,
    generator: torch.Generator | None = None,
    holdout: float = 0.0,
    patience: int = 5,
    min_improvement: float = 0.01,
) -> EnsembleFit:
    """Train every agent's ensemble for up to ``epochs`` passes over ``data``, optionally
    stopping early on a held-out NLL.

    All ``I * B`` members take each optimisation step together (one batched forward/backward);
    with :class:`~mapets_rl.objectives.EnsembleNLLLoss` each member sees its own bootstrap
    resample of every minibatch.

    Any other ``LossModule`` trains the ensemble it holds as ``loss_module.model`` through its
    ``forward`` on TensorDict minibatches of ``data`` (the ``"agents"`` keys, see
    :func:`read_transitions`), minimising the sum of its ``loss_*`` outputs; its optional
    ``nll_per_member`` ``[I, B]`` output is what the returned history records (without it,
    the summed loss over ``I * B``, for every member).

    Early stopping (``holdout > 0``): each agent holds out ``floor(holdout * n_i)`` of its
    ``n_i`` valid rows (:func:`holdout_split`, drawn from ``generator`` before any shuffle) and
    trains on the rest. The Gaussian NLL of eq. 9 (no bootstrap) of every member on its agent's
    held-out rows is evaluated before training and after each epoch, all members in one batched
    forward. Each member remembers the weights of its lowest held-out NLL so far; training
    stops once ``patience`` epochs in a row brought no member an improvement of more than
    ``min_improvement`` relative to its best (``(best - nll) > min_improvement * |best|``),
    or after ``epochs``. Each member then gets its best weights back (one ``torch.where`` per
    stacked parameter) unless they are worse than the last epoch's under the final
    log-variance bounds (the bounds are shared by the members of a group and are not
    restored), so every member's held-out NLL is at most the last epoch's. With
    ``share_across_agents`` a member's score is its NLL over every agent's held-out rows.
    Agents with no held-out row (fewer than ``1 / holdout`` rows) do not vote; when no agent
    has one the training runs all ``epochs``, as without a hold-out.

    Args:
        loss_module: an ``EnsembleNLLLoss`` (keys as set on it), or any ``LossModule`` with
            the ensemble as ``.model`` that reads the ``"agents"`` keys.
        optimizer: optimiser over ``loss_module.parameters()`` (paper: Adam, lr 1e-3).
        data: transitions with batch shape ``[N]`` and the loss's keys shaped ``[N, I, *]``
            (agents with fewer transitions pad with ``mask=False`` rows; every agent needs at
            least one valid row, ValueError otherwise).
        epochs: passes over the data (> 0), the most that run with a hold-out.
        batch_size: rows per optimisation step (> 0).
        fit_normalizer: refit the per-agent input/output normalisation on ``data`` first (on
            all of it, the held-out rows included).
        generator: optional generator for the hold-out split and the shuffling.
        holdout: fraction of each agent's rows held out, in ``[0, 0.5)``; ``0`` (default)
            trains exactly ``epochs`` passes over all rows, without evaluation.
        patience: epochs without improvement before stopping (>= 1).
        min_improvement: relative held-out NLL improvement that counts, in ``[0, 1)``.

    Returns:
        an :class:`EnsembleFit`: the ``[E, I, B]`` mean per-member training NLL of each epoch
        run, ``E``, and with a hold-out the held-out NLL curve and each member's kept epoch.
    """
    if not isinstance(epochs, int) or epochs <= 0:
        raise ValueError(f"epochs must be a positive integer, got {epochs!r}.")
    if not isinstance(batch_size, int) or batch_size <= 0:
        raise ValueError(f"batch_size must be a positive integer, got {batch_size!r}.")
    holdout = finite_number("holdout", holdout, minimum=0)
    if not holdout < 0.5:
        raise ValueError(f"holdout must be in [0, 0.5), got {holdout!r}.")
    if not isinstance(patience, int) or isinstance(patience, bool) or patience <= 0:
        raise ValueError(f"patience must be a positive integer, got {patience!r}.")
    min_improvement = finite_number("min_improvement", min_improvement, minimum=0)
    if not min_improvement < 1:
        raise ValueError(f"min_improvement must be in [0, 1), got {min_improvement!r}.")
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
    mask = batch[3]  # [N, I] or None
    empty = [] if mask is None else (~mask.any(0)).nonzero().flatten().tolist()
    if empty:
        raise ValueError(
            f"data holds no valid row (mask all False) for agents {empty}: an ensemble cannot "
            "be fitted on nothing (its training NLL would read 0 and its held-out NLL NaN); "
            "leave those agents out or give them transitions."
        )
    if fit_normalizer:
        model.fit_normalizer(*batch)
    rows = data.batch_size[0]
    # A subclass that redefines ``forward`` (another loss) is trained through it, on TensorDict
    # minibatches, summing its ``loss_*`` outputs. Otherwise the normalisation is fixed during
    # training, so the dataset is normalised once and the steps only index it (no TensorDict,
    # validation or host sync per step).
    custom = type(loss_module).forward is not EnsembleNLLLoss.forward
    members = (model.n_agents, model.ensemble_size)
    device = next(model.parameters()).device  # a TensorDict built without one has device None
    stopper = None
    if holdout > 0:
        held = holdout_split(batch[3], rows, model.n_agents, holdout, generator, device)
        if bool(held.any()):
            x, y, weight = _normalized_data(model, *batch)
            val_weight, (x_val, y_val) = _compact(held, x, y)
            stopper = _EarlyStopping(model, x_val, y_val, val_weight, patience, min_improvement)
            train_rows = (weight > 0) & ~held  # [I, N]
            if custom:
                # the loss reads the rows it trains on from the "agents" mask
                data = data.clone()
                data.set(EnsembleNLLLoss.default_keys.mask, train_rows.transpose(0, 1))
            else:
                weight, (x, y) = _compact(train_rows, x, y)
                rows = x.shape[1]
    if not custom and stopper is None:
        x, y, weight = loss_module.normalized_data(*batch)
    history = []
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
        if stopper is not None and stopper.after_epoch(len(history)):
            break
    train_nll = torch.stack(history)
    if stopper is None:
        return EnsembleFit(train_nll, len(history))
    final = stopper.restore_best()
    return EnsembleFit(
        train_nll, len(history), torch.stack(stopper.curve), stopper.best_epoch, final
    )


class _EarlyStopping:
    """Held-out evaluation, per-member best weights and the stopping rule of
    :func:`fit_ensemble` (see there). ``x`` / ``y`` / ``weight``: the agent-major normalised
    held-out rows ``[I, M, *]`` and their ``[I, M]`` weights (0 on padding)."""

    def __init__(
        self,
        model: ProbabilisticEnsemble,
        x: torch.Tensor,
        y: torch.Tensor,
        weight: torch.Tensor,
        patience: int,
        min_improvement: float,
    ) -> None:
        self.model, self.y, self.weight = model, y, weight
        self.x = x.unsqueeze(1).expand(-1, model.ensemble_size, -1, -1)  # [I, B, M, in]
        self.count = weight.sum(1)  # [I]
        self.patience, self.min_improvement = patience, min_improvement
        # the stacked member parameters, [G, B, ...] (the log-variance bounds are per group)
        self.params = [*model.weights, *model.biases]
        groups = model.weights[0].shape[0]
        counts = self.count.sum(0, keepdim=True) if groups == 1 else self.count
        self.voting = counts > 0  # [G]: groups with held-out rows
        self.curve: list[torch.Tensor] = []
        self.stale = 0
        self.best_score, self.last_score = self.evaluate()
        self.best_epoch = torch.zeros_like(self.best_score, dtype=torch.long)
        self.best = [p.detach().clone() for p in self.params]

    @torch.no_grad()
    def evaluate(self) -> tuple[torch.Tensor, torch.Tensor]:
        """Appends the ``[I, B]`` held-out NLL to ``curve``; returns the ``[G, B]`` member
        scores twice (``+inf`` for groups without held-out rows)."""
        mean, logvar = self.model.normalized_forward(self.x)  # one batched forward
        rows = ((mean - self.y.unsqueeze(1)).pow(2) * torch.exp(-logvar) + logvar).sum(-1)
        total = (rows * self.weight.unsqueeze(1)).sum(-1)  # [I, B]
        count = self.count.unsqueeze(1)
        self.curve.append(torch.where(count > 0, total / count.clamp_min(1.0), math.nan))
        if self.model.weights[0].shape[0] == 1:  # one set of members for all agents
            total, count = total.sum(0, keepdim=True), count.sum(0, keepdim=True)
        score = torch.where(count > 0, total / count.clamp_min(1.0), math.inf)
        return score, score

    @torch.no_grad()
    def after_epoch(self, epoch: int) -> bool:
        """Evaluates the members after ``epoch``, keeps the better ones; ``True``: stop."""
        score, self.last_score = self.evaluate()
        better = score < self.best_score  # [G, B]
        gain = (self.best_score - score) > self.min_improvement * self.best_score.abs()
        improved = bool((gain & self.voting[:, None]).any())  # the epoch's only host sync
        view = (*better.shape, 1, 1)
        for param, best in zip(self.params, self.best, strict=True):
            best.copy_(torch.where(better.view(view), param, best))
        self.best_score = torch.where(better, score, self.best_score)
        self.best_epoch = torch.where(better, epoch, self.best_epoch)
        self.stale = 0 if improved else self.stale + 1
        return self.stale >= self.patience and bool(self.voting.any())

    @torch.no_grad()
    def restore_best(self) -> torch.Tensor:
        """Gives every member its best weights back (unless worse than its last epoch's under
        the final log-variance bounds); returns their ``[I, B]`` held-out NLL."""
        last_epoch = len(self.curve) - 1
        restore = self.best_epoch < last_epoch  # [G, B]
        if not bool(restore.any()):
            return self.curve[-1]
        view = (*restore.shape, 1, 1)
        last = [p.detach().clone() for p in self.params]
        for param, best in zip(self.params, self.best, strict=True):
            param.copy_(torch.where(restore.view(view), best, param))
        score, _ = self.evaluate()
        restored_curve = self.curve.pop()
        worse = restore & (score > self.last_score)
        if bool(worse.any()):
            for param, kept in zip(self.params, last, strict=True):
                param.copy_(torch.where(worse.view(view), kept, param))
            restore = restore & ~worse
        self.best_epoch = torch.where(restore, self.best_epoch, last_epoch)
        groups = self.best_epoch.shape[0]
        keep = restore.expand(self.model.n_agents, -1) if groups == 1 else restore
        return torch.where(keep, restored_curve, self.curve[-1])
