"""Federated independent learners over the vehicles' communication graph (FIRL: Xu, Li, Zhao,
Zhang, "Communication-efficient consensus mechanism for federated reinforcement learning",
ICC 2022, arXiv 2201.12718; its journal version, arXiv 2103.13026).

Each of the ``I`` agents keeps its own parameters, stacked along a leading agent dimension
(``[I, ...]`` per tensor, as a ``MultiAgentMLP`` with ``share_params=False`` holds them). Two
exchanges shape their local training:

- **consensus** (every local update): the agents' local gradients ``G`` ``[I, P]`` are mixed
  with their neighbours' over the range-``d`` graph, ``G <- W^K G``, with ``W`` the
  Metropolis-Hastings weights of the graph (:func:`metropolis_weights`): an agent out of
  everyone's range, or whose links all failed, keeps its own gradient; a failed link carries
  nothing.
- **periodic averaging** (every ``averaging_period`` local updates): a central server replaces
  every agent's parameters by their mean over agents (:func:`average_agents`).

The papers' consensus weights and round count are not public (only their abstracts are): the
Metropolis-Hastings weights (symmetric and doubly stochastic on any graph, so consensus keeps
the agents' mean gradient and needs no step size tied to the largest degree) and ``K`` rounds
are this library's choice.

Communication is counted in bytes as MA-PETS's sharing counts it (:class:`ExchangeStats`): one
message per link and direction. A consensus round sends each agent's gradient (``P`` values) to
each of its neighbours: ``links * P * element_size`` bytes (``links``: the graph's ordered pairs);
an averaging uploads every agent's parameters to the server and downloads the mean:
``2 * I * P * element_size`` bytes.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import torch
from tensordict import TensorDictBase
from torch import nn

from mapets_rl.comm.transform import CommunicationRange

__all__ = [
    "FederatedConsensus",
    "average_agents",
    "metropolis_weights",
    "mix",
    "set_stacked_gradients",
    "stacked_gradients",
]


def metropolis_weights(adjacency: torch.Tensor) -> torch.Tensor:
    """Metropolis-Hastings mixing matrix of an undirected graph.

    ``W[i, j] = 1 / (1 + max(deg_i, deg_j))`` for linked ``i != j``, ``0`` for unlinked ones,
    and ``W[i, i] = 1 - sum_{j != i} W[i, j]``: symmetric, rows and columns summing to 1, so
    ``W G`` keeps the mean of ``G``'s rows; a node without links has ``W[i] = e_i``.

    Args:
        adjacency: ``[I, I]`` bool (or 0/1), symmetric; the diagonal is ignored.

    Returns:
        ``[I, I]`` float (the default dtype).

    Raises:
        ValueError: not square, or not symmetric.
    """
    if adjacency.ndim != 2 or adjacency.shape[0] != adjacency.shape[1]:
        raise ValueError(f"adjacency must have shape [I, I], got {tuple(adjacency.shape)}")
    eye = torch.eye(adjacency.shape[0], dtype=torch.bool, device=adjacency.device)
    links = adjacency.to(torch.bool) & ~eye
    if not torch.equal(links, links.T):
        raise ValueError("adjacency must be symmetric (links carry messages both ways)")
    degree = links.sum(1).to(torch.get_default_dtype())  # [I]
    weights = links / (1 + torch.maximum(degree[:, None], degree[None, :]))
    return weights + torch.diag(1 - weights.sum(1))


def mix(values: torch.Tensor, weights: torch.Tensor, rounds: int = 1) -> torch.Tensor:
    """``rounds`` consensus rounds: ``W^rounds @ values`` (``values`` ``[I, ...]``, ``weights``
    ``[I, I]``); ``rounds = 0`` returns ``values``."""
    if isinstance(rounds, bool) or int(rounds) != rounds or rounds < 0:
        raise ValueError(f"rounds must be an integer >= 0, got {rounds!r}")
    flat = values.reshape(values.shape[0], -1)
    for _ in range(int(rounds)):
        flat = weights.to(flat.dtype) @ flat
    return flat.reshape(values.shape)


@torch.no_grad()
def average_agents(params: Sequence[nn.Parameter]) -> None:
    """Replace every agent's slice of each ``[I, ...]`` parameter by the mean over agents (the
    server's periodic averaging); the mean itself is unchanged."""
    for param in params:
        param.copy_(param.mean(0, keepdim=True).expand_as(param))


def stacked_gradients(params: Sequence[nn.Parameter]) -> torch.Tensor:
    """The gradients of ``[I, ...]`` parameters as one ``[I, P]`` matrix (row ``i``: agent
    ``i``'s whole gradient; a parameter without a gradient counts as zeros)."""
    return torch.cat(
        [
            (p.grad if p.grad is not None else torch.zeros_like(p)).reshape(p.shape[0], -1)
            for p in params
        ],
        dim=1,
    )


