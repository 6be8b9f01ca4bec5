"""Minimum clique cover of a communication graph (MA-PETS sec. V-B2, Lemma 6, Fig. 7).

A clique cover of ``G`` partitions its nodes into cliques; its minimum size ``chi_bar(G)`` is the
chromatic number of the complement of ``G`` (two agents may share a clique iff they are linked).
The cover also splits over the connected components of ``G``, so each component is solved on
its own:

- exact: branch and bound over DSATUR colourings of the component's complement (Brelaz), seeded
  with a maximum clique of the complement (a lower bound that also fixes colour symmetry) and the
  best greedy colouring as the first upper bound. Used by default for components of at most
  ``EXACT_MAX_NODES`` nodes (exponential in the worst case beyond).
- greedy: the best of networkx's greedy colourings of the complement (strategies
  ``largest_first``, ``smallest_last``, ``DSATUR``). An upper bound on ``chi_bar``.

``CliqueCover.exact`` tells which was used: ``True`` only when every component was solved
exactly, i.e. the cover is proven minimum.
"""

from __future__ import annotations

from collections.abc import Hashable

import networkx as nx
import numpy as np
import torch

__all__ = ["EXACT_MAX_NODES", "CliqueCover", "clique_cover", "clique_cover_number"]

EXACT_MAX_NODES = 32
"""Largest connected component solved exactly when ``exact=None`` (auto)."""

_GREEDY_STRATEGIES = ("largest_first", "smallest_last", "DSATUR")


class CliqueCover(list):
    """A clique cover: a ``list[set]`` of node sets, each a clique, partitioning the nodes.

    Attributes:
        exact: ``True`` if the cover is proven minimum (exact algorithm on every component),
            ``False`` if some component used the greedy upper bound.
    """

    def __init__(self, cliques: list[set], exact: bool) -> None:
        super().__init__(cliques)
        self.exact = bool(exact)

    @property
    def number(self) -> int:
        """The number of cliques (``chi_bar`` when ``exact``, an upper bound otherwise)."""
        return len(self)

    def __repr__(self) -> str:
        return f"CliqueCover({list.__repr__(self)}, exact={self.exact})"


def _as_graph(graph: nx.Graph | torch.Tensor | np.ndarray) -> nx.Graph:
    if isinstance(graph, nx.Graph):
        if graph.is_directed():
            raise ValueError("graph must be undirected")
        out = nx.Graph()
        out.add_nodes_from(graph.nodes)
        out.add_edges_from((u, v) for u, v in graph.edges if u != v)
        return out
    if isinstance(graph, torch.Tensor):
        adjacency = graph.detach().to("cpu", torch.bool).numpy()
    elif isinstance(graph, np.ndarray):
        adjacency = graph.astype(bool)
    else:
        raise ValueError(
            "graph must be a networkx.Graph or a square bool adjacency (torch.Tensor or "
            f"numpy.ndarray), got {type(graph).__name__}"
        )
    if adjacency.ndim != 2 or adjacency.shape[0] != adjacency.shape[1]:
        raise ValueError(f"graph adjacency must have shape (n, n), got {adjacency.shape}")
    if not np.array_equal(adjacency, adjacency.T):
        raise ValueError("graph adjacency must be symmetric (an undirected graph)")
    rows, cols = np.nonzero(np.triu(adjacency, 1))
    out = nx.Graph()
    out.add_nodes_from(range(adjacency.shape[0]))
    out.add_edges_from(zip(rows.tolist(), cols.tolist(), strict=True))
    return out


def _greedy_cover(component: nx.Graph) -> list[set]:
    complement = nx.complement(component)
    best: dict[Hashable, int] | None = None
    for strategy in _GREEDY_STRATEGIES:
        colouring = nx.greedy_color(complement, strategy=strategy)
        if best is None or max(colouring.values()) < max(best.values()):
            best = colouring
    return _classes(best)


def _classes(colouring: dict[Hashable, int]) -> list[set]:
    classes: dict[int, set] = {}
    for node, colour in colouring.items():
        classes.setdefault(colour, set()).add(node)
    return [classes[c] for c in sorted(classes)]


