"""Observation standardisation with running statistics, as a module and as the
TensorDictModule writing ``("agents", "observation_normalized")``."""

from __future__ import annotations

import torch
from tensordict.nn import TensorDictModule
from torch import nn

from mapets_rl.modules.agents import AgentGroupSpec
from mapets_rl.modules.keys import OBS, OBS_NORM


class RunningObsNorm(nn.Module):
    """Per-feature observation standardisation with running statistics (Chan et al.'s parallel
    mean/variance update), shared by the agents: ``(obs - mean) / sqrt(var + eps)``, clipped
    to ``[-clip, clip]``. Statistics change only through :meth:`update` (called by the recipe
    on collected data), so the module is a fixed function between updates and its buffers
    travel with checkpoints and policy-weight syncs.

    Args:
        obs_dim: feature size (the last dim of the observation).
        eps: variance floor (> 0).
        clip: output clip (> 0).
    """

    def __init__(self, obs_dim: int, eps: float = 1e-6, clip: float = 10.0) -> None:
        super().__init__()
        if obs_dim < 1:
            raise ValueError(f"obs_dim must be >= 1, got {obs_dim}")
        if eps <= 0 or clip <= 0:
            raise ValueError(f"eps and clip must be > 0, got eps={eps}, clip={clip}")
        self.eps, self.clip = eps, clip
        self.register_buffer("mean", torch.zeros(obs_dim))
        self.register_buffer("var", torch.ones(obs_dim))
        self.register_buffer("count", torch.zeros(()))

    @torch.no_grad()
    def update(self, obs: torch.Tensor, mask: torch.Tensor | None = None) -> None:
        """Fold ``obs`` [..., obs_dim] into the statistics (rows whose ``mask`` [...] is False,
        e.g. crashed agents, are skipped)."""
        x = obs.reshape(-1, obs.shape[-1]).to(self.mean.dtype)
        if mask is not None:
            x = x[mask.reshape(-1)]
        n = x.shape[0]
        if n == 0:
            return
        batch_mean, batch_var = x.mean(0), x.var(0, unbiased=False)
        total = self.count + n
        delta = batch_mean - self.mean
        self.var.copy_(
            (self.var * self.count + batch_var * n + delta.pow(2) * self.count * n / total) / total
        )
        self.mean.add_(delta * n / total)
        self.count.copy_(total)

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        return ((obs - self.mean) / (self.var + self.eps).sqrt()).clamp(-self.clip, self.clip)


def make_obs_norm(spec: AgentGroupSpec) -> tuple[RunningObsNorm, TensorDictModule]:
    """A running observation normaliser and the module writing ``("agents",
    "observation_normalized")`` [*, I, obs] from ``("agents", "observation")``."""
    norm = RunningObsNorm(spec.obs_dim)
    return norm, TensorDictModule(norm, in_keys=[OBS], out_keys=[OBS_NORM])


@torch.no_grad()
def sync_target_statistics(loss: nn.Module, norm: RunningObsNorm) -> int:
    """Copy ``norm``'s running statistics into every target-network copy that ``loss`` keeps.

    A torchrl loss with target networks (``DDPGLoss``, ``SACLoss``, ...) clones the networks'
    parameters *and buffers* into ``target_*_params`` and moves them by soft updates. The
    normaliser's statistics are not learned parameters: a target copy that lags them feeds the
    target network inputs standardised with stale statistics (at the start of training, the
    initial mean 0 / variance 1, so raw gaps in metres hit the clip), and the TD targets it
    produces are off-distribution. Call this after every :meth:`RunningObsNorm.update`; soft
    updates then leave the (equal) copies unchanged.

    Args:
        loss: a torchrl ``LossModule``; every ``<name>_params`` with a ``target_<name>_params``
            is searched for the normaliser's buffers (matched by storage, so any nesting works).
        norm: the normaliser shared by the loss's networks.

    Returns:
        The number of target entries written (0 when the loss keeps no target copy of ``norm``).
    """
    buffers = {buf.data_ptr() for buf in norm.buffers()}
    written = 0
    for name in dir(loss):
        if not name.startswith("target_") or not name.endswith("_params"):
            continue
        target, online = getattr(loss, name), getattr(loss, name[len("target_") :], None)
        if online is None or target is None:
            continue
        for key, value in online.items(True, True):
            if value.data_ptr() in buffers:
                target.get(key).copy_(value)
                written += 1
    return written
