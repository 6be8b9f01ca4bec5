"""Per-agent transition datasets ``D(i)+`` with end-of-episode neighbour exchange (MA-PETS III-B).

Agent ``i`` trains its dynamics model on ``D(i)+``: its own transitions plus those its
neighbours sent at the end of each episode,
``D^{(i)+}_{0:t_k} = D^{(i)+}_{0:t_k-H-1} U {D^{(j)}_{t_k-H:t_k} : j in F_{d,k}(i)}`` (sec. III-B).

Layout: one shared :class:`~torchrl.data.LazyTensorStorage` holds every transition once, whoever
owns or received it. Each agent's ``D(i)+`` is a FIFO ring of ``capacity_per_agent`` indices into
that storage (``[I, C]`` long tensor). A storage slot is reference-counted by the rings that hold
it and reused once no ring does, so the storage never needs more than ``I * C`` slots: memory is
fixed at construction and does not grow with the number of neighbours. Exchanging data only
writes indices. The overhead that a real radio would carry (one copy per link) is counted.

A checkpoint (:meth:`NeighbourDatasets.state_dict`) holds the slots that were ever written and
their transitions, not the whole storage: the slots never written hold whatever the allocator
left there (``torch.empty``), which would make identical runs write different checkpoints, put
the process's old memory on disk and cost ``I * C`` transitions of space from the first episode.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import LazyTensorStorage

from mapets_rl._console import torchrl_info_dropped

__all__ = ["ExchangeStats", "NeighbourDatasets"]


@dataclass(frozen=True)
class ExchangeStats:
    """Overhead of one exchange.

    Attributes:
        transitions: transitions sent, counted once per link (one copy per receiver).
        bytes: ``transitions * bytes_per_transition``.
        sent: ``[I]`` long, transitions each agent sent (summed over its links).
        received: ``[I]`` long, transitions each agent received.
    """

    transitions: int
    bytes: int
    sent: torch.Tensor
    received: torch.Tensor


class NeighbourDatasets:
    """Per-agent datasets ``D(i)+`` over one shared storage, with neighbour exchange.

    Protocol (one episode): call :meth:`add` with the episode's transitions (any number of times,
    e.g. once per step or once with the whole rollout), then :meth:`exchange` with the
    communication graph at the end of the episode. :meth:`exchange` sends every agent's own
    transitions added since the previous exchange to its neighbours.

    Args:
        n_agents: ``I >= 1``.
        capacity_per_agent: size ``C >= 1`` of each ``D(i)+`` (FIFO eviction, oldest first;
            paper: 2048).
        device: device of the storage and index tensors.
        seed: seed of the sampling generator.

    Example:
        >>> data = NeighbourDatasets(n_agents=8, capacity_per_agent=2048)
        >>> comm = CommunicationRange(100.0)
        >>> # per episode: transitions is a TensorDict with batch_size [T, I]
        >>> data.add(transitions, mask=rollout["agents", "mask"])
        >>> stats = data.exchange(comm.episode_graph(rollout))
        >>> batch = data.sample(128)  # TensorDict [I, 128], one row per agent
    """

    def __init__(
        self,
        n_agents: int,
        capacity_per_agent: int = 2048,
        *,
        device: torch.device | str | None = None,
        seed: int | None = None,
    ) -> None:
        if isinstance(n_agents, bool) or int(n_agents) != n_agents or n_agents < 1:
            raise ValueError(f"n_agents must be an integer >= 1, got {n_agents}")
        if (
            isinstance(capacity_per_agent, bool)
            or int(capacity_per_agent) != capacity_per_agent
            or capacity_per_agent < 1
        ):
            raise ValueError(
                f"capacity_per_agent must be an integer >= 1, got {capacity_per_agent}"
            )
        self.n_agents = int(n_agents)
        self.capacity_per_agent = int(capacity_per_agent)
        self.device = torch.device("cpu" if device is None else device)
        n_slots = self.n_agents * self.capacity_per_agent
        self.storage = LazyTensorStorage(n_slots, device=self.device)
        long = {"dtype": torch.long, "device": self.device}
        self._ring = torch.full((self.n_agents, self.capacity_per_agent), -1, **long)
        self._cursor = torch.zeros(self.n_agents, **long)
        self._size = torch.zeros(self.n_agents, **long)
        self._refcount = torch.zeros(n_slots, **long)
        self._owner = torch.full((n_slots,), -1, **long)
        self._uid = torch.full((n_slots,), -1, **long)  # unique id of the slot's transition
        self._next_uid = 0
        # Own transitions since the last exchange: slot, uid, owner (each [M]).
        self._pending = torch.zeros(3, 0, **long)
        self.bytes_per_transition = 0
        self.total_transitions_sent = 0
        self.total_bytes_sent = 0
        self.n_exchanges = 0
        self.generator = torch.Generator(device=self.device)
        if seed is None:
            self.generator.seed()
        else:
            self.generator.manual_seed(int(seed))

    # ------------------------------------------------------------------ sizes
    @property
    def sizes(self) -> torch.Tensor:
        """``[I]`` long: number of transitions in each ``D(i)+``."""
        return self._size.clone()

    @property
    def n_stored(self) -> int:
        """Distinct transitions held in the shared storage (each stored once)."""
        return int((self._refcount > 0).sum())

    @property
    def memory_bytes(self) -> int:
        """Bytes held: the shared storage (``I * C`` transition slots, allocated on the first
        :meth:`add`) plus the index tensors. Independent of how many neighbours share data."""
        index_bytes = sum(
            t.numel() * t.element_size()
            for t in (self._ring, self._cursor, self._size, self._refcount, self._owner, self._uid)
        )
        data_bytes = self.bytes_per_transition * self.storage.max_size
        return index_bytes + data_bytes

    @property
    def mean_transitions_per_exchange(self) -> float:
        """Mean of :attr:`ExchangeStats.transitions` over all exchanges so far."""
        return self.total_transitions_sent / max(self.n_exchanges, 1)

    # ------------------------------------------------------------------ ring bookkeeping
    def _plan(self, receive: torch.Tensor) -> tuple[torch.Tensor, ...]:
        """Ring writes for ``receive`` ``[I, M]`` bool (agent i gets item m, in order of m).

        Only the newest ``C`` items per agent are kept. Returns agent, item and ring position of
        each kept write (sorted by item), and the per-agent count of received items ``[I]``.
        """
        cap = self.capacity_per_agent
        count = receive.sum(1)
        rank = receive.cumsum(1) - 1
        keep = receive & (rank >= (count - cap).unsqueeze(1))
        item, agent = keep.T.nonzero(as_tuple=True)  # item-major: keeps insertion order
        position = (self._cursor[agent] + rank[agent, item]) % cap
        return agent, item, position, count

    def _evict(self, agent: torch.Tensor, position: torch.Tensor) -> None:
        old = self._ring[agent, position]
        old = old[old >= 0]
        self._refcount.index_add_(0, old, torch.full_like(old, -1))

    def _write(
        self, agent: torch.Tensor, position: torch.Tensor, slots: torch.Tensor, count: torch.Tensor
    ) -> None:
        self._ring[agent, position] = slots
        self._refcount.index_add_(0, slots, torch.ones_like(slots))
        self._cursor = (self._cursor + count) % self.capacity_per_agent
        self._size = torch.clamp(self._size + count, max=self.capacity_per_agent)

    # ------------------------------------------------------------------ public API
    def add(self, transitions: TensorDictBase, mask: torch.Tensor | None = None) -> None:
        """Stores own transitions, each once, in its owner's ``D(i)+``.

        Args:
            transitions: TensorDict with batch size ``[*T, I]``; entry ``[..., i]`` is a
                transition of agent ``i`` (e.g. ``observation``, ``action``,
                ``next_observation``; any keys, the same for every call).
            mask: optional ``[*T, I]`` (or ``[*T, I, 1]``) bool; ``False`` entries (crashed or
                removed agents) are not stored.

        If an agent adds more than ``C`` transitions in one call, only its newest ``C`` are
        kept.
        """
        if not isinstance(transitions, TensorDictBase):
            raise ValueError(f"transitions must be a TensorDict, got {type(transitions).__name__}")
        shape = transitions.batch_size
        if len(shape) < 1 or shape[-1] != self.n_agents:
            raise ValueError(
                f"transitions must have batch size [*T, n_agents={self.n_agents}], "
                f"got {list(shape)}"
            )
        if mask is not None:
            mask = torch.as_tensor(mask, device=self.device)
            if mask.shape == shape + (1,):
                mask = mask.squeeze(-1)
            if mask.shape != shape:
                raise ValueError(f"mask must have shape {list(shape)}, got {list(mask.shape)}")
        flat = transitions.reshape(-1).to(self.device)  # [M], agent-major within each step
        owner = torch.arange(self.n_agents, device=self.device).repeat(shape[:-1].numel())
        if mask is not None:
            keep = mask.reshape(-1).to(torch.bool)
            flat, owner = flat[keep], owner[keep]
        if owner.numel() == 0:
            return
        if self.bytes_per_transition == 0:
            self.bytes_per_transition = sum(
                v[0].numel() * v.element_size()
                for v in flat.values(include_nested=True, leaves_only=True)
            )
        receive = owner.unsqueeze(0) == torch.arange(self.n_agents, device=self.device)[:, None]
        agent, item, position, count = self._plan(receive)
        self._evict(agent, position)
        # Evictions freed at least as many slots as are written (see module docstring).
        slots = torch.nonzero(self._refcount == 0).squeeze(1)[: item.numel()]
        uid = torch.arange(self._next_uid, self._next_uid + item.numel(), device=self.device)
        self._next_uid += item.numel()
        with torchrl_info_dropped():  # the first write allocates the storage
            self.storage.set(slots, flat[item])
        self._owner[slots] = owner[item]
        self._uid[slots] = uid
        self._write(agent, position, slots, count)
        self._pending = torch.cat([self._pending, torch.stack([slots, uid, owner[item]])], 1)

    def exchange(self, neighbors: torch.Tensor) -> ExchangeStats:
        """End-of-episode exchange: agent ``i`` receives the episode's transitions of every
        ``j`` with ``neighbors[i, j]`` (paper sec. III-B).

        Sends the transitions each agent added since the previous exchange and still holds in
        its own ``D(j)+``, then starts a new episode. Receivers evict their oldest entries when
        full. Only indices are written; the overhead is counted per link.

        Args:
            neighbors: ``[I, I]`` bool adjacency (row ``i`` receives from column ``j``; the
                diagonal is ignored), e.g. ``("agents", "neighbors")`` of
                :class:`~mapets_rl.comm.CommunicationRange` at the episode's last step.

        Returns:
            :class:`ExchangeStats` of this exchange (also added to the running totals).
        """
        neighbors = torch.as_tensor(neighbors, device=self.device)
        if neighbors.shape != (self.n_agents, self.n_agents):
            raise ValueError(
                f"neighbors must have shape ({self.n_agents}, {self.n_agents}), "
                f"got {tuple(neighbors.shape)}"
            )
        neighbors = neighbors.to(torch.bool)
        slot, uid, owner = self._pending
        # Shareable: still in the storage and held by its owner (not evicted since `add`).
        valid = (self._uid[slot] == uid) & (self._refcount[slot] > 0)
        slot, owner = slot[valid], owner[valid]
        agents = torch.arange(self.n_agents, device=self.device)
        receive = neighbors[:, owner] & (owner.unsqueeze(0) != agents[:, None])  # [I, M]
        received = receive.sum(1)
        sent = torch.zeros_like(received).index_add_(0, owner, receive.sum(0))
        agent, item, position, count = self._plan(receive)
        self._evict(agent, position)
        self._write(agent, position, slot[item], count)
        self._pending = self._pending[:, :0]

        n_sent = int(received.sum())
        stats = ExchangeStats(
            transitions=n_sent,
            bytes=n_sent * self.bytes_per_transition,
            sent=sent,
            received=received,
        )
        self.total_transitions_sent += stats.transitions
        self.total_bytes_sent += stats.bytes
        self.n_exchanges += 1
        return stats

    def _ring_positions(self, agent: int) -> torch.Tensor:
        size = int(self._size[agent])
        start = self._cursor[agent] - size
        return (start + torch.arange(size, device=self.device)) % self.capacity_per_agent

    def _check_agent(self, agent: int) -> int:
        if isinstance(agent, bool) or int(agent) != agent or not 0 <= agent < self.n_agents:
            raise ValueError(f"agent must be an integer in [0, {self.n_agents}), got {agent}")
        return int(agent)

    def dataset(self, agent: int) -> TensorDictBase:
        """All of ``D(agent)+``, oldest first: a TensorDict ``[size]``."""
        agent = self._check_agent(agent)
        if not self.storage.initialized:
            raise RuntimeError("no transitions have been added yet")
        slots = self._ring[agent, self._ring_positions(agent)]
        return self.storage.get(slots)

    def owners(self, agent: int) -> torch.Tensor:
        """``[size]`` long: the agent that collected each transition of :meth:`dataset`."""
        agent = self._check_agent(agent)
        return self._owner[self._ring[agent, self._ring_positions(agent)]]

    def _check_nonempty(self) -> None:
        if bool((self._size == 0).any()):
            empty = torch.nonzero(self._size == 0).squeeze(1).tolist()
            raise RuntimeError(f"agents {empty} have no transitions to sample")

    def _gather(self, position: torch.Tensor) -> TensorDictBase:
        """``position`` ``[I, *S]`` ring positions (0 = oldest) -> TensorDict ``[I, *S]``."""
        shape = position.shape
        start = (self._cursor - self._size).view(-1, *([1] * (len(shape) - 1)))
        ring_pos = (start + position) % self.capacity_per_agent
        slots = torch.gather(self._ring, 1, ring_pos.reshape(self.n_agents, -1))
        return self.storage.get(slots.reshape(-1)).reshape(shape)

    def sample(self, batch_size: int | tuple[int, ...]) -> TensorDictBase:
        """Uniform sample with replacement from every ``D(i)+`` at once.

        Args:
            batch_size: ``B`` or a shape ``(*S)`` (e.g. ``(members, B)`` for independent
                bootstrap batches of an ensemble).

        Returns:
            TensorDict ``[I, *S]``; row ``i`` comes from ``D(i)+``.
        """
        shape = (batch_size,) if isinstance(batch_size, int) else tuple(batch_size)
        if not shape or any(int(s) < 1 for s in shape):
            raise ValueError(f"batch_size must be positive, got {batch_size}")
        self._check_nonempty()
        u = torch.rand((self.n_agents, *shape), generator=self.generator, device=self.device)
        size = self._size.view(-1, *([1] * len(shape)))
        position = torch.clamp((u * size).long(), max=size - 1)
        return self._gather(position)

    def iter_epoch(self, batch_size: int) -> Iterator[TensorDictBase]:
        """One shuffled pass over every ``D(i)+`` at once, in TensorDicts ``[I, batch_size]``.

        Yields ``ceil(max_i |D(i)+| / batch_size)`` batches. Each agent's rows are a random
        permutation of its dataset, repeated (re-used from the start) for agents whose
        dataset is smaller than the largest.
        """
        if isinstance(batch_size, bool) or int(batch_size) != batch_size or batch_size < 1:
            raise ValueError(f"batch_size must be an integer >= 1, got {batch_size}")
        self._check_nonempty()
        n_batches = math.ceil(int(self._size.max()) / batch_size)
        cap = self.capacity_per_agent
        keys = torch.rand((self.n_agents, cap), generator=self.generator, device=self.device)
        keys = keys.masked_fill(torch.arange(cap, device=self.device) >= self._size[:, None], 2.0)
        permutation = keys.argsort(1)  # first size_i entries: a permutation of 0..size_i-1
        steps = torch.arange(n_batches * batch_size, device=self.device)
        position = torch.gather(permutation, 1, steps % self._size[:, None])
        for b in range(n_batches):
            yield self._gather(position[:, b * batch_size : (b + 1) * batch_size])

    # ------------------------------------------------------------------ checkpointing
    def state_dict(self) -> dict[str, Any]:
        """Everything needed to resume: the stored transitions, rings, counters and the
        sampling RNG.

        ``"storage"`` is ``{"slots": [S] long, "data": {key: tensor [S, ...]}}``: the slots
        ever written (the only ones a ring can point to) and their transitions, ``{}`` before
        the first :meth:`add`; slots never written are not saved (see the module docstring).
        """
        return {
            "n_agents": self.n_agents,
            "capacity_per_agent": self.capacity_per_agent,
            "storage": self._storage_state(),
            "ring": self._ring.clone(),
            "cursor": self._cursor.clone(),
            "size": self._size.clone(),
            "refcount": self._refcount.clone(),
            "owner": self._owner.clone(),
            "uid": self._uid.clone(),
            "next_uid": self._next_uid,
            "pending": self._pending.clone(),
            "bytes_per_transition": self.bytes_per_transition,
            "total_transitions_sent": self.total_transitions_sent,
            "total_bytes_sent": self.total_bytes_sent,
            "n_exchanges": self.n_exchanges,
            "generator": self.generator.get_state(),
        }

    def load_state_dict(self, state_dict: dict[str, Any]) -> None:
        """Restores :meth:`state_dict` output (same ``n_agents`` and ``capacity_per_agent``)."""
        for name in ("n_agents", "capacity_per_agent"):
            if state_dict[name] != getattr(self, name):
                raise ValueError(
                    f"{name} of the state dict ({state_dict[name]}) differs from this "
                    f"instance ({getattr(self, name)})"
                )
        self._load_storage_state(state_dict["storage"])
        for name in ("ring", "cursor", "size", "refcount", "owner", "uid", "pending"):
            setattr(self, f"_{name}", state_dict[name].to(self.device).clone())
        self._next_uid = int(state_dict["next_uid"])
        self.bytes_per_transition = int(state_dict["bytes_per_transition"])
        self.total_transitions_sent = int(state_dict["total_transitions_sent"])
        self.total_bytes_sent = int(state_dict["total_bytes_sent"])
        self.n_exchanges = int(state_dict["n_exchanges"])
        self.generator.set_state(state_dict["generator"].cpu())  # map_location may move it

    def _storage_state(self) -> dict[str, Any]:
        """The written slots of the storage and their transitions (see :meth:`state_dict`)."""
        if not self.storage.initialized:
            return {}
        slots = torch.nonzero(self._uid >= 0).squeeze(1)
        return {"slots": slots, "data": self.storage.get(slots).to_dict()}

    def _load_storage_state(self, state: dict[str, Any]) -> None:
        """Rebuild the storage from :meth:`_storage_state` output (or, from a checkpoint of an
        older version, a whole ``LazyTensorStorage`` state)."""
        self.storage = LazyTensorStorage(
            self.n_agents * self.capacity_per_agent, device=self.device
        )
        if "slots" not in state:
            if state:
                self.storage.load_state_dict(state)
            return
        slots = state["slots"].to(self.device)
        data = TensorDict(state["data"], batch_size=slots.shape).to(self.device)
        if slots.numel():
            with torchrl_info_dropped():
                self.storage.set(slots, data)

    def __repr__(self) -> str:
        return (
            f"{type(self).__name__}(n_agents={self.n_agents}, "
            f"capacity_per_agent={self.capacity_per_agent}, sizes={self._size.tolist()}, "
            f"stored={self.n_stored}, total_transitions_sent={self.total_transitions_sent})"
        )
