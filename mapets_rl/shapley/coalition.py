"""Per-timestep coalition sampling (Han et al., Algorithm 1 line 6)."""

from __future__ import annotations

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from tensordict.utils import NestedKey
from torchrl.envs.utils import ExplorationType, exploration_type

from mapets_rl.modules.arguments import require_positive_ints
from mapets_rl.modules.tensor_checks import as_mask

__all__ = ["RandomCoalition"]

_EVAL_MODES = ("grand", "empty", "random")


class RandomCoalition(TensorDictModuleBase):
    """Writes the coalition ``C`` of the current timestep, ``coalition [*, n]`` (bool).

    While collecting (``ExplorationType.RANDOM``) every alive agent joins independently with
    probability ``join_prob`` (``0.5`` samples uniformly over all ``2**n`` coalitions, Algorithm 1
    line 6). Otherwise (evaluation) the coalition is ``eval_mode``: ``"grand"`` (all agents
    cooperate, as in the paper's reported results), ``"empty"`` (decentralised execution) or
    ``"random"``. Agents whose ``mask`` is False (crashed or removed) are never members.

    Reads ``observation [*, n, obs]`` (for the batch shape) and, if present, ``mask [*, n]``.
    """

    def __init__(
        self,
        n_agents: int,
        *,
        join_prob: float = 0.5,
        eval_mode: str = "grand",
        observation_key: NestedKey = ("agents", "observation"),
        mask_key: NestedKey = ("agents", "mask"),
        out_key: NestedKey = ("agents", "coalition"),
    ) -> None:
        require_positive_ints(n_agents=n_agents)
        if not 0.0 <= join_prob <= 1.0:
            raise ValueError(f"join_prob must be in [0, 1], got {join_prob}")
        if eval_mode not in _EVAL_MODES:
            raise ValueError(f"eval_mode must be one of {_EVAL_MODES}, got {eval_mode!r}")
        super().__init__()
        self.n_agents = n_agents
        self.join_prob = join_prob
        self.eval_mode = eval_mode
        self.mask_key = mask_key
        self.in_keys = [observation_key]
        self.out_keys = [out_key]

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        obs = tensordict.get(self.in_keys[0])
        shape = (*obs.shape[:-2], self.n_agents)
        mode = "random" if exploration_type() is ExplorationType.RANDOM else self.eval_mode
        if mode == "random":
            coalition = torch.rand(shape, device=obs.device) < self.join_prob
        else:
            coalition = torch.full(shape, mode == "grand", dtype=torch.bool, device=obs.device)
        mask = tensordict.get(self.mask_key, None)
        if mask is not None:
            coalition = coalition & as_mask(repr(self.mask_key), mask, f"{list(shape)}")
        tensordict.set(self.out_keys[0], coalition)
        return tensordict
