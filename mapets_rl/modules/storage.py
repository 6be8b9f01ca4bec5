"""Replay storage whose checkpoints hold only what was written.

torchrl's :class:`~torchrl.data.LazyTensorStorage` allocates all ``max_size`` rows with
``torch.empty`` on the first write, and its ``state_dict`` returns them all: a checkpoint of a
buffer filled to 4% held 96% leftover heap bytes (different between identical runs, and the
process's old memory written to disk). :class:`FilledTensorStorage` saves the rows written so far
and restores the rest as zeros, so identical runs write identical checkpoints, and small buffers
small ones.
"""

from __future__ import annotations

from typing import Any

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import LazyTensorStorage

from mapets_rl._console import torchrl_info_dropped

__all__ = ["FilledTensorStorage"]


class FilledTensorStorage(LazyTensorStorage):
    """A :class:`~torchrl.data.LazyTensorStorage` (one batch dimension) whose ``state_dict``
    holds only its filled rows ``[0, len(self))`` (a round-robin writer fills them in order
    before it wraps around), as ``{"rows", "data"}`` with ``data`` a nested dict of tensors (or
    a tensor). :meth:`load_state_dict` puts them back and zeroes the rows after them; it also
    reads the state of a plain ``LazyTensorStorage`` (every row)."""

    def _init(self, data: TensorDictBase | torch.Tensor) -> None:
        """torchrl's allocation on the first write, without its INFO line on stdout."""
        with torchrl_info_dropped():
            super()._init(data)

    def state_dict(self) -> dict[str, Any]:
        """``{"rows", "data", "initialized", "_len"}``; see the class docstring."""
        state = super().state_dict()
        storage = self._storage
        if not self.initialized or storage is None or self.ndim != 1:
            return state
        rows = len(self)
        if isinstance(storage, TensorDictBase):
            data: Any = storage[:rows].clone().to_dict()
        elif isinstance(storage, torch.Tensor):
            data = storage[:rows].clone()  # a view would save the whole underlying storage
        else:
            return state
        return {"rows": rows, "data": data, "initialized": True, "_len": state["_len"]}

    def load_state_dict(self, state_dict: dict[str, Any]) -> None:
        """Restore :meth:`state_dict` output (or a ``LazyTensorStorage``'s)."""
        if "data" not in state_dict:
            super().load_state_dict(state_dict)
            return
        rows, data = int(state_dict["rows"]), state_dict["data"]
        filled = data if isinstance(data, torch.Tensor) else TensorDict(data, batch_size=[rows])
        size = max(int(self.max_size), rows)
        if isinstance(filled, torch.Tensor):
            full: Any = filled.new_zeros((size, *filled.shape[1:]))
        else:
            full = filled.new_zeros(size)
        full[:rows] = filled
        if isinstance(full, TensorDictBase):
            full = full.state_dict()
        super().load_state_dict(
            {"_storage": full, "initialized": True, "_len": int(state_dict["_len"])}
        )
