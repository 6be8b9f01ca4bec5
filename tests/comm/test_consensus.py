"""FIRL's exchanges (mapets_rl.comm.consensus): the consensus step against a hand-computed
average on a 4-node graph, the graph respected (an agent out of range keeps its gradient, a
failed link carries nothing), averaging keeps the mean and equalises the agents, known byte
counts, bad input refused."""

from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict
from torch import nn

from mapets_rl.comm.consensus import (
    FederatedConsensus,
    average_agents,
    metropolis_weights,
    mix,
    stacked_gradients,
)

PATH = torch.tensor(
    [[0, 1, 0, 0], [1, 0, 1, 0], [0, 1, 0, 1], [0, 0, 1, 0]], dtype=torch.bool
)  # 0 - 1 - 2 - 3


def _params(n_agents: int = 4) -> list[nn.Parameter]:
    """Two stacked parameters [I, 3] and [I, 2, 1] (P = 5 values per agent)."""
    torch.manual_seed(0)
    return [nn.Parameter(torch.randn(n_agents, 3)), nn.Parameter(torch.randn(n_agents, 2, 1))]


def _batch(positions: torch.Tensor) -> TensorDict:
    """A one-step batch [1] whose agents stand at ``positions`` [I, 2]."""
    n = positions.shape[0]
    return TensorDict(
        {
            "agents": {"mask": torch.ones(1, n, dtype=torch.bool)},
            "next": {"agents": {"position": positions[None]}},
        },
        batch_size=[1],
    )


def test_consensus_on_a_4_node_path_is_the_hand_computed_metropolis_average() -> None:
    weights = metropolis_weights(PATH)
    third = 1 / 3
    expected_w = torch.tensor(
        [
            [2 * third, third, 0, 0],
            [third, third, third, 0],
            [0, third, third, third],
            [0, 0, third, 2 * third],
        ]
    )
    assert torch.allclose(weights, expected_w)
    grads = torch.tensor([[1.0], [2.0], [3.0], [4.0]])
    mixed = mix(grads, weights)
    # 0: 2/3 + 2/3; 1: (1 + 2 + 3) / 3; 2: (2 + 3 + 4) / 3; 3: 3/3 + 8/3
    assert torch.allclose(mixed, torch.tensor([[4 / 3], [2.0], [3.0], [11 / 3]]))
    assert torch.allclose(mixed.mean(), grads.mean())  # consensus keeps the mean gradient
    assert torch.allclose(mix(grads, weights, rounds=2), weights @ weights @ grads)
    assert torch.equal(mix(grads, weights, rounds=0), grads)


def test_an_agent_out_of_range_keeps_its_gradient_and_gives_none() -> None:
    # agents 0-2 within 10 m of each other, agent 3 a kilometre away
    positions = torch.tensor([[0.0, 0.0], [5.0, 0.0], [10.0, 0.0], [1000.0, 0.0]])
    params = _params()
    federation = FederatedConsensus(
        params, comm_range=10.0, p_fail=0.0, rounds=1, averaging_period=100
    )
    for p in params:
        p.grad = torch.arange(p.numel(), dtype=torch.float32).reshape(p.shape) ** 2
    before = stacked_gradients(params)
    sent = federation.local_update(_batch(positions))
    after = stacked_gradients(params)
    assert torch.equal(after[3], before[3])
    adjacency = federation.comm.episode_graph(_batch(positions))
    assert torch.allclose(after[:3], metropolis_weights(adjacency)[:3, :3] @ before[:3])
    # 0-1, 1-2 within 10 m (0-2 exactly at 10 m too): 6 ordered links of 5 float32 values
    assert sent == {"bytes_consensus": 6 * 5 * 4.0}


