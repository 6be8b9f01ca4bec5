"""NeighbourDatasets: exchange semantics, overhead accounting, FIFO, memory, sampling."""

import io
from collections import deque

import pytest
import torch
from tensordict import TensorDict

from mapets_rl.comm import NeighbourDatasets

OBS = 7
# One transition: observation (7 f32) + action (1 f32) + next_observation (7 f32) + id (1 i64).
BYTES_PER_TRANSITION = 7 * 4 + 4 + 7 * 4 + 8


def _episode(n_steps: int, n_agents: int, first_id: int) -> TensorDict:
    """Transitions [T, I] whose "id" is unique: first_id + t * I + i."""
    ids = first_id + torch.arange(n_steps * n_agents).reshape(n_steps, n_agents)
    return TensorDict(
        {
            "observation": torch.randn(n_steps, n_agents, OBS),
            "action": torch.randn(n_steps, n_agents, 1),
            "next_observation": torch.randn(n_steps, n_agents, OBS),
            "id": ids,
        },
        [n_steps, n_agents],
    )


def _ids(data: NeighbourDatasets, agent: int) -> set[int]:
    return set(data.dataset(agent)["id"].tolist())


def _graph(n: int, edges: list[tuple[int, int]]) -> torch.Tensor:
    a = torch.zeros(n, n, dtype=torch.bool)
    for i, j in edges:
        a[i, j] = a[j, i] = True
    return a


def test_exchange_shows_exactly_neighbours_last_episode_and_counts_overhead():
    n, steps = 4, 5
    data = NeighbourDatasets(n, capacity_per_agent=100, seed=0)
    ep1 = _episode(steps, n, first_id=0)
    data.add(ep1)
    own1 = [set(ep1["id"][:, i].tolist()) for i in range(n)]
    for i in range(n):
        assert _ids(data, i) == own1[i]

    graph1 = _graph(n, [(0, 1), (1, 2)])
    stats = data.exchange(graph1)
    assert _ids(data, 0) == own1[0] | own1[1]
    assert _ids(data, 1) == own1[1] | own1[0] | own1[2]
    assert _ids(data, 2) == own1[2] | own1[1]
    assert _ids(data, 3) == own1[3]
    # 4 directed links x 5 transitions.
    assert stats.transitions == 20
    assert stats.bytes == 20 * BYTES_PER_TRANSITION
    assert stats.sent.tolist() == [5, 10, 5, 0]
    assert stats.received.tolist() == [5, 10, 5, 0]

    # Episode 2, another graph: only episode-2 data of the new neighbours arrive.
    ep2 = _episode(steps, n, first_id=1000)
    own2 = [set(ep2["id"][:, i].tolist()) for i in range(n)]
    data.add(ep2)
    stats2 = data.exchange(_graph(n, [(0, 3)]))
    assert _ids(data, 3) == own1[3] | own2[3] | own2[0]
    assert _ids(data, 0) == own1[0] | own1[1] | own2[0] | own2[3]
    assert _ids(data, 2) == own1[2] | own1[1] | own2[2]
    assert stats2.transitions == 10
    assert data.total_transitions_sent == 30
    assert data.total_bytes_sent == 30 * BYTES_PER_TRANSITION
    assert data.n_exchanges == 2
    assert data.mean_transitions_per_exchange == 15.0
    # Received data is never forwarded: a second exchange without new data sends nothing.
    assert data.exchange(torch.ones(n, n, dtype=torch.bool)).transitions == 0


def test_owners_and_directed_rows():
    data = NeighbourDatasets(3, capacity_per_agent=10)
    data.add(_episode(2, 3, 0))
    neighbors = torch.zeros(3, 3, dtype=torch.bool)
    neighbors[0, 2] = True  # row 0 receives from 2; 2 receives nothing
    stats = data.exchange(neighbors)
    assert stats.transitions == 2
    assert sorted(data.owners(0).tolist()) == [0, 0, 2, 2]
    assert data.owners(2).tolist() == [2, 2]


