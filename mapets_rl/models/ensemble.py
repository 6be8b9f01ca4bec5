"""Probabilistic ensemble dynamics model of MA-PETS (paper sec. IV-A, PETS).

Every agent ``i`` owns ``B`` bootstrapped probabilistic MLPs
``P~_{theta_b}^{(i)}(s_{t+1} | s_t, a_t)`` that output the mean and the diagonal log-variance of the
next-state delta ``s_{t+1} - s_t``. All ``I * B`` MLPs are stored as stacked weights and evaluated
as one batched matrix product per layer (``torch.baddbmm``): there is no Python loop over agents
or members.

Two entry points:

* :meth:`ProbabilisticEnsemble.forward` — a ``TensorDictModuleBase`` forward reading
  ``("agents", "observation")`` ``[*, I, obs]`` and ``("agents", "action")`` ``[*, I, act]`` and
  writing per-member predictions ``("agents", "delta_mean")`` / ``("agents", "delta_logvar")``
  ``[*, I, B, obs]``.
* :meth:`ProbabilisticEnsemble.predict` — the raw-tensor fast path used by the planner: inputs
  ``[I, B, N, *]`` (``N`` rows per member), outputs ``[I, B, N, obs]``.
"""

from __future__ import annotations

import contextlib
import math
from collections.abc import Iterator, Sequence
from itertools import pairwise

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from tensordict.utils import NestedKey
from torch import nn
from torch.nn import functional as F

from mapets_rl.memory import check_memory
from mapets_rl.modules.arguments import is_positive_int
from mapets_rl.modules.tensor_checks import (
    as_mask,
    check_finite,
    check_finite_many,
    check_real,
    get_tensor,
)

__all__ = ["ProbabilisticEnsemble", "check_finite"]