def test_a_failed_link_carries_nothing() -> None:
    grads = torch.tensor([[1.0], [2.0], [3.0], [4.0]])
    cut = PATH.clone()
    cut[1, 2] = cut[2, 1] = False  # the middle link failed: two separate pairs
    mixed = mix(grads, metropolis_weights(cut))
    assert torch.allclose(mixed, torch.tensor([[1.5], [1.5], [3.5], [3.5]]))
    # every link failing: nobody receives anything and nothing is sent
    params = _params()
    federation = FederatedConsensus(
        params, comm_range=float("inf"), p_fail=1.0, rounds=3, averaging_period=1, seed=0
    )
    for p in params:
        p.grad = torch.randn_like(p)
    before = stacked_gradients(params)
    assert federation.local_update(_batch(torch.zeros(4, 2))) == {"bytes_consensus": 0.0}
    assert torch.equal(stacked_gradients(params), before)


def test_averaging_keeps_the_mean_and_equalises_the_agents() -> None:
    params = _params()
    means = [p.detach().mean(0).clone() for p in params]
    average_agents(params)
    for p, mean in zip(params, means, strict=True):
        assert torch.allclose(p.mean(0), mean)
        assert torch.allclose(p, mean.expand_as(p))


def test_byte_counts_on_a_constructed_graph() -> None:
    params = _params()
    federation = FederatedConsensus(
        params, comm_range=float("inf"), p_fail=0.0, rounds=2, averaging_period=3
    )
    assert federation.message_bytes == 5 * 4  # P = 3 + 2 float32 values
    assert federation.consensus_bytes(PATH) == 6 * 20  # 3 links, both directions
    assert federation.averaging_bytes() == 2 * 4 * 20  # up and down, every agent
    # the complete graph of 4 agents: 12 ordered links, 2 rounds
    for p in params:
        p.grad = torch.ones_like(p)
    out = federation.local_update(_batch(torch.zeros(4, 2)))
    assert out == {"bytes_consensus": 2 * 12 * 20.0}
    # averaging every 3rd update only
    assert [federation.after_step()["bytes_averaging"] for _ in range(6)] == [0, 0, 160, 0, 0, 160]
    assert federation.bytes_consensus == 480 and federation.bytes_averaging == 320


def test_the_state_round_trips_and_continues_the_link_failures() -> None:
    params = _params()
    a = FederatedConsensus(params, 100.0, 0.5, 1, 2, seed=3)
    a.after_step()
    state = a.state_dict()
    first = a.comm.episode_graph(_batch(torch.zeros(4, 2)))
    b = FederatedConsensus(params, 100.0, 0.5, 1, 2, seed=99)
    b.load_state_dict(state)
    assert b.updates == 1
    assert torch.equal(b.comm.episode_graph(_batch(torch.zeros(4, 2))), first)


@pytest.mark.parametrize(
    "call, match",
    [
        (lambda: metropolis_weights(torch.ones(2, 3, dtype=torch.bool)), r"shape \[I, I\]"),
        (lambda: metropolis_weights(torch.tensor([[0, 1], [0, 0]])), "symmetric"),
        (lambda: mix(torch.ones(2, 1), torch.eye(2), rounds=-1), "rounds must be an integer >= 0"),
        (lambda: FederatedConsensus([], 1.0, 0.0, 1, 1), "at least one"),
        (
            lambda: FederatedConsensus(
                [nn.Parameter(torch.ones(4, 2)), nn.Parameter(torch.ones(3))], 1.0, 0.0, 1, 1
            ),
            r"stacked over the same 4 agents",
        ),
        (
            lambda: FederatedConsensus(_params(), 1.0, 0.0, 1, 0),
            "averaging_period must be an integer >= 1",
        ),
        (lambda: FederatedConsensus(_params(), -1.0, 0.0, 1, 1), r"comm_range must be"),
        (lambda: FederatedConsensus(_params(), 1.0, 2.0, 1, 1), r"p_fail must be"),
    ],
)
def test_bad_input_is_refused_naming_the_argument(call, match: str) -> None:
    with pytest.raises(ValueError, match=match):
        call()
