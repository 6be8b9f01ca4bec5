"""Per-timestep coalition sampling (Han et al., Algorithm 1 line 6)."""

from __future__ import annotations

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from tensordict.utils import NestedKey
from torchrl.envs.utils import ExplorationType, exploration_type

from mapets_rl.modules.arguments import require_positive_ints
from mapets_rl.modules.tensor_checks import as_mask

__all__ = ["RandomCoalition", "uniform_size_coalition"]

_EVAL_MODES = ("grand", "empty", "random")
_SIZE_LAWS = ("binomial", "uniform")


class RandomCoalition(TensorDictModuleBase):
    """Writes the coalition ``C`` of the current timestep, ``coalition [*, n]`` (bool).

    While collecting (``ExplorationType.RANDOM``) the coalition is drawn by ``sizes``:

    - ``"binomial"`` (the paper's Algorithm 1 line 6): every alive agent joins independently with
      probability ``join_prob`` (``0.5`` samples uniformly over all ``2**n`` coalitions, so their
      sizes are Bin(n, 1/2): at n = 30, 90% of them have 11-19 members);
    - ``"uniform"``: the size is uniform over ``1..m`` (``m`` alive agents), then the members are
      a uniformly random set of that size. These are the sizes at which the permutation
      estimator of the Shapley value evaluates the critic (a prefix of a random ordering has a
      uniform size), so the critic is trained where ``phi`` reads it. ``join_prob`` is unused.

    Otherwise (evaluation) the coalition is ``eval_mode``: ``"grand"`` (all agents
    cooperate, as in the paper's reported results), ``"empty"`` (decentralised execution) or
    ``"random"`` (drawn as in collection). Agents whose ``mask`` is False (crashed or removed)
    are never members.

    Reads ``observation [*, n, obs]`` (for the batch shape) and, if present, ``mask [*, n]``.
    """

    def __init__(
        self,
        n_agents: int,
        *,
        join_prob: float = 0.5,
        eval_mode: str = "grand",
        sizes: str = "binomial",
        observation_key: NestedKey = ("agents", "observation"),
        mask_key: NestedKey = ("agents", "mask"),
        out_key: NestedKey = ("agents", "coalition"),
    ) -> None:
        require_positive_ints(n_agents=n_agents)
        if not 0.0 <= join_prob <= 1.0:
            raise ValueError(f"join_prob must be in [0, 1], got {join_prob}")
        if eval_mode not in _EVAL_MODES:
            raise ValueError(f"eval_mode must be one of {_EVAL_MODES}, got {eval_mode!r}")
        if sizes not in _SIZE_LAWS:
            raise ValueError(f"sizes must be one of {_SIZE_LAWS}, got {sizes!r}")
        super().__init__()
        self.n_agents = n_agents
        self.join_prob = join_prob
        self.eval_mode = eval_mode
        self.sizes = sizes
        self.mask_key = mask_key
        self.in_keys = [observation_key]
        self.out_keys = [out_key]

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        obs = tensordict.get(self.in_keys[0])
        shape = (*obs.shape[:-2], self.n_agents)
        mode = "random" if exploration_type() is ExplorationType.RANDOM else self.eval_mode
        mask = tensordict.get(self.mask_key, None)
        alive = (
            torch.ones(shape, dtype=torch.bool, device=obs.device)
            if mask is None
            else as_mask(repr(self.mask_key), mask, f"{list(shape)}").expand(shape)
        )
        if mode == "random" and self.sizes == "uniform":
            coalition = uniform_size_coalition(alive)
        elif mode == "random":
            coalition = torch.rand(shape, device=obs.device) < self.join_prob
        else:
            coalition = torch.full(shape, mode == "grand", dtype=torch.bool, device=obs.device)
        tensordict.set(self.out_keys[0], coalition & alive)
        return tensordict


def uniform_size_coalition(alive: torch.Tensor) -> torch.Tensor:
    """A random coalition of the ``alive`` agents whose size is uniform over ``1..m``.

    Args:
        alive: bool ``[*, n]``; ``m`` = its number of True entries per row.

    Returns:
        bool ``[*, n]``: a uniformly random subset of the alive agents of a size drawn uniformly
        from ``1..m`` (empty where ``m = 0``).
    """
    keys = torch.rand(alive.shape, device=alive.device).masked_fill(~alive, 2.0)
    rank = keys.argsort(-1).argsort(-1)  # alive agents first, in random order
    count = alive.sum(-1, keepdim=True)
    size = (torch.rand(count.shape, device=alive.device) * count).floor() + 1
    return (rank < size) & alive