def _exact_cover(component: nx.Graph) -> list[set]:
    """Minimum colouring of the complement by DSATUR branch and bound (bitmask sets)."""
    nodes = list(component.nodes)
    n = len(nodes)
    index = {v: k for k, v in enumerate(nodes)}
    full = (1 << n) - 1
    # conflict[v]: nodes that cannot share a clique with v (non-neighbours in G, v excluded).
    conflict = []
    for v in nodes:
        linked = 0
        for u in component.adj[v]:
            linked |= 1 << index[u]
        conflict.append(full & ~linked & ~(1 << index[v]))

    greedy = _greedy_cover(component)
    best_k = len(greedy)
    best_colour = [0] * n
    for c, clique in enumerate(greedy):
        for v in clique:
            best_colour[index[v]] = c

    complement = nx.complement(component)
    seed_clique, lower = nx.max_weight_clique(complement, weight=None)
    if lower >= best_k:
        return greedy

    colour = [-1] * n
    classes: list[int] = []  # bitmask of the nodes of each colour class
    for c, v in enumerate(seed_clique):
        colour[index[v]] = c
        classes.append(1 << index[v])
    uncoloured = full
    for v in seed_clique:
        uncoloured &= ~(1 << index[v])

    def choose(uncol: int) -> int:
        best_v, best_key = -1, (-1, -1)
        rest = uncol
        while rest:
            low = rest & -rest
            v = low.bit_length() - 1
            rest ^= low
            saturation = sum(1 for m in classes if m & conflict[v])
            key = (saturation, (conflict[v] & uncol).bit_count())
            if key > best_key:
                best_v, best_key = v, key
        return best_v

    def search(uncol: int) -> bool:
        """Returns True once an optimal colouring (= lower bound) is found."""
        nonlocal best_k, best_colour
        k = len(classes)
        if k >= best_k:
            return False
        if not uncol:
            best_k, best_colour = k, colour.copy()
            return best_k == lower
        v = choose(uncol)
        bit = 1 << v
        for c in range(k):
            if not classes[c] & conflict[v]:
                classes[c] |= bit
                colour[v] = c
                if search(uncol & ~bit):
                    return True
                classes[c] &= ~bit
        if k + 1 < best_k:
            classes.append(bit)
            colour[v] = k
            if search(uncol & ~bit):
                return True
            classes.pop()
        colour[v] = -1
        return False

    search(uncoloured)
    cover: dict[int, set] = {}
    for k, c in enumerate(best_colour):
        cover.setdefault(c, set()).add(nodes[k])
    return [cover[c] for c in sorted(cover)]


def clique_cover(
    graph: nx.Graph | torch.Tensor | np.ndarray,
    exact: bool | None = None,
    exact_max_nodes: int = EXACT_MAX_NODES,
) -> CliqueCover:
    """Clique cover of an undirected graph (partition of its nodes into cliques).

    Args:
        graph: a ``networkx.Graph`` or a symmetric bool adjacency ``[n, n]`` (torch or numpy;
            the diagonal is ignored; nodes are then ``0..n-1``).
        exact: ``True``: exact minimum on every connected component (exponential worst case);
            ``False``: greedy upper bound; ``None`` (default): exact for components of at most
            ``exact_max_nodes`` nodes, greedy beyond.
        exact_max_nodes: component size limit of the automatic choice (``>= 1``).

    Returns:
        A :class:`CliqueCover` (a ``list[set]``) whose ``exact`` attribute says whether it is a
        proven minimum cover. ``len(cover)`` is ``chi_bar(G)`` when exact.
    """
    if exact is not None and not isinstance(exact, bool):
        raise ValueError(f"exact must be True, False or None, got {exact!r}")
    if int(exact_max_nodes) < 1:
        raise ValueError(f"exact_max_nodes must be >= 1, got {exact_max_nodes}")
    g = _as_graph(graph)
    cliques: list[set] = []
    all_exact = True
    order = {v: k for k, v in enumerate(g.nodes)}
    components = sorted(nx.connected_components(g), key=lambda c: min(order[v] for v in c))
    for nodes in components:
        component = g.subgraph(nodes)
        use_exact = len(nodes) <= exact_max_nodes if exact is None else exact
        cliques.extend(_exact_cover(component) if use_exact else _greedy_cover(component))
        all_exact &= use_exact
    return CliqueCover(cliques, exact=all_exact)


def clique_cover_number(
    graph: nx.Graph | torch.Tensor | np.ndarray,
    exact: bool | None = None,
    exact_max_nodes: int = EXACT_MAX_NODES,
) -> int:
    """Size of :func:`clique_cover` (``chi_bar(G)``, paper Lemma 6 / Fig. 7).

    Exact when every connected component has at most ``exact_max_nodes`` nodes (or
    ``exact=True``); otherwise a greedy upper bound. Use ``clique_cover(...).exact`` to get the
    flag with the number.
    """
    return len(clique_cover(graph, exact=exact, exact_max_nodes=exact_max_nodes))