class ProbabilisticEnsemble(TensorDictModuleBase):
    """Per-agent ensembles of probabilistic MLPs predicting the next-state delta.

    Args:
        obs_dim: observation size ``S`` (> 0).
        action_dim: action size ``A`` (> 0).
        n_agents: number of agents ``I`` (> 0); each owns its own ensemble.
        ensemble_size: members ``B`` per agent (> 0). Paper: 5.
        hidden: hidden layer widths (each > 0). Paper: 3 layers of 300-400 units.
        share_across_agents: if ``True`` all agents use one set of ``B`` MLPs (a centralised
            model trained on everybody's data); input/output normalisation stays per agent.
        init_max_logvar / init_min_logvar: initial soft bounds of the normalised log-variance.
        observation_key / action_key: input keys of the TensorDict forward.
        mean_key / logvar_key: output keys of the TensorDict forward.

    Shapes: weights of layer ``l`` are ``[G, B, in_l, out_l]`` with ``G = I`` (or 1 when
    shared). Normalisation statistics are ``[I, 1, 1, dim]`` buffers fitted by
    :meth:`fit_normalizer` on each agent's own data. Without autograd (planning) the hidden
    activations go to a workspace of ``2 x rows x max(hidden)`` floats kept on the module and
    reused across calls (paper config, I=22: ~420 MB).
    """

    def __init__(
        self,
        obs_dim: int,
        action_dim: int,
        n_agents: int,
        ensemble_size: int = 5,
        hidden: Sequence[int] = (200, 200, 200),
        *,
        share_across_agents: bool = False,
        init_max_logvar: float = 0.5,
        init_min_logvar: float = -10.0,
        observation_key: NestedKey = ("agents", "observation"),
        action_key: NestedKey = ("agents", "action"),
        mean_key: NestedKey = ("agents", "delta_mean"),
        logvar_key: NestedKey = ("agents", "delta_logvar"),
    ) -> None:
        for name, value in (
            ("obs_dim", obs_dim),
            ("action_dim", action_dim),
            ("n_agents", n_agents),
            ("ensemble_size", ensemble_size),
        ):
            if not is_positive_int(value):
                raise ValueError(f"{name} must be a positive integer, got {value!r}.")
        hidden = tuple(hidden)
        if len(hidden) == 0 or not all(is_positive_int(h) for h in hidden):
            raise ValueError(f"hidden must be a non-empty sequence of positive ints, got {hidden}.")
        if not init_min_logvar < init_max_logvar:
            raise ValueError(
                f"init_min_logvar ({init_min_logvar}) must be < "
                f"init_max_logvar ({init_max_logvar})."
            )
        groups = 1 if share_across_agents else n_agents
        sizes = (obs_dim + action_dim, *hidden, 2 * obs_dim)
        weights = groups * ensemble_size * sum((a + 1) * b for a, b in pairwise(sizes))
        check_memory(  # the fp32 weights alone: a lower bound that never refuses what fits
            4 * weights,
            "cpu",
            f"the ensemble's weights ({groups} x ensemble_size={ensemble_size} MLPs of "
            f"hidden={list(hidden)})",
            "lower ensemble_size or hidden",
        )
        super().__init__()
        self.obs_dim = obs_dim
        self.action_dim = action_dim
        self.n_agents = n_agents
        self.ensemble_size = ensemble_size
        self.hidden = hidden
        self.share_across_agents = share_across_agents
        self.in_keys = [observation_key, action_key]
        self.out_keys = [mean_key, logvar_key]

        in_dim = obs_dim + action_dim
        self.weights = nn.ParameterList()
        self.biases = nn.ParameterList()
        for fan_in, fan_out in zip(sizes[:-1], sizes[1:], strict=True):
            weight = torch.empty(groups, ensemble_size, fan_in, fan_out)
            # PETS initialisation: truncated normal with std 1 / (2 sqrt(fan_in)).
            std = 1.0 / (2.0 * math.sqrt(fan_in))
            nn.init.trunc_normal_(weight, std=std, a=-2 * std, b=2 * std)
            self.weights.append(nn.Parameter(weight))
            self.biases.append(nn.Parameter(torch.zeros(groups, ensemble_size, 1, fan_out)))
        # Learned soft bounds on the (normalised) log-variance (PETS appendix A.1).
        self.max_logvar = nn.Parameter(torch.full((groups, 1, 1, obs_dim), float(init_max_logvar)))
        self.min_logvar = nn.Parameter(torch.full((groups, 1, 1, obs_dim), float(init_min_logvar)))

        self.register_buffer("input_mean", torch.zeros(n_agents, 1, 1, in_dim))
        self.register_buffer("input_std", torch.ones(n_agents, 1, 1, in_dim))
        self.register_buffer("output_mean", torch.zeros(n_agents, 1, 1, obs_dim))
        self.register_buffer("output_std", torch.ones(n_agents, 1, 1, obs_dim))
        # (dtype, per-layer parameters) while a frozen_parameters block is open
        self._param_cache: tuple[torch.dtype, list[tuple[torch.Tensor, torch.Tensor]]] | None = None
        self._buffers_cache: list[torch.Tensor] | None = None  # inference workspace

    # ------------------------------------------------------------------ normalisation
    @torch.no_grad()
    def fit_normalizer(
        self,
        obs: torch.Tensor,
        action: torch.Tensor,
        next_obs: torch.Tensor,
        mask: torch.Tensor | None = None,
    ) -> None:
        """Fit per-agent input and delta statistics.

        Args:
            obs: ``[N, I, obs]`` observations of every agent's dataset.
            action: ``[N, I, act]``.
            next_obs: ``[N, I, obs]``.
            mask: optional ``[N, I]`` bool, ``False`` for rows that are padding / invalid for
                that agent (agents may hold datasets of different sizes).
        """
        if mask is not None:
            mask = as_mask("mask", mask, "[N, n_agents]")
        self.check_batch(obs, action, next_obs, mask)
        if mask is not None:  # masked rows may hold anything (NaN padding): zero them out
            keep = mask.unsqueeze(-1)
            obs, action, next_obs = (
                torch.where(keep, v, torch.zeros_like(v)) for v in (obs, action, next_obs)
            )
        inputs = torch.cat([obs, action], dim=-1).transpose(0, 1)  # [I, N, in]
        delta = (next_obs - obs).transpose(0, 1)  # [I, N, obs]
        if mask is None:
            weight = torch.ones(inputs.shape[:2], dtype=inputs.dtype, device=inputs.device)
        else:
            weight = mask.transpose(0, 1).to(inputs.dtype)
        count = weight.sum(1, keepdim=True).clamp_min(1.0).unsqueeze(-1)  # [I, 1, 1]
        w = weight.unsqueeze(-1)
        for data, mean_buf, std_buf in (
            (inputs, self.input_mean, self.input_std),
            (delta, self.output_mean, self.output_std),
        ):
            mean = (data * w).sum(1, keepdim=True) / count
            var = ((data - mean).pow(2) * w).sum(1, keepdim=True) / count
            std = var.sqrt()
            std = torch.where(std < 1e-6, torch.ones_like(std), std)
            mean_buf.copy_(mean.unsqueeze(1))
            std_buf.copy_(std.unsqueeze(1))

    def check_batch(
        self,
        obs: torch.Tensor,
        action: torch.Tensor,
        next_obs: torch.Tensor | None = None,
        mask: torch.Tensor | None = None,
    ) -> None:
        """Validate ``[N, I, *]`` training tensors (dtype, shape and finiteness) and the bool
        (or 0/1) ``[N, I]`` mask."""
        expected = {"obs": self.obs_dim, "action": self.action_dim, "next_obs": self.obs_dim}
        tensors = {"obs": obs, "action": action, "next_obs": next_obs}
        for name, value in tensors.items():
            if value is None:
                continue
            check_real(name, value, f"[N, n_agents={self.n_agents}, {expected[name]}]")
            if (
                value.ndim != 3
                or value.shape[1] != self.n_agents
                or value.shape[2] != expected[name]
            ):
                raise ValueError(
                    f"{name} must be shaped [N, n_agents={self.n_agents}, {expected[name]}], "
                    f"got {tuple(value.shape)}."
                )
            if value.shape[0] != obs.shape[0]:
                raise ValueError(f"{name} has {value.shape[0]} rows, obs has {obs.shape[0]}.")
        if mask is not None and tuple(mask.shape) != tuple(obs.shape[:2]):
            raise ValueError(
                f"mask must be shaped {tuple(obs.shape[:2])}, got {tuple(mask.shape)}."
            )
        if mask is not None:
            mask = as_mask("mask", mask, f"{tuple(obs.shape[:2])}")
        for name, value in tensors.items():
            if value is not None:
                if mask is not None:
                    value = torch.where(mask.unsqueeze(-1), value, torch.zeros_like(value))
                check_finite(f"training batch '{name}'", value, agent_dim=1)

    # ------------------------------------------------------------------ core computation
    def _batched_params(self, dtype: torch.dtype) -> list[tuple[torch.Tensor, torch.Tensor]]:
        """Per layer ``(weight [G*B, in, out], bias [G*B, 1, out])`` in ``dtype``.

        Inside :meth:`frozen_parameters` the copies made on entry; otherwise fresh views
        (gradients flow) or, in another dtype, fresh detached casts.
        """
        if self._param_cache is not None and self._param_cache[0] == dtype:
            return self._param_cache[1]
        if not isinstance(dtype, torch.dtype):  # not on a planner's cached path: no cost there
            raise TypeError(
                f"dtype must be a torch.dtype (e.g. torch.bfloat16) or None, got {dtype!r}"
            )
        if dtype == self.weights[0].dtype:
            return [
                (w.flatten(0, 1), b.flatten(0, 1))
                for w, b in zip(self.weights, self.biases, strict=True)
            ]
        with torch.no_grad():
            return [
                (w.detach().flatten(0, 1).to(dtype), b.detach().flatten(0, 1).to(dtype))
                for w, b in zip(self.weights, self.biases, strict=True)
            ]

    @contextlib.contextmanager
    def frozen_parameters(self, dtype: torch.dtype | None = None) -> Iterator[None]:
        """Within the block, :meth:`predict` in ``dtype`` (default: the parameters') reuses one
        detached copy of the parameters cast on entry, instead of casting at every call (a
        planner calls it ``H`` times per CEM iteration). The parameters must not change inside
        the block. The copy is dropped on exit: optimisers update parameters in place, and a
        fused Adam does not bump their version counters, so no cache can outlive a block."""
        dtype = self.weights[0].dtype if dtype is None else dtype
        if self._param_cache is not None and self._param_cache[0] == dtype:
            yield  # nested: the outer block's copy is still valid
            return
        outer = self._param_cache
        with torch.no_grad():
            self._param_cache = (
                dtype,
                [(w.detach(), b.detach()) for w, b in self._batched_params(dtype)],
            )
        try:
            yield
        finally:
            self._param_cache = outer

    def _workspace(self, rows: int, dtype: torch.dtype, device: torch.device) -> list[torch.Tensor]:
        """Two flat buffers for ``rows`` x widest hidden layer, reused while the size fits.

        While a CUDA graph is being captured the buffers are the graph's own (allocated in its
        pool, not cached): a cached buffer that an eager call later replaced would be freed
        under the graph."""
        size = rows * max(self.hidden)
        if device.type == "cuda" and torch.cuda.is_current_stream_capturing():
            return [torch.empty(size, dtype=dtype, device=device) for _ in range(2)]
        ws = self._buffers_cache
        if ws is None or ws[0].numel() < size or ws[0].dtype != dtype or ws[0].device != device:
            ws = [torch.empty(size, dtype=dtype, device=device) for _ in range(2)]
            self._buffers_cache = ws
        return ws

    def normalized_forward(
        self, x: torch.Tensor, dtype: torch.dtype | None = None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Run the ``I * B`` MLPs on normalised inputs.

        Args:
            x: normalised inputs ``[I, B, N, obs + act]``.
            dtype: compute dtype of the matrix products (default: the parameters' dtype);
                outputs are returned in the parameters' dtype.

        Returns:
            ``(mean, logvar)`` of the normalised delta, each ``[I, B, N, obs]``; the
            log-variance is softly bounded by the learned ``max_logvar`` / ``min_logvar``.
        """
        n_agents, members, rows, in_dim = x.shape
        param_dtype = self.weights[0].dtype
        dtype = param_dtype if dtype is None else dtype
        flat = self._batched_params(dtype)  # [G*B, in, out] with G = 1 when shared
        if self.share_across_agents:
            # [I, B, N, in] -> [B, I*N, in]: one bmm over the B shared members.
            h = x.transpose(0, 1).reshape(members, n_agents * rows, in_dim).to(dtype)
        else:
            h = x.reshape(n_agents * members, rows, in_dim).to(dtype)
        last = len(flat) - 1
        if torch.is_grad_enabled() or torch.compiler.is_compiling():
            # (a compiled graph plans its own buffers and fuses bias + SiLU)
            for layer, (weight, bias) in enumerate(flat):
                h = torch.baddbmm(bias, h, weight)
                if layer < last:
                    h = F.silu(h)
        else:
            # Inference: hidden activations ping-pong between two reused buffers (large fresh
            # allocations page-fault on every planning step); bias fused into the GEMM
            # (baddbmm), SiLU in place.
            buffers = self._workspace(h.shape[0] * h.shape[1], dtype, h.device)
            for layer, (weight, bias) in enumerate(flat):
                if layer < last:
                    shape = (h.shape[0], h.shape[1], weight.shape[-1])
                    out = buffers[layer % 2][: math.prod(shape)].view(shape)
                    h = F.silu(torch.baddbmm(bias, h, weight, out=out), inplace=True)
                else:
                    h = torch.baddbmm(bias, h, weight)
        out = h.to(param_dtype)
        if self.share_across_agents:
            out = out.reshape(members, n_agents, rows, -1).transpose(0, 1)
        else:
            out = out.reshape(n_agents, members, rows, -1)
        mean, raw_logvar = out.split(self.obs_dim, dim=-1)
        # PETS soft bounds: logvar = max - softplus(max - raw); logvar = min + softplus(. - min).
        logvar = self.max_logvar - F.softplus(self.max_logvar - raw_logvar)
        logvar = self.min_logvar + F.softplus(logvar - self.min_logvar)
        return mean, logvar

    def normalize_inputs(self, obs: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        """``[I, ..., obs]``, ``[I, ..., act]`` -> normalised inputs ``[I, ..., obs + act]``."""
        x = torch.cat([obs, action], dim=-1)
        view = (self.n_agents, *([1] * (x.ndim - 2)), x.shape[-1])
        return (x - self.input_mean.view(view)) / self.input_std.view(view)

    def predict(
        self,
        obs: torch.Tensor,
        action: torch.Tensor,
        dtype: torch.dtype | None = None,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Raw-tensor fast path: per-member delta distribution in real units.

        Args:
            obs: ``[I, B, N, obs]`` (``N`` rows per member; a size-1 member dim broadcasts).
            action: ``[I, B, N, act]``.
            dtype: compute dtype of the MLP (e.g. ``torch.bfloat16``); outputs stay in the
                parameters' dtype.

        Returns:
            ``(delta_mean, delta_logvar)``, each ``[I, B, N, obs]``.

        Raises:
            ValueError: ``dtype`` is an integer or bool torch dtype, or ``obs`` / ``action``
                are not ``[I, B or 1, N, obs]`` / ``[I, B or 1, N, act]`` (checked on the
                shapes only: no device sync).
            TypeError: ``dtype`` is not a torch dtype.
        """
        if isinstance(dtype, torch.dtype) and not dtype.is_floating_point:
            raise ValueError(f"dtype must be a floating-point torch dtype or None, got {dtype!r}.")
        for name, tensor, width in (
            ("obs", obs, self.obs_dim),
            ("action", action, self.action_dim),
        ):
            if tensor.ndim != 4 or tensor.shape[0] != self.n_agents or tensor.shape[-1] != width:
                raise ValueError(
                    f"{name} must be [I={self.n_agents}, B, N, {width}], got {tuple(tensor.shape)}."
                )
        x = self.normalize_inputs(obs, action)
        if x.shape[1] != self.ensemble_size:
            x = x.expand(-1, self.ensemble_size, -1, -1)
        mean, logvar = self.normalized_forward(x, dtype)
        delta_mean = torch.addcmul(self.output_mean, mean, self.output_std)
        delta_logvar = logvar + 2.0 * torch.log(self.output_std)
        return delta_mean, delta_logvar

    # ------------------------------------------------------------------ TensorDict API
    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        """Write per-member predictions ``[*, I, B, obs]`` for inputs ``[*, I, obs/act]``
        (float, finite: checked here, once per call)."""
        obs_shape = f"[*, {self.n_agents}, {self.obs_dim}]"
        act_shape = f"[*, {self.n_agents}, {self.action_dim}]"
        obs = get_tensor(tensordict, self.in_keys[0], obs_shape, type(self).__name__)
        action = get_tensor(tensordict, self.in_keys[1], act_shape, type(self).__name__)
        check_real(repr(self.in_keys[0]), obs, obs_shape)
        check_real(repr(self.in_keys[1]), action, act_shape)
        if obs.ndim < 2 or obs.shape[-2:] != (self.n_agents, self.obs_dim):
            raise ValueError(
                f"{self.in_keys[0]} must be shaped [*, {self.n_agents}, {self.obs_dim}], "
                f"got {tuple(obs.shape)}."
            )
        if action.shape[:-1] != obs.shape[:-1] or action.shape[-1] != self.action_dim:
            raise ValueError(
                f"{self.in_keys[1]} must be shaped [*, {self.n_agents}, {self.action_dim}], "
                f"got {tuple(action.shape)}."
            )
        names = [repr(key) for key in self.in_keys]
        check_finite_many({names[0]: obs, names[1]: action}, agent_dim=-2)
        batch = obs.shape[:-2]
        # [*, I, d] -> [I, 1, N, d]
        flat_obs = obs.reshape(-1, self.n_agents, self.obs_dim).transpose(0, 1).unsqueeze(1)
        flat_act = action.reshape(-1, self.n_agents, self.action_dim).transpose(0, 1).unsqueeze(1)
        mean, logvar = self.predict(flat_obs, flat_act)
        # [I, B, N, obs] -> [*, I, B, obs]
        shape = (*batch, self.n_agents, self.ensemble_size, self.obs_dim)
        tensordict.set(self.out_keys[0], mean.permute(2, 0, 1, 3).reshape(shape))
        tensordict.set(self.out_keys[1], logvar.permute(2, 0, 1, 3).reshape(shape))
        return tensordict
