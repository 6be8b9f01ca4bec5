"""Tile coding of observations and actions: the MA-PETS paper's discretised variant (sec. VI,
"MA-PETS with tile coding", the check of its tabular Assumption 1).

A :class:`TileCoder` covers the box ``[low, high]`` (``D`` dimensions) with ``tilings``
uniform grids of ``bins`` tiles per dimension, tiling ``k`` shifted by ``k / tilings`` of a tile
(Sutton & Barto, sec. 9.5.4, one-dimensional tilings per variable). A point's discrete state is
its active tile in every tiling and dimension (:meth:`TileCoder.tiles`, the paper's bit vector
has a 1 exactly there); the intersection of the active tiles is a cell ``width / tilings``
wide, and :meth:`TileCoder.quantise` maps the point to that cell's centre, the representative
of its discrete state. Every point of one cell has the same tiles, so quantising is idempotent
and loses at most half a cell per dimension.

:class:`TileCodedObservation` is the TorchRL transform that hands the agents quantised
observations; :func:`action_quantiser` is the policy step that makes the executed (and stored)
actions discrete. :class:`TileCodingConfig` is the MA-PETS recipe's ``tile_coding`` section.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModule
from tensordict.utils import NestedKey
from torch import Tensor, nn
from torchrl.data import TensorSpec
from torchrl.envs.transforms import Transform

from mapets_rl.config import ConfigSection, check


@dataclasses.dataclass(frozen=True)
class TileCodingConfig(ConfigSection):
    """The discretised variant of MA-PETS (off by default).

    Attributes:
        tilings: tilings per dimension; ``0`` keeps observations and actions continuous (the
            paper's main method). With ``tilings >= 1`` every observation feature takes
            ``bins * tilings`` values and every action dimension ``action_bins * tilings``.
        bins: tiles per dimension and tiling of an observation feature. The resolution that
            matters is the observation's: on the figure-eight a 0.1 s step moves a gap by at
            most 1.4 m, and with ``bins=8, tilings=4`` (32 values, 2.5 m gap cells) most
            transitions show no change and then a jump, the model's NLL stays ~25 nats above
            the continuous model's and safety falls to 0.61 (continuous 0.93; 3 seeds, 10
            episodes); ``bins=64`` (256 values) kept one seed within 0.07 of continuous
            (``docs/results/ablations.md``, tile-coded MA-PETS).
        action_bins: tiles per dimension and tiling of an action dimension.
        obs_low: lower bounds of the observation features (``None``: the figure-eight's,
            from :func:`mapets_rl.envs.figure_eight_observation_bounds`; required on other
            scenarios).
        obs_high: upper bounds, as ``obs_low``.
    """

    tilings: int = 0
    bins: int = 8
    action_bins: int = 8
    obs_low: list[float] | None = None
    obs_high: list[float] | None = None

    def __post_init__(self) -> None:
        super().__post_init__()
        check(self.tilings >= 0, "tilings", ">= 0 (0: continuous)", self.tilings)
        check(self.bins >= 1, "bins", ">= 1", self.bins)
        check(self.action_bins >= 1, "action_bins", ">= 1", self.action_bins)
        check(
            (self.obs_low is None) == (self.obs_high is None),
            "obs_low",
            "given together with obs_high (or both None)",
            self.obs_low,
        )
        if self.obs_low is not None and self.obs_high is not None:
            check(
                len(self.obs_low) == len(self.obs_high)
                and all(lo < hi for lo, hi in zip(self.obs_low, self.obs_high, strict=True)),
                "obs_high",
                f"as long as obs_low ({len(self.obs_low)}) and above it in every feature",
                self.obs_high,
            )

    @property
    def enabled(self) -> bool:
        return self.tilings > 0


class TileCoder(nn.Module):
    """Tile coding of the box ``[low, high]`` (``D`` dimensions).

    Args:
        low: ``[D]`` lower bounds (finite).
        high: ``[D]`` upper bounds, each above its ``low``.
        bins: tiles per dimension and tiling (>= 1).
        tilings: tilings, each shifted by ``1 / tilings`` of a tile (>= 1).

    Points outside the box are clamped onto it first.
    """

    def __init__(
        self, low: Sequence[float] | Tensor, high: Sequence[float] | Tensor, bins: int, tilings: int
    ) -> None:
        super().__init__()
        low_t = torch.as_tensor(low, dtype=torch.float32).flatten()
        high_t = torch.as_tensor(high, dtype=torch.float32).flatten()
        if low_t.shape != high_t.shape or low_t.numel() == 0:
            raise ValueError(
                f"low and high must be non-empty and of one shape, got {tuple(low_t.shape)} "
                f"and {tuple(high_t.shape)}"
            )
        if not bool(torch.isfinite(low_t).all() & torch.isfinite(high_t).all()):
            raise ValueError("low and high must be finite (tile coding covers a bounded box)")
        if not bool((high_t > low_t).all()):
            raise ValueError(f"high must exceed low in every dimension, got {low_t} and {high_t}")
        if bins < 1:
            raise ValueError(f"bins must be >= 1, got {bins}")
        if tilings < 1:
            raise ValueError(f"tilings must be >= 1, got {tilings}")
        self.bins, self.tilings = int(bins), int(tilings)
        self.register_buffer("low", low_t)
        self.register_buffer("high", high_t)
        self.register_buffer("width", (high_t - low_t) / bins)
        self.register_buffer("offsets", torch.arange(tilings, dtype=torch.float32) / tilings)

    @property
    def levels(self) -> int:
        """Values a dimension can take after :meth:`quantise`: ``bins * tilings``."""
        return self.bins * self.tilings

    def _tile_units(self, x: Tensor) -> Tensor:
        """``x`` ``[..., D]`` in tile widths from ``low``, inside ``[0, bins)``."""
        z = (x - self.low.to(x.dtype)) / self.width.to(x.dtype)
        return z.clamp(0.0, self.bins - 0.5 / self.tilings)

    def tiles(self, x: Tensor) -> Tensor:
        """Active tile of every tiling: ``x`` ``[..., D]`` -> int64 ``[..., D, tilings]`` in
        ``[0, bins]`` (a shifted tiling has ``bins + 1`` tiles)."""
        z = self._tile_units(x)
        return torch.floor(z.unsqueeze(-1) + self.offsets.to(x.dtype)).long()

    def quantise(self, x: Tensor) -> Tensor:
        """Centre of the intersection of ``x``'s active tiles: ``[..., D]`` -> ``[..., D]``."""
        offsets = self.offsets.to(x.dtype)
        starts = self.tiles(x).to(x.dtype) - offsets  # [..., D, T], in tile widths from low
        centre = 0.5 * (starts.amax(-1) + (starts + 1.0).amin(-1))
        return self.low.to(x.dtype) + centre * self.width.to(x.dtype)


