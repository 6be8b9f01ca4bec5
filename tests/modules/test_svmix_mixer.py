"""SVMIX's graph mixer: it respects the communication graph (an agent out of range, or behind a
failed link, changes nobody else's weights or contribution), it is monotone in every agent's
value, equivariant to a permutation of the agents, and refuses mis-shaped input."""

from __future__ import annotations

import pytest
import torch

from mapets_rl.comm import communication_graph
from mapets_rl.modules.graph_mixer import GraphValueMixer

N_FEATURES = 5


def _mixer(seed: int = 0) -> GraphValueMixer:
    torch.manual_seed(seed)
    return GraphValueMixer(N_FEATURES, hidden=16, layers=2, embed=4)


def _inputs(batch: int, n: int, seed: int = 1) -> tuple[torch.Tensor, torch.Tensor]:
    gen = torch.Generator().manual_seed(seed)
    value = torch.randn(batch, n, 1, generator=gen)
    features = torch.randn(batch, n, N_FEATURES, generator=gen)
    return value, features


def test_an_agent_out_of_range_changes_no_other_agents_weights_or_contribution() -> None:
    """Agents 0-3 stand 50 m apart on a line (a connected chain at d = 60 m), agent 4 is 1 km
    away: changing agent 4's value and features leaves the others' weights and contributions
    exactly as they were; changing agent 3's changes its neighbour 2's (the test can fail)."""
    mixer = _mixer()
    position = torch.tensor([[0.0, 0.0], [50.0, 0.0], [100.0, 0.0], [150.0, 0.0], [1e3, 0.0]])
    adjacency = communication_graph(position.expand(3, 5, 2), comm_range=60.0)
    assert not adjacency[:, 4].any() and adjacency[:, 2, 3].all()
    value, features = _inputs(3, 5)
    _, contribution, weight = mixer(value, features, adjacency)

    moved_value, moved_features = value.clone(), features.clone()
    moved_value[:, 4] += 3.0
    moved_features[:, 4] = torch.randn(3, N_FEATURES)
    _, contribution_after, weight_after = mixer(moved_value, moved_features, adjacency)
    assert torch.equal(weight_after[:, :4], weight[:, :4])
    assert torch.equal(contribution_after[:, :4], contribution[:, :4])
    assert not torch.allclose(contribution_after[:, 4], contribution[:, 4])

    neighbour_moved = features.clone()
    neighbour_moved[:, 3] += 1.0
    _, _, weight_neighbour = mixer(value, neighbour_moved, adjacency)
    assert not torch.allclose(weight_neighbour[:, 2], weight[:, 2])


def test_a_failed_link_carries_nothing() -> None:
    """Agents 0 and 1 linked only to each other: with the link, agent 1's features reach agent
    0's weights; with the link failed (p_fail = 1 on it), they do not."""
    mixer = _mixer(3)
    value, features = _inputs(2, 3, seed=4)
    linked = torch.zeros(2, 3, 3, dtype=torch.bool)
    linked[:, 0, 1] = linked[:, 1, 0] = True
    failed = communication_graph(torch.zeros(2, 3, 2), comm_range=10.0, p_fail=1.0)
    assert not failed.any()
    other = features.clone()
    other[:, 1] += 2.0
    for adjacency, carries in ((linked, True), (failed, False)):
        _, _, weight = mixer(value, features, adjacency)
        _, _, weight_other = mixer(value, other, adjacency)
        assert torch.allclose(weight[:, 0], weight_other[:, 0]) is not carries


@pytest.mark.parametrize("seed", range(4))
def test_the_mixed_value_is_monotone_in_each_agents_value(seed: int) -> None:
    """dV_tot / dV_i >= 0 by autograd for random parameters, values, features and graphs (and
    > 0 for most agents: the weights are non-negative, not zero)."""
    mixer = _mixer(seed)
    gen = torch.Generator().manual_seed(100 + seed)
    value = (3 * torch.randn(64, 6, 1, generator=gen)).requires_grad_()
    features = torch.randn(64, 6, N_FEATURES, generator=gen)
    adjacency = torch.rand(64, 6, 6, generator=gen) < 0.4
    adjacency = adjacency.triu(1) | adjacency.triu(1).transpose(-1, -2)
    total, _, _ = mixer(value, features, adjacency)
    (grad,) = torch.autograd.grad(total.sum(), value)
    assert (grad >= 0).all()
    assert (grad > 0).float().mean() > 0.5


def test_the_mixer_is_equivariant_to_a_permutation_of_the_agents() -> None:
    mixer = _mixer(5)
    value, features = _inputs(4, 6, seed=6)
    adjacency = communication_graph(20 * torch.randn(4, 6, 2), comm_range=25.0)
    mask = torch.tensor([True, True, False, True, True, True]).expand(4, 6)
    total, contribution, weight = mixer(value, features, adjacency, mask)
    perm = torch.tensor([3, 0, 5, 1, 4, 2])
    total_p, contribution_p, weight_p = mixer(
        value[:, perm],
        features[:, perm],
        adjacency[:, perm][:, :, perm],
        mask[:, perm],
    )
    assert torch.allclose(total_p, total, atol=1e-5)
    assert torch.allclose(contribution_p, contribution[:, perm], atol=1e-6)
    assert torch.allclose(weight_p, weight[:, perm], atol=1e-6)


def test_a_masked_agent_contributes_nothing_and_passes_no_message() -> None:
    mixer = _mixer(7)
    value, features = _inputs(2, 3, seed=8)
    adjacency = ~torch.eye(3, dtype=torch.bool).expand(2, 3, 3)
    mask = torch.tensor([[True, False, True]] * 2)
    total, contribution, weight = mixer(value, features, adjacency, mask)
    assert torch.equal(contribution[:, 1], torch.zeros(2, 1))
    assert torch.allclose(total, contribution.sum(-2))
    other = features.clone()
    other[:, 1] += 5.0
    _, _, weight_other = mixer(value, other, adjacency, mask)
    assert torch.equal(weight_other[:, [0, 2]], weight[:, [0, 2]])


@pytest.mark.parametrize(
    "value_shape, features_shape, adjacency, mask, needle",
    [
        ((2, 3, 1), (2, 3, 4), torch.zeros(2, 3, 3, dtype=torch.bool), None, "features"),
        ((2, 3), (2, 3, 5), torch.zeros(2, 3, 3, dtype=torch.bool), None, "value"),
        ((2, 3, 1), (2, 3, 5), torch.zeros(2, 3, 3), None, "adjacency"),
        ((2, 3, 1), (2, 3, 5), torch.zeros(2, 3, 2, dtype=torch.bool), None, "adjacency"),
        ((2, 3, 1), (2, 3, 5), torch.zeros(2, 3, 3, dtype=torch.bool), torch.ones(2, 3), "mask"),
    ],
)
def test_bad_input_is_refused_naming_the_argument(
    value_shape, features_shape, adjacency, mask, needle: str
) -> None:
    mixer = _mixer()
    with pytest.raises(ValueError, match=rf"^{needle} must"):
        mixer(torch.zeros(value_shape), torch.zeros(features_shape), adjacency, mask)


@pytest.mark.parametrize("argument", ["n_features", "hidden", "layers", "embed"])
def test_bad_sizes_are_refused(argument: str) -> None:
    kwargs = {"n_features": 3, argument: 0}
    with pytest.raises(ValueError, match=f"{argument} must be an int >= 1"):
        GraphValueMixer(**kwargs)
