"""Game-theory core: closed-form games, Shapley axioms, sampling, convexity and the core."""

import itertools
import math

import pytest
import torch

from mapets_rl.shapley import (
    coalition_masks,
    exact_shapley,
    in_core,
    is_convex,
    is_efficient,
    permutation_prefix_masks,
    prefixes_with_agents,
    sample_permutations,
    sampled_shapley,
    shapley_matrix,
)

DT = torch.float64


def _random_game(n: int, *batch: int, seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    v = torch.rand(*batch, 2**n, generator=g, dtype=DT)
    v[..., 0] = 0.0
    return v


def _brute_force_shapley(v: torch.Tensor, n: int) -> torch.Tensor:
    """Textbook eq. 3 with Python loops (reference only)."""
    phi = torch.zeros(n, dtype=DT)
    for i in range(n):
        others = [j for j in range(n) if j != i]
        for size in range(n):
            w = math.factorial(size) * math.factorial(n - size - 1) / math.factorial(n)
            for members in itertools.combinations(others, size):
                k = sum(1 << j for j in members)
                phi[i] += w * (v[k | (1 << i)] - v[k])
    return phi


def test_coalition_masks_encoding():
    m = coalition_masks(3)
    assert m.shape == (8, 3) and m.dtype == torch.bool
    assert m[0].tolist() == [False, False, False]
    assert m[5].tolist() == [True, False, True]  # 5 = 0b101
    assert m[7].all()
    assert (m.sum(-1) == torch.tensor([0, 1, 1, 2, 1, 2, 2, 3])).all()


def test_matches_brute_force():
    n = 5
    v = _random_game(n, seed=1)
    assert torch.allclose(exact_shapley(v, n), _brute_force_shapley(v, n), atol=1e-12)


@pytest.mark.parametrize("n", [3, 8, 16])
def test_squared_sum_game(n):
    # v(C) = (sum_{i in C} w_i)^2  ->  phi_i = w_i * sum_j w_j
    w = torch.rand(n, dtype=DT, generator=torch.Generator().manual_seed(n)) + 0.1
    v = (coalition_masks(n).to(DT) @ w) ** 2
    phi = exact_shapley(v, n)
    assert torch.allclose(phi, w * w.sum(), rtol=1e-10, atol=1e-10)


def test_n16_float32_precision_and_batch():
    n = 16
    w = torch.rand(2, n, dtype=DT, generator=torch.Generator().manual_seed(3))
    v = (w @ coalition_masks(n).to(DT).T) ** 2  # [2, 2**16]
    phi = exact_shapley(v.float(), n)
    assert phi.shape == (2, n) and phi.dtype == torch.float32
    expected = w * w.sum(-1, keepdim=True)
    assert torch.allclose(phi.double(), expected, rtol=1e-4, atol=1e-4)


def test_glove_game():
    # Agent 0 owns a left glove, agents 1 and 2 a right glove each: v(C) = #pairs.
    m = coalition_masks(3)
    v = torch.minimum(m[:, 0].to(DT), m[:, 1:].sum(-1).to(DT))
    phi = exact_shapley(v, 3)
    assert torch.allclose(phi, torch.tensor([2 / 3, 1 / 6, 1 / 6], dtype=DT))


def test_weighted_majority_game():
    # [quota 51; weights 50, 49, 1]: player 0 is pivotal in 4 of 6 orderings.
    weights = torch.tensor([50.0, 49.0, 1.0], dtype=DT)
    v = ((coalition_masks(3).to(DT) @ weights) >= 51).to(DT)
    phi = exact_shapley(v, 3)
    assert torch.allclose(phi, torch.tensor([2 / 3, 1 / 6, 1 / 6], dtype=DT))
    # Simple majority games are not convex, and this Shapley value is outside the core.
    assert not is_convex(v, 3)
    assert not in_core(phi, v, 3)


def test_additive_game():
    n = 6
    r = torch.randn(4, n, dtype=DT, generator=torch.Generator().manual_seed(4))
    v = r @ coalition_masks(n).to(DT).T
    phi = exact_shapley(v, n)
    assert torch.allclose(phi, r, atol=1e-12)  # phi_i = v({i})
    assert is_convex(v, n).all()  # Proposition 2
    assert in_core(phi, v, n).all()


def test_efficiency_random_games():
    n = 7
    v = _random_game(n, 10, seed=5)
    v[..., 0] = torch.rand(10, dtype=DT)  # v(empty) != 0 is allowed by eq. 3
    phi = exact_shapley(v, n)
    assert is_efficient(phi, v, n).all()
    assert torch.allclose(phi.sum(-1), v[..., -1] - v[..., 0], atol=1e-12)
    assert not is_efficient(phi + 0.1, v, n).any()


def test_symmetry():
    n, i, j = 6, 1, 4
    v = _random_game(n, 5, seed=6)
    k = torch.arange(2**n)
    bit_i, bit_j = (k >> i) & 1, (k >> j) & 1
    swapped = k - (bit_i << i) - (bit_j << j) + (bit_i << j) + (bit_j << i)
    v_sym = (v + v[..., swapped]) / 2  # invariant under swapping agents i and j
    phi = exact_shapley(v_sym, n)
    assert torch.allclose(phi[..., i], phi[..., j], atol=1e-12)
    assert not torch.allclose(exact_shapley(v, n)[..., i], exact_shapley(v, n)[..., j])


def test_dummy_player():
    n, d = 6, 2
    v = _random_game(n, 5, seed=7)
    k = torch.arange(2**n)
    v_dummy = v[..., k & ~(1 << d)]  # v(C) = v(C \ {d}): d never contributes
    phi = exact_shapley(v_dummy, n)
    assert torch.allclose(phi[..., d], torch.zeros((), dtype=DT), atol=1e-12)


def test_additivity():
    n = 6
    v1, v2 = _random_game(n, 3, seed=8), _random_game(n, 3, seed=9)
    assert torch.allclose(
        exact_shapley(v1 + v2, n), exact_shapley(v1, n) + exact_shapley(v2, n), atol=1e-12
    )


def test_gradient_flows_to_values():
    n = 4
    v = _random_game(n, seed=10).requires_grad_()
    exact_shapley(v, n)[2].backward()
    assert torch.allclose(v.grad, shapley_matrix(n)[:, 2])


@pytest.mark.parametrize("antithetic", [True, False])
def test_sampled_within_three_standard_errors(antithetic):
    n = 8
    v = _random_game(n, 4, seed=11)
    exact = exact_shapley(v, n)
    calls = []

    def value_fn(masks):
        calls.append(masks.shape)
        idx = (masks.long() << torch.arange(n)).sum(-1)  # coalition index of each mask
        return v[..., idx]

    gen = torch.Generator().manual_seed(12)
    phi, stderr = sampled_shapley(value_fn, n, 400, gen, antithetic=antithetic)
    assert calls == [(400 * (n + 1), n)]  # one batched call
    assert phi.shape == stderr.shape == (4, n)
    assert (stderr > 0).all()
    assert ((phi - exact).abs() <= 3 * stderr).all()
    # every ordering's marginals telescope: the estimate is exactly efficient
    assert is_efficient(phi, v, n).all()


def test_sampled_large_n_additive():
    n = 30
    r = torch.rand(n, dtype=DT)
    phi, stderr = sampled_shapley(lambda m: m.to(DT) @ r, n, 8)
    assert torch.allclose(phi, r) and torch.allclose(stderr, torch.zeros(n, dtype=DT))


def test_permutations_and_prefixes():
    perms = sample_permutations(6, 5, generator=torch.Generator().manual_seed(0))
    assert (perms.sort(-1).values == torch.arange(5)).all()
    assert (perms[1] == perms[0].flip(0)).all()  # antithetic pair
    pre = permutation_prefix_masks(torch.tensor([[2, 0, 1]]))
    assert pre[0].tolist() == [[False, False, True], [True, False, True], [False, False, False]]
    # ordering 2, 0, 1 and its reverse; agents 0 and 2 (twice): the agents before it, plus it
    with_agents = prefixes_with_agents(torch.tensor([[2, 0, 1], [1, 0, 2]]), torch.tensor([0, 2]))
    assert with_agents.tolist() == [
        [[True, False, True], [True, True, False]],
        [[False, False, True], [True, True, True]],
    ]


def test_convex_game_shapley_in_core():
    # Theorem 2: v(C) = sum_{i in C} a_i + sum_{i<j in C} W_ij, W >= 0, is convex.
    n = 7
    g = torch.Generator().manual_seed(13)
    a = torch.rand(5, n, dtype=DT, generator=g)
    w = torch.rand(5, n, n, dtype=DT, generator=g).triu(1)
    m = coalition_masks(n).to(DT)
    v = m @ a.unsqueeze(-1)
    v = v.squeeze(-1) + torch.einsum("ki,bij,kj->bk", m, w, m)
    assert is_convex(v, n).all()
    assert in_core(exact_shapley(v, n), v, n).all()
    # Making the pair terms negative breaks convexity.
    v_bad = m @ a.unsqueeze(-1)
    v_bad = v_bad.squeeze(-1) - torch.einsum("ki,bij,kj->bk", m, w, m)
    assert not is_convex(v_bad, n).any()


def test_is_convex_matches_definition():
    n = 4
    k = torch.arange(2**n)
    size = coalition_masks(n).sum(-1).to(DT)
    g = torch.Generator().manual_seed(14)
    outcomes = []
    for trial in range(30):
        # convex size term plus integer noise: convex for some draws, not for others
        v = (trial % 4) * size**2 + torch.randint(0, 3, (2**n,), generator=g).to(DT)
        v[0] = 0
        definition = (v[k.view(-1, 1) | k] + v[k.view(-1, 1) & k] >= v.view(-1, 1) + v).all()
        assert bool(is_convex(v, n)) == bool(definition)
        outcomes.append(bool(definition))
    assert any(outcomes) and not all(outcomes)


def test_bad_input():
    with pytest.raises(ValueError, match="values"):
        exact_shapley(torch.zeros(7), 3)
    with pytest.raises(ValueError, match="sampled_shapley"):
        exact_shapley(torch.zeros(8), 40)
    with pytest.raises(ValueError, match="n must"):
        coalition_masks(0)
    with pytest.raises(ValueError, match="num_permutations"):
        sampled_shapley(lambda m: m.sum(-1).float(), 5, 0)
    with pytest.raises(ValueError, match="num_permutations"):
        sampled_shapley(lambda m: m.sum(-1).float(), 5, -4)
    with pytest.raises(ValueError, match="num_permutations"):
        sample_permutations(3, 5, antithetic=True)
    with pytest.raises(ValueError, match="value_fn"):
        sampled_shapley(lambda m: m.sum(-1)[:3].float(), 5, 4)
    with pytest.raises(ValueError, match="phi"):
        in_core(torch.zeros(2), torch.zeros(8), 3)
    with pytest.raises(ValueError, match="values"):
        is_convex(torch.zeros(9), 3)


def test_sampled_chunked_calls_match_single_call():
    n = 6
    v = _random_game(n, 3, seed=15)

    def value_fn(masks):
        sizes.append(masks.shape[0])
        return v[..., (masks.long() << torch.arange(n)).sum(-1)]

    sizes = []
    one = sampled_shapley(value_fn, n, 20, torch.Generator().manual_seed(1))
    assert sizes == [20 * (n + 1)]
    sizes = []
    chunked = sampled_shapley(
        value_fn, n, 20, torch.Generator().manual_seed(1), max_coalitions_per_call=30
    )
    assert sizes == [28] * 5  # whole orderings per call: 4 * (n + 1) masks
    assert torch.equal(one[0], chunked[0]) and torch.equal(one[1], chunked[1])
    with pytest.raises(ValueError, match="max_coalitions_per_call"):
        sampled_shapley(value_fn, n, 20, max_coalitions_per_call=3)