def test_masked_transitions_are_neither_stored_nor_sent():
    n = 3
    data = NeighbourDatasets(n, capacity_per_agent=10)
    ep = _episode(4, n, 0)
    mask = torch.ones(4, n, dtype=torch.bool)
    mask[2:, 1] = False  # agent 1 crashed after two steps
    data.add(ep, mask=mask.unsqueeze(-1))
    assert data.sizes.tolist() == [4, 2, 4]
    stats = data.exchange(~torch.eye(n, dtype=torch.bool))
    assert stats.sent.tolist() == [8, 4, 8]
    assert _ids(data, 0) >= set(ep["id"][:2, 1].tolist())
    assert not _ids(data, 0) & set(ep["id"][2:, 1].tolist())


def test_fifo_eviction_at_capacity_and_only_held_data_is_sent():
    data = NeighbourDatasets(2, capacity_per_agent=4)
    ep = _episode(6, 2, 0)  # 6 own transitions each, capacity 4
    data.add(ep[:3])
    data.add(ep[3:])
    assert data.dataset(0)["id"].tolist() == ep["id"][2:, 0].tolist()  # oldest two evicted
    stats = data.exchange(~torch.eye(2, dtype=torch.bool))
    assert stats.transitions == 8  # each sends the 4 it still holds
    # Receiving 4 into a full ring of 4 evicts all own data: FIFO over D(i)+.
    assert data.dataset(0)["id"].tolist() == ep["id"][2:, 1].tolist()
    assert data.n_stored == 8


def test_memory_does_not_grow_with_the_number_of_neighbours():
    n, steps = 6, 10
    results = {}
    for name, graph in {
        "none": torch.zeros(n, n, dtype=torch.bool),
        "complete": ~torch.eye(n, dtype=torch.bool),
    }.items():
        data = NeighbourDatasets(n, capacity_per_agent=256, seed=0)
        before = None
        for episode in range(3):
            data.add(_episode(steps, n, first_id=1000 * episode))
            if before is None:
                before = data.memory_bytes
            data.exchange(graph)
        results[name] = data
        assert data.memory_bytes == before
        assert data.n_stored == 3 * steps * n  # every transition stored once
        assert len(data.storage) == 3 * steps * n  # storage written only by `add`
    assert results["complete"].memory_bytes == results["none"].memory_bytes
    assert results["complete"].sizes.tolist() == [3 * steps * n] * n
    assert results["none"].sizes.tolist() == [3 * steps] * n


def _reference_check(data, ref, n):
    for i in range(n):
        assert data.dataset(i)["id"].tolist() == list(ref[i])


def test_matches_a_reference_model_under_random_adds_and_exchanges():
    """Random episode lengths, masks, graphs; compared with a list-of-deques model."""
    n, cap = 5, 7
    gen = torch.Generator().manual_seed(0)
    data = NeighbourDatasets(n, capacity_per_agent=cap)
    ref = [deque(maxlen=cap) for _ in range(n)]
    next_id = 0
    for _ in range(12):
        pending = []  # (id, owner) in insertion order
        for _ in range(int(torch.randint(1, 3, (1,), generator=gen))):
            steps = int(torch.randint(1, 6, (1,), generator=gen))
            ep = _episode(steps, n, next_id)
            next_id += steps * n
            mask = torch.rand(steps, n, generator=gen) > 0.2
            data.add(ep, mask=mask)
            for t in range(steps):
                for i in range(n):
                    if mask[t, i]:
                        ref[i].append(int(ep["id"][t, i]))
                        pending.append((int(ep["id"][t, i]), i))
            _reference_check(data, ref, n)
        upper = (torch.rand(n, n, generator=gen) < 0.5).triu(1)
        graph = upper | upper.T
        held = [set(r) for r in ref]
        shareable = [(x, j) for x, j in pending if x in held[j]]
        expected = 0
        for i in range(n):
            incoming = [x for x, j in shareable if graph[i, j] and j != i]
            expected += len(incoming)
            ref[i].extend(incoming)
        assert data.exchange(graph).transitions == expected
        _reference_check(data, ref, n)
        assert data.n_stored == len(set().union(*map(set, ref)))
        assert data.n_stored <= n * cap


