"""A discrete action set over a continuous action space: the value-based baselines (``dqn``)
choose one of ``K`` actions per agent, and an action map turns the choice into the continuous
action the scenario takes.

:func:`action_grid` lays the grid (a product of evenly spaced levels per action dimension, the
first dimension varying slowest); :class:`DiscreteActionMap` maps a one-hot choice
``[*, I, K]`` to its grid point ``[*, I, A]``; :func:`make_action_map` builds both for an
agent group, with the one-hot spec ``[I, K]`` that Q-value and exploration modules need.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from tensordict.nn import TensorDictModule
from torch import nn
from torchrl.data import OneHot

from mapets_rl.modules.agents import AgentGroupSpec
from mapets_rl.modules.keys import ACTION, GROUP

ACTION_CHOICE = (GROUP, "action_choice")
"""The discrete choice per agent, one-hot ``[*, I, K]`` (what a DQN learns and replays; the
continuous ``("agents", "action")`` is its image under the action map)."""


def action_grid(low: torch.Tensor, high: torch.Tensor, levels: Sequence[int]) -> torch.Tensor:
    """Every combination of ``levels[d]`` evenly spaced values in ``[low[d], high[d]]`` (both
    ends included; one level is ``low[d]``), the first dimension varying slowest.

    Args:
        low, high: ``[A]`` finite bounds with ``low <= high``.
        levels: ``A`` integers >= 1.

    Returns:
        ``[prod(levels), A]``: row ``k`` is action ``k`` of the discrete set.

    Raises:
        ValueError: bounds not ``[A]`` or not finite or ``low > high``; a level count that is not
            an integer >= 1 or a ``levels`` of another length than ``A``.
    """
    if low.ndim != 1 or low.shape != high.shape:
        raise ValueError(
            f"low and high must both have shape [A], got {tuple(low.shape)} and {tuple(high.shape)}"
        )
    if not bool(torch.isfinite(low).all() & torch.isfinite(high).all() & (low <= high).all()):
        raise ValueError(f"bounds must be finite with low <= high, got low {low} high {high}")
    if len(levels) != low.shape[0] or any(
        isinstance(n, bool) or int(n) != n or n < 1 for n in levels
    ):
        raise ValueError(
            f"levels must be {low.shape[0]} integers >= 1 (one per action dimension), "
            f"got {list(levels)}"
        )
    axes = [
        torch.linspace(float(lo), float(hi), int(n), dtype=low.dtype) if n > 1 else lo[None]
        for lo, hi, n in zip(low, high, levels, strict=True)
    ]
    return torch.cartesian_prod(*axes).reshape(-1, low.shape[0])


class DiscreteActionMap(nn.Module):
    """One-hot choice ``[*, I, K]`` -> the chosen row of ``table`` ``[*, I, A]``.

    Args:
        table: ``[K, A]`` the continuous action of each discrete one (e.g. :func:`action_grid`);
            kept as a buffer, so it travels with the module's device and state dict.
    """

    def __init__(self, table: torch.Tensor) -> None:
        super().__init__()
        if table.ndim != 2 or table.shape[0] < 1:
            raise ValueError(f"table must have shape [K >= 1, A], got {tuple(table.shape)}")
        self.register_buffer("table", table.clone())

    @property
    def n_actions(self) -> int:
        """``K``."""
        return self.table.shape[0]

    def forward(self, choice: torch.Tensor) -> torch.Tensor:
        if choice.shape[-1] != self.n_actions:
            raise ValueError(
                f"choice must be one-hot over {self.n_actions} actions [*, I, "
                f"{self.n_actions}], got {tuple(choice.shape)}"
            )
        return choice.to(self.table.dtype) @ self.table


def make_action_map(
    spec: AgentGroupSpec, speed_levels: int
) -> tuple[TensorDictModule, OneHot, torch.Tensor]:
    """The discrete action set of a continuous agent group and its map.

    The first action dimension (the figure-eight's target speed) takes ``speed_levels`` evenly
    spaced values within its bounds; every further dimension (the two-lane figure-eight's
    lane-change flag) its two bounds (flag 0: keep the lane, 1: request a change), so
    ``K = speed_levels * 2 ** (A - 1)``.

    Args:
        spec: a continuous group whose bounds are the same for every agent.
        speed_levels: levels of the first dimension (>= 1).

    Returns:
        The policy step ``ACTION_CHOICE`` ``[*, I, K]`` -> ``("agents", "action")``
        ``[*, I, A]``, the one-hot spec ``[I, K]`` of the choice and the table ``[K, A]``.

    Raises:
        ValueError: a discrete group, agents with different bounds, or ``speed_levels`` < 1.
    """
    if spec.discrete:
        raise ValueError("make_action_map needs a continuous action group; this one is one-hot")
    low, high = spec.action_spec.space.low, spec.action_spec.space.high  # [I, A]
    if not (bool((low == low[0]).all()) and bool((high == high[0]).all())):
        raise ValueError("make_action_map needs the same action bounds for every agent")
    if isinstance(speed_levels, bool) or int(speed_levels) != speed_levels or speed_levels < 1:
        raise ValueError(f"speed_levels must be an integer >= 1, got {speed_levels!r}")
    levels = [int(speed_levels)] + [2] * (spec.action_dim - 1)
    table = action_grid(low[0], high[0], levels)
    choice_spec = OneHot(table.shape[0], shape=(spec.n_agents, table.shape[0]))
    module = TensorDictModule(DiscreteActionMap(table), in_keys=[ACTION_CHOICE], out_keys=[ACTION])
    return module, choice_spec, table