def set_stacked_gradients(params: Sequence[nn.Parameter], grads: torch.Tensor) -> None:
    """Write ``grads`` ``[I, P]`` (as :func:`stacked_gradients` lays them out) into the
    parameters' ``.grad``."""
    offset = 0
    for param in params:
        size = param[0].numel()
        param.grad = grads[:, offset : offset + size].reshape(param.shape).to(param.dtype)
        offset += size
    if offset != grads.shape[1]:
        raise ValueError(f"grads must have {offset} columns, got {grads.shape[1]}")


class FederatedConsensus:
    """FIRL's exchanges for ``I`` learners whose parameters are stacked ``[I, ...]``.

    Args:
        params: the learners' parameters, each ``[I, ...]``.
        comm_range: ``d`` in metres (``0``: no consensus links, ``inf``: complete graph).
        p_fail: probability that a link fails, drawn afresh for every exchange (one draw per
            unordered pair, from this object's generator).
        rounds: consensus rounds ``K >= 0`` per local update (0: periodic averaging only).
        averaging_period: local updates between the server's averagings (>= 1).
        seed: seed of the link-failure generator.

    Attributes:
        comm: the :class:`CommunicationRange` whose :meth:`~CommunicationRange.episode_graph`
            gives the graph of a collected batch (every agent at its last driving position).
        updates: local updates so far; ``bytes_consensus``, ``bytes_averaging``: bytes sent
            so far by each exchange.
    """

    def __init__(
        self,
        params: Sequence[nn.Parameter],
        comm_range: float,
        p_fail: float,
        rounds: int,
        averaging_period: int,
        seed: int | None = None,
    ) -> None:
        self.params = list(params)
        if not self.params:
            raise ValueError("params must hold at least one [I, ...] parameter")
        self.n_agents = self.params[0].shape[0]
        odd = [tuple(p.shape) for p in self.params if p.ndim < 1 or p.shape[0] != self.n_agents]
        if odd:
            raise ValueError(
                f"params must all be stacked over the same {self.n_agents} agents [I, ...], "
                f"got shapes {odd}"
            )
        if isinstance(rounds, bool) or int(rounds) != rounds or rounds < 0:
            raise ValueError(f"rounds must be an integer >= 0, got {rounds!r}")
        if (
            isinstance(averaging_period, bool)
            or int(averaging_period) != averaging_period
            or averaging_period < 1
        ):
            raise ValueError(f"averaging_period must be an integer >= 1, got {averaging_period!r}")
        self.comm = CommunicationRange(comm_range, p_fail, seed)
        self.rounds = int(rounds)
        self.averaging_period = int(averaging_period)
        self.message_bytes = sum(p[0].numel() * p.element_size() for p in self.params)
        """Bytes of one agent's gradient or parameters (``P * element_size``)."""
        self.updates = 0
        self.bytes_consensus = 0
        self.bytes_averaging = 0

    def consensus_bytes(self, adjacency: torch.Tensor) -> int:
        """Bytes of one consensus round on ``adjacency`` ``[I, I]``: one gradient per ordered
        linked pair."""
        eye = torch.eye(self.n_agents, dtype=torch.bool, device=adjacency.device)
        return int((adjacency.to(torch.bool) & ~eye).sum()) * self.message_bytes

    def averaging_bytes(self) -> int:
        """Bytes of one averaging: every agent's parameters up to the server and the mean back."""
        return 2 * self.n_agents * self.message_bytes

    def local_update(self, batch: TensorDictBase) -> dict[str, float]:
        """Call after ``backward`` and before the optimiser's step: the graph of ``batch``
        (``[T]`` with ``("next", "agents", "position")``; link failures drawn now), ``K``
        consensus rounds on the gradients; returns this update's ``bytes_consensus``."""
        adjacency = self.comm.episode_graph(batch)
        weights = metropolis_weights(adjacency)
        grads = stacked_gradients(self.params)
        set_stacked_gradients(self.params, mix(grads, weights.to(grads.device), self.rounds))
        sent = self.rounds * self.consensus_bytes(adjacency)
        self.bytes_consensus += sent
        return {"bytes_consensus": float(sent)}

    def after_step(self) -> dict[str, float]:
        """Call after the optimiser's step: counts the local update and, every
        ``averaging_period`` of them, averages the parameters; returns this call's
        ``bytes_averaging``."""
        self.updates += 1
        if self.updates % self.averaging_period:
            return {"bytes_averaging": 0.0}
        average_agents(self.params)
        sent = self.averaging_bytes()
        self.bytes_averaging += sent
        return {"bytes_averaging": float(sent)}

    def state_dict(self) -> dict[str, Any]:
        return {
            "updates": self.updates,
            "bytes_consensus": self.bytes_consensus,
            "bytes_averaging": self.bytes_averaging,
            "generator": self.comm.generator.get_state(),
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.updates = int(state["updates"])
        self.bytes_consensus = int(state["bytes_consensus"])
        self.bytes_averaging = int(state["bytes_averaging"])
        self.comm.generator.set_state(state["generator"])