def test_sample_rows_come_from_each_agents_dataset():
    n = 3
    data = NeighbourDatasets(n, capacity_per_agent=50, seed=1)
    data.add(_episode(6, n, 0))
    data.exchange(_graph(n, [(0, 1)]))
    batch = data.sample(32)
    assert batch.batch_size == (n, 32)
    assert batch["observation"].shape == (n, 32, OBS)
    for i in range(n):
        assert set(batch["id"][i].tolist()) <= _ids(data, i)
    members = data.sample((5, 16))
    assert members.batch_size == (n, 5, 16)
    for i in range(n):
        assert set(members["id"][i].flatten().tolist()) <= _ids(data, i)


def test_iter_epoch_covers_every_dataset():
    n = 3
    data = NeighbourDatasets(n, capacity_per_agent=50, seed=2)
    data.add(_episode(10, n, 0))
    data.exchange(_graph(n, [(0, 1)]))  # sizes 20, 20, 10
    batches = list(data.iter_epoch(8))
    assert len(batches) == 3 and all(b.batch_size == (n, 8) for b in batches)
    ids = torch.cat([b["id"] for b in batches], dim=1)  # [I, 24]
    for i in range(n):
        size = int(data.sizes[i])
        assert set(ids[i, :size].tolist()) == _ids(data, i)  # a permutation first
        assert ids[i, size:].tolist() == ids[i, : 24 - size].tolist()  # then repeated


def test_state_dict_round_trip_restores_data_counters_and_rng():
    n = 3
    data = NeighbourDatasets(n, capacity_per_agent=8, seed=0)
    data.add(_episode(5, n, 0))
    data.exchange(_graph(n, [(0, 2)]))
    data.add(_episode(2, n, 100))  # pending, not yet exchanged
    buffer = io.BytesIO()
    torch.save(data.state_dict(), buffer)
    buffer.seek(0)
    restored = NeighbourDatasets(n, capacity_per_agent=8, seed=99)
    restored.load_state_dict(torch.load(buffer, weights_only=True))
    for i in range(n):
        assert torch.equal(restored.dataset(i)["id"], data.dataset(i)["id"])
    assert torch.equal(restored.sample(16)["id"], data.sample(16)["id"])
    graph = ~torch.eye(n, dtype=torch.bool)
    assert restored.exchange(graph).transitions == data.exchange(graph).transitions == 12
    assert restored.total_bytes_sent == data.total_bytes_sent
    with pytest.raises(ValueError, match="capacity_per_agent"):
        NeighbourDatasets(n, capacity_per_agent=9).load_state_dict(data.state_dict())


@pytest.mark.parametrize("bad", [0, -1, 2.5])
def test_bad_n_agents_raises(bad):
    with pytest.raises(ValueError, match="n_agents"):
        NeighbourDatasets(bad)


@pytest.mark.parametrize("bad", [0, -5, 1.5])
def test_bad_capacity_raises(bad):
    with pytest.raises(ValueError, match="capacity_per_agent"):
        NeighbourDatasets(2, capacity_per_agent=bad)


def test_bad_exchange_and_add_inputs_raise():
    data = NeighbourDatasets(3, capacity_per_agent=4)
    with pytest.raises(ValueError, match="neighbors"):
        data.exchange(torch.zeros(4, 4, dtype=torch.bool))
    with pytest.raises(ValueError, match="neighbors"):
        data.exchange(torch.zeros(2, 3, 3, dtype=torch.bool))
    with pytest.raises(ValueError, match="transitions"):
        data.add(_episode(2, 4, 0))
    with pytest.raises(ValueError, match="mask"):
        data.add(_episode(2, 3, 0), mask=torch.ones(3, 3, dtype=torch.bool))
    with pytest.raises(RuntimeError, match="no transitions"):
        data.sample(4)
    data.add(_episode(2, 3, 0))
    with pytest.raises(ValueError, match="batch_size"):
        data.sample(0)
    with pytest.raises(ValueError, match="agent"):
        data.dataset(3)
