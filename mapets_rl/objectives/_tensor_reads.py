"""Checked reads of a loss's input keys, shared by the on-policy losses (COMA, SVMIX)."""

from __future__ import annotations

import torch
from tensordict import TensorDictBase
from tensordict.utils import NestedKey, unravel_key

from mapets_rl.modules.tensor_checks import as_mask, get_tensor

__all__ = ["CheckedReads"]


class CheckedReads:
    """Mixin for a :class:`~torchrl.objectives.LossModule`: ``_get`` and ``_flags`` read a key
    of the loss's input with a one-line error that names the key, the expected shape
    (``expected``, e.g. ``"[*, T, 1]"``) and the loss's class."""

    def _get(self, tensordict: TensorDictBase, key: NestedKey, expected: str) -> torch.Tensor:
        """``tensordict[key]``; a one-line ValueError naming ``key`` when it is missing."""
        return get_tensor(tensordict, key, expected, type(self).__name__)

    def _flags(self, tensordict: TensorDictBase, key: NestedKey, expected: str) -> torch.Tensor:
        """``tensordict[key]`` as bool; ValueError if missing or holding values other than 0/1."""
        return as_mask(repr(unravel_key(key)), self._get(tensordict, key, expected), expected)