class TileCodedObservation(Transform):
    """Replaces the observation at ``in_keys`` by its :meth:`TileCoder.quantise` (at reset and
    after every step); shapes and specs are unchanged.

    Args:
        coder: the observation's :class:`TileCoder` (``D`` = the observation's last dimension).
        in_keys: observation keys (default ``("agents", "observation")``), each ``[*B, I, D]``.
    """

    def __init__(
        self, coder: TileCoder, in_keys: Sequence[NestedKey] = (("agents", "observation"),)
    ) -> None:
        super().__init__(in_keys=list(in_keys), out_keys=list(in_keys))
        self.coder = coder

    def _apply_transform(self, observation: Tensor) -> Tensor:
        return self.coder.quantise(observation)

    def _reset(
        self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase
    ) -> TensorDictBase:
        return self._call(tensordict_reset)

    def transform_observation_spec(self, observation_spec: TensorSpec) -> TensorSpec:
        return observation_spec


def action_quantiser(coder: TileCoder, key: NestedKey = ("agents", "action")) -> TensorDictModule:
    """Policy step that replaces the action at ``key`` (``[*B, I, A]``) by its
    :meth:`TileCoder.quantise`; append it to a continuous policy to make it act on the grid."""
    return TensorDictModule(coder.quantise, in_keys=[key], out_keys=[key])
