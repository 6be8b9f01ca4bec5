"""Checks of the tensors a public module reads at its boundary (a ``forward`` / ``plan`` /
loss entry), each raising a one-line ``ValueError`` or ``TypeError`` that names the key or
argument, what is expected and what was given.

They run once per call, at entry: a finiteness or 0/1 check costs one device-to-host sync
(bool masks none), so none of them belongs in a per-iteration loop."""

from __future__ import annotations

from collections.abc import Mapping

import torch
from tensordict import TensorDictBase
from tensordict.utils import NestedKey, unravel_key

__all__ = [
    "as_mask",
    "check_finite",
    "check_finite_many",
    "check_real",
    "get_tensor",
]


def get_tensor(
    tensordict: TensorDictBase, key: NestedKey, expected: str, owner: str
) -> torch.Tensor:
    """``tensordict[key]``; ``ValueError`` naming ``key`` and ``expected`` (e.g. ``"[*, 3, 4]"``)
    if it is missing, ``TypeError`` if it is not a tensor. ``owner`` names the reader."""
    value = tensordict.get(key, None)
    key = unravel_key(key)  # ("next", ("agents", "reward")) -> ("next", "agents", "reward")
    if value is None:
        raise ValueError(f"{owner} needs {key!r} {expected} in its input; the key is missing")
    if not isinstance(value, torch.Tensor):
        raise TypeError(f"{key!r} must be a tensor {expected}, got a {type(value).__name__}")
    return value


def check_real(name: str, value: torch.Tensor, expected: str = "") -> None:
    """``TypeError`` unless ``value`` is a tensor of real numbers (float or int; bool and
    complex refused: a bool tensor is a mask, not a quantity)."""
    if not isinstance(value, torch.Tensor):
        raise TypeError(f"{name} must be a real tensor {expected}, got a {type(value).__name__}")
    if value.dtype == torch.bool or value.is_complex():
        shape = f" {expected}" if expected else ""
        raise TypeError(f"{name} must be a float (or int) tensor{shape}, got dtype {value.dtype}")


def check_finite(name: str, value: torch.Tensor, agent_dim: int | None = None) -> None:
    """``ValueError`` naming ``name`` if ``value`` holds NaN or inf (one host sync).

    Args:
        name: the parameter / key name used in the message.
        value: the tensor.
        agent_dim: index of the agent dimension: the message names the offending agents;
            ``None``: it counts the offending entries.
    """
    finite = torch.isfinite(value)
    if bool(finite.all()):
        return
    if agent_dim is None or value.ndim == 0:
        bad = int((~finite).sum())
        raise ValueError(
            f"{name} must be finite, got {bad} NaN or infinite entries of {value.numel()}"
        )
    dims = [d for d in range(value.ndim) if d != agent_dim % value.ndim]
    bad_agents = (~finite).any(dim=dims) if dims else ~finite
    agents = torch.nonzero(bad_agents).flatten().tolist()
    raise ValueError(f"{name} contains NaN or inf values for agent(s) {agents}; clean the batch.")


def check_finite_many(tensors: Mapping[str, torch.Tensor], agent_dim: int | None = None) -> None:
    """:func:`check_finite` of each of ``tensors`` (``name -> tensor``) with one host sync
    when all are finite."""
    flags = [torch.isfinite(v).all() for v in tensors.values() if v.is_floating_point()]
    if not flags or bool(torch.stack(flags).all()):
        return
    for name, value in tensors.items():
        check_finite(name, value, agent_dim)


def as_mask(name: str, mask: torch.Tensor, expected: str = "") -> torch.Tensor:
    """``mask`` as a bool tensor. A bool tensor is returned as is (no sync); a numeric one must
    hold only 0 and 1 (one sync), else ``ValueError``: casting 0.5 or 2 to ``True`` would
    silently turn a weight into membership."""
    if not isinstance(mask, torch.Tensor):
        raise TypeError(f"{name} must be a bool tensor {expected}, got a {type(mask).__name__}")
    if mask.dtype == torch.bool:
        return mask
    if mask.is_complex() or not bool(((mask == 0) | (mask == 1)).all()):
        shape = f" {expected}" if expected else ""
        bad = mask[(mask != 0) & (mask != 1)].flatten()[:3].tolist()
        raise ValueError(
            f"{name} must be a bool tensor{shape} (or hold only 0 and 1), got dtype "
            f"{mask.dtype} with values such as {bad}"
        )
    return mask.bool()
