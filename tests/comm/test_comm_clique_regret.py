"""Clique cover (exact and greedy) and the Theorem 1 group regret bound."""

import itertools
import math

import networkx as nx
import numpy as np
import pytest
import torch

from mapets_rl.comm import clique_cover, clique_cover_number, group_regret_bound


def _assert_valid_cover(graph: nx.Graph, cover) -> None:
    nodes = [v for clique in cover for v in clique]
    assert sorted(nodes, key=str) == sorted(graph.nodes, key=str)  # a partition
    for clique in cover:
        for u, v in itertools.combinations(clique, 2):
            assert graph.has_edge(u, v)


def _brute_force_cover_number(graph: nx.Graph) -> int:
    """Minimum clique partition by dynamic programming over node subsets (small n)."""
    nodes = list(graph.nodes)
    n = len(nodes)
    is_clique = [True] * (1 << n)
    for mask in range(1 << n):
        members = [k for k in range(n) if mask >> k & 1]
        is_clique[mask] = all(
            graph.has_edge(nodes[a], nodes[b]) for a, b in itertools.combinations(members, 2)
        )
    best = [0] + [n + 1] * ((1 << n) - 1)
    for mask in range(1, 1 << n):
        low = mask & -mask
        rest = mask ^ low
        sub = rest
        while True:  # cliques containing the lowest node of `mask`
            if is_clique[sub | low]:
                best[mask] = min(best[mask], 1 + best[mask ^ (sub | low)])
            if sub == 0:
                break
            sub = (sub - 1) & rest
    return best[(1 << n) - 1]


@pytest.mark.parametrize(
    "graph, expected",
    [
        (nx.complete_graph(7), 1),
        (nx.empty_graph(6), 6),
        (nx.cycle_graph(5), 3),
        (nx.cycle_graph(7), 4),
        (nx.petersen_graph(), 5),
        (nx.disjoint_union(nx.complete_graph(3), nx.cycle_graph(5)), 4),
    ],
)
def test_exact_cover_on_known_graphs(graph, expected):
    cover = clique_cover(graph)
    assert cover.exact
    assert len(cover) == cover.number == clique_cover_number(graph) == expected
    _assert_valid_cover(graph, cover)


def test_exact_matches_brute_force_and_greedy_is_an_upper_bound():
    rng = np.random.default_rng(0)
    for trial in range(40):
        n = int(rng.integers(2, 11))
        graph = nx.gnp_random_graph(n, float(rng.uniform(0.2, 0.8)), seed=trial)
        exact = clique_cover(graph, exact=True)
        greedy = clique_cover(graph, exact=False)
        _assert_valid_cover(graph, exact)
        _assert_valid_cover(graph, greedy)
        assert exact.exact and not greedy.exact
        assert len(exact) == _brute_force_cover_number(graph)
        assert len(greedy) >= len(exact)
    for trial in range(10):  # up to 16 nodes and beyond: exact never above greedy
        graph = nx.gnp_random_graph(18, 0.5, seed=100 + trial)
        exact, greedy = clique_cover(graph), clique_cover(graph, exact=False)
        _assert_valid_cover(graph, exact)
        assert exact.exact and len(greedy) >= len(exact)


def test_automatic_choice_and_flag():
    c5 = nx.cycle_graph(5)
    assert not clique_cover(c5, exact_max_nodes=4).exact  # component too big: greedy
    assert clique_cover(c5, exact_max_nodes=5).exact
    two = nx.disjoint_union(nx.cycle_graph(5), nx.path_graph(2))
    assert not clique_cover(two, exact_max_nodes=4).exact
    assert clique_cover(two, exact=True, exact_max_nodes=1).exact


def test_bool_adjacency_input():
    c5 = nx.to_numpy_array(nx.cycle_graph(5), dtype=bool)
    assert clique_cover_number(torch.from_numpy(c5)) == 3
    assert clique_cover_number(c5) == 3
    with_loops = c5 | np.eye(5, dtype=bool)  # self-loops are ignored
    assert clique_cover_number(with_loops) == 3
    assert clique_cover_number(torch.zeros(4, 4, dtype=torch.bool)) == 4
    assert clique_cover_number(~torch.eye(4, dtype=torch.bool)) == 1


@pytest.mark.parametrize(
    "graph",
    [
        torch.zeros(3, 4, dtype=torch.bool),
        torch.zeros(2, 3, 3, dtype=torch.bool),
        torch.tensor([[False, True], [False, False]]),
        [[0, 1], [1, 0]],
        nx.DiGraph([(0, 1)]),
    ],
)
def test_bad_graph_raises(graph):
    with pytest.raises(ValueError, match="graph"):
        clique_cover(graph)


def test_bad_options_raise():
    with pytest.raises(ValueError, match="exact_max_nodes"):
        clique_cover(nx.cycle_graph(3), exact_max_nodes=0)
    with pytest.raises(ValueError, match="exact"):
        clique_cover(nx.cycle_graph(3), exact="yes")


BASE = {"n_agents": 8, "T": 3000, "S": 20, "A": 4, "D": 5.0, "chi": 4}


def test_regret_bound_known_value():
    # D = 0 keeps two terms; delta = 8 / e^3 makes log(8IT/delta) = 3 with I = T = 1.
    delta = 8.0 / math.e**3
    value = group_regret_bound(1, 1, 1, 1, 0.0, 1, delta=delta)
    assert value == pytest.approx(math.sqrt(3.0) + 1.0 + (1.0 + math.sqrt(2.0)))
    # The chi term: (1 + sqrt2) D S sqrt(C2 chi I A T log(2AT/delta)).
    kwargs = {k: v for k, v in BASE.items() if k != "chi"}
    diff = group_regret_bound(**kwargs, chi=4) - group_regret_bound(**kwargs, chi=1)
    scale = (1 + math.sqrt(2)) * 5.0 * 20 * math.sqrt(8 * 4 * 3000 * math.log(2 * 4 * 3000 / 0.05))
    assert diff == pytest.approx(scale * (2.0 - 1.0))


def test_regret_bound_grows_with_chi():
    values = [group_regret_bound(**{**BASE, "chi": chi}) for chi in range(1, 9)]
    assert all(b > a for a, b in itertools.pairwise(values))


def test_per_agent_regret_bound_shrinks_with_more_agents():
    per_agent = [
        group_regret_bound(**{**BASE, "n_agents": n, "chi": 1}) / n for n in (1, 2, 4, 8, 16, 64)
    ]
    assert all(b < a for a, b in itertools.pairwise(per_agent))


@pytest.mark.parametrize(
    "name, value",
    [
        ("n_agents", 0),
        ("n_agents", 2.5),
        ("T", 0.5),
        ("T", 1),  # 8T < S*A = 80
        ("S", 0),
        ("A", -1),
        ("D", -1.0),
        ("chi", 0.5),
        ("chi", 9),  # > n_agents
        ("delta", 0.0),
        ("delta", 1.0),
        ("C1", 0.0),
        ("C2", -2.0),
    ],
)
def test_regret_bound_domain_errors(name, value):
    with pytest.raises(ValueError, match=name):
        group_regret_bound(**{**BASE, name: value})
