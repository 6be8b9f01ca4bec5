"""Transferable-utility (TU) game core: coalitions, Shapley values, convexity and the core.

Everything here is a pure tensor function. A game over ``n`` agents is a tensor ``values`` of
shape ``[..., 2**n]`` where ``values[..., k]`` is ``v(C_k)`` and ``C_k`` is the coalition whose
member set is the binary expansion of ``k`` (bit ``i`` set means agent ``i`` is in ``C_k``).
Leading dimensions are independent games (for instance one game per state of a batch).

References are to Han et al., *Stable and Efficient Shapley Value-Based Reward Reallocation for
Multi-Agent RL of Autonomous Vehicles* (eq. 3 = the Shapley value, Theorem 1 = efficiency,
Definition 5 = convex game, Theorem 2 = Shapley value in the core of a convex game).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from functools import lru_cache

import torch

from mapets_rl.modules.tensor_checks import check_finite

__all__ = [
    "MAX_EXACT_AGENTS",
    "coalition_masks",
    "shapley_matrix",
    "exact_shapley",
    "sample_permutations",
    "permutation_prefix_masks",
    "prefixes_with_agents",
    "sampled_shapley",
    "is_efficient",
    "is_convex",
    "in_core",
]

#: Largest number of agents the exact (all-coalitions) path accepts: 2**20 coalitions per game.
MAX_EXACT_AGENTS = 20


def _check_n(n: int, *, exact: bool) -> None:
    if isinstance(n, bool) or not isinstance(n, int) or n < 1:
        raise ValueError(f"n must be a positive int, got {n!r}")
    if exact and n > MAX_EXACT_AGENTS:
        raise ValueError(
            f"n={n} is too large for the exact path (1 <= n <= {MAX_EXACT_AGENTS}: it needs all "
            f"2**n coalitions); use sampled_shapley(value_fn, n, num_permutations) instead"
        )


def _check_values(values: torch.Tensor, n: int) -> None:
    if not isinstance(values, torch.Tensor) or values.ndim < 1:
        raise ValueError("values must be a tensor of shape [..., 2**n]")
    if values.shape[-1] != 2**n:
        raise ValueError(
            f"values must have last dimension 2**n = {2**n} for n={n}, got shape "
            f"{tuple(values.shape)}"
        )
    if not values.is_floating_point():
        raise ValueError(f"values must be a floating-point tensor, got dtype {values.dtype}")
    check_finite("values", values)


def coalition_masks(n: int, device: torch.device | str | None = None) -> torch.Tensor:
    """All ``2**n`` coalitions of ``n`` agents as a boolean tensor ``[2**n, n]``.

    Row ``k`` is the coalition whose member set is the binary expansion of ``k``:
    ``masks[k, i]`` is True iff bit ``i`` of ``k`` is set.
    """
    _check_n(n, exact=True)
    k = torch.arange(2**n, device=device)
    bits = torch.arange(n, device=device)
    return ((k.unsqueeze(-1) >> bits) & 1).bool()


@lru_cache(maxsize=32)
def _shapley_matrix_cpu(n: int) -> torch.Tensor:
    # Weight of a marginal contribution to a coalition of size s (eq. 3):
    #   s! (n - s - 1)! / n!  =  1 / (n * C(n-1, s)),   s = 0..n-1, exact in float64.
    w = torch.tensor([1.0 / (n * math.comb(n - 1, s)) for s in range(n)], dtype=torch.float64)
    masks = coalition_masks(n)
    size = masks.sum(-1)
    plus = w[(size - 1).clamp(min=0)].unsqueeze(-1)  # v(C) enters phi_i, i in C, as v(C'+i)
    minus = w[size.clamp(max=n - 1)].unsqueeze(-1)  # v(C) enters phi_i, i not in C, as -v(C)
    return torch.where(masks, plus, -minus)


def shapley_matrix(
    n: int, dtype: torch.dtype = torch.float64, device: torch.device | str | None = None
) -> torch.Tensor:
    """The linear map from a game to its Shapley value: ``phi = values @ M``, ``M [2**n, n]``.

    Eq. 3 regrouped by coalition: ``M[k, i] = (|C_k|-1)!(n-|C_k|)!/n!`` if ``i in C_k`` and
    ``-|C_k|!(n-|C_k|-1)!/n!`` otherwise. Weights are computed exactly in float64 (no factorial
    overflow) and then cast; every column has absolute sum 2, so the product is well conditioned.
    """
    _check_n(n, exact=True)
    return _shapley_matrix_cpu(n).to(device=device, dtype=dtype)


def exact_shapley(values: torch.Tensor, n: int) -> torch.Tensor:
    """Exact Shapley value (eq. 3) of every game in a batch.

    Args:
        values: ``[..., 2**n]`` finite floating tensor, ``values[..., k] = v(C_k)`` (see module
            doc); NaN or infinite values raise ValueError.
        n: number of agents, ``1 <= n <= MAX_EXACT_AGENTS``.

    Returns:
        ``phi`` of shape ``[..., n]``, differentiable w.r.t. ``values``. One matrix product, no
        loop over coalitions or agents. ``phi.sum(-1) == v(N) - v(empty)`` (Theorem 1).
    """
    _check_n(n, exact=True)
    _check_values(values, n)
    m = shapley_matrix(n, dtype=values.dtype, device=values.device)
    return values @ m


def sample_permutations(
    num_permutations: int,
    n: int,
    *,
    antithetic: bool = True,
    generator: torch.Generator | None = None,
    device: torch.device | str | None = None,
) -> torch.Tensor:
    """Uniformly random agent orderings ``[num_permutations, n]`` (row p = agents in order).

    With ``antithetic=True`` rows come in pairs ``(pi, reversed(pi))`` (rows ``2q`` and ``2q+1``);
    ``num_permutations`` must then be even.
    """
    _check_n(n, exact=False)
    if isinstance(num_permutations, bool) or not isinstance(num_permutations, int):
        raise ValueError(f"num_permutations must be a positive int, got {num_permutations!r}")
    if num_permutations < 1:
        raise ValueError(f"num_permutations must be >= 1, got {num_permutations}")
    if antithetic and num_permutations % 2:
        raise ValueError(
            f"num_permutations must be even when antithetic=True, got {num_permutations}"
        )
    draws = num_permutations // 2 if antithetic else num_permutations
    gen_device = generator.device if generator is not None else device
    keys = torch.rand(draws, n, generator=generator, device=gen_device)
    perms = keys.argsort(dim=-1).to(device)
    if antithetic:
        perms = torch.stack([perms, perms.flip(-1)], dim=1).reshape(num_permutations, n)
    return perms


def permutation_prefix_masks(perms: torch.Tensor) -> torch.Tensor:
    """Coalitions preceding each agent: ``[P, n] -> bool [P, n(agent i), n]``.

    ``out[p, i, j]`` is True iff agent ``j`` comes before agent ``i`` in ordering ``p``.
    """
    if perms.ndim != 2:
        raise ValueError(f"perms must have shape [P, n], got {tuple(perms.shape)}")
    pos = perms.argsort(dim=-1)  # pos[p, i] = position of agent i in ordering p
    return pos.unsqueeze(-1) > pos.unsqueeze(-2)


def prefixes_with_agents(perms: torch.Tensor, agents: torch.Tensor) -> torch.Tensor:
    """The coalitions at which a permutation estimate reads each given agent's value with it:
    ``perms [P, n]``, agent indices ``[K]`` -> bool ``[K, P, n]``, row ``k`` holding the agents
    before ``agents[k]`` in each ordering, plus ``agents[k]``."""
    before = permutation_prefix_masks(perms).transpose(0, 1)[agents]  # [K, P, n]
    own = torch.nn.functional.one_hot(agents, perms.shape[-1]).bool().unsqueeze(-2)
    return before | own


def sampled_shapley(
    value_fn: Callable[[torch.Tensor], torch.Tensor],
    n: int,
    num_permutations: int,
    generator: torch.Generator | None = None,
    *,
    antithetic: bool = True,
    max_coalitions_per_call: int | None = None,
    device: torch.device | str | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Monte-Carlo permutation estimate of the Shapley value, with its standard error.

    ``phi_i = E_pi[v(P_i(pi) + i) - v(P_i(pi))]`` where ``P_i(pi)`` is the set of agents before
    ``i`` in a uniformly random ordering ``pi`` (eq. 3 rewritten over orderings).

    Args:
        value_fn: maps bool masks ``[K, n]`` to values ``[..., K]`` (any leading batch shape,
            e.g. one game per state). Called once with all ``num_permutations * (n + 1)``
            prefix coalitions of all orderings (or in chunks, see below).
        n: number of agents (>= 1, no upper limit).
        num_permutations: orderings to sample, >= 2 (even and >= 4 with ``antithetic``).
        generator: optional ``torch.Generator`` for reproducibility.
        antithetic: pair every ordering with its reverse (variance reduction); the standard
            error is then computed over the pair means.
        max_coalitions_per_call: bound on ``K`` per ``value_fn`` call to cap memory; the masks
            are then split into consecutive chunks (whole orderings each). ``None``: one call.
        device: device of the masks handed to ``value_fn``.

    Returns:
        ``(phi, stderr)``, both ``[..., n]``. Every ordering's marginals telescope to
        ``v(N) - v(empty)``, so ``phi`` is exactly efficient.
    """
    _check_n(n, exact=False)
    if isinstance(num_permutations, bool) or not isinstance(num_permutations, int):
        raise ValueError(f"num_permutations must be a positive int, got {num_permutations!r}")
    min_perms = 4 if antithetic else 2
    if num_permutations < min_perms:
        raise ValueError(
            f"num_permutations must be >= {min_perms} (antithetic={antithetic}) to estimate a "
            f"standard error, got {num_permutations}"
        )
    if max_coalitions_per_call is not None and (
        not isinstance(max_coalitions_per_call, int) or max_coalitions_per_call < n + 1
    ):
        raise ValueError(
            f"max_coalitions_per_call must be None or an int >= n + 1 = {n + 1}, "
            f"got {max_coalitions_per_call!r}"
        )
    perms = sample_permutations(
        num_permutations, n, antithetic=antithetic, generator=generator, device=device
    )
    # Prefix coalitions of every ordering: prefixes[p, j] = first j agents of ordering p.
    steps = torch.arange(n + 1, device=perms.device)
    pos = perms.argsort(dim=-1)  # [P, n]
    prefixes = pos.unsqueeze(1) < steps.view(1, n + 1, 1)  # [P, n+1, n]
    flat = prefixes.reshape(-1, n)
    chunk = flat.shape[0] if max_coalitions_per_call is None else max_coalitions_per_call
    chunk = (chunk // (n + 1)) * (n + 1)
    parts = []
    for masks in flat.split(chunk):
        part = value_fn(masks)
        if part.ndim < 1 or part.shape[-1] != masks.shape[0]:
            raise ValueError(
                f"value_fn must return values [..., K] with K = {masks.shape[0]} "
                f"(one per mask), got shape {tuple(part.shape)}"
            )
        check_finite("value_fn's values", part)
        parts.append(part)
    values = torch.cat(parts, dim=-1)
    values = values.unflatten(-1, (num_permutations, n + 1))
    marginal_by_pos = values[..., 1:] - values[..., :-1]  # [..., P, n] by position
    idx = pos.expand(*marginal_by_pos.shape[:-2], -1, -1)
    marginal = marginal_by_pos.gather(-1, idx)  # [..., P, n] by agent
    if antithetic:
        marginal = marginal.unflatten(-2, (num_permutations // 2, 2)).mean(-2)
    samples = marginal.shape[-2]
    phi = marginal.mean(-2)
    stderr = marginal.std(-2, correction=1) / math.sqrt(samples)
    return phi, stderr


def is_efficient(
    phi: torch.Tensor, values: torch.Tensor, n: int, *, rtol: float = 1e-5, atol: float = 1e-6
) -> torch.Tensor:
    """Efficiency (Theorem 1): ``sum_i phi_i == v(N) - v(empty)``.

    Args:
        phi: ``[..., n]``; values: ``[..., 2**n]``.

    Returns:
        bool ``[...]``.
    """
    _check_n(n, exact=True)
    _check_values(values, n)
    if phi.shape[-1] != n:
        raise ValueError(f"phi must have last dimension n={n}, got shape {tuple(phi.shape)}")
    total = values[..., -1] - values[..., 0]
    return torch.isclose(phi.sum(-1).to(total.dtype), total, rtol=rtol, atol=atol)


def _pair_indices(n: int, device: torch.device) -> tuple[torch.Tensor, ...]:
    """Indices of (C, C+i, C+j, C+i+j) for all C and agents i < j not in C, flattened."""
    k = torch.arange(2**n, device=device)
    ii, jj = torch.triu_indices(n, n, offset=1, device=device)
    bi, bj = (1 << ii), (1 << jj)
    base = k.unsqueeze(-1)  # [2**n, 1]
    valid = ((base & bi) == 0) & ((base & bj) == 0)  # [2**n, n(n-1)/2]
    c = base.expand_as(valid)[valid]
    ci = (base | bi).expand_as(valid)[valid]
    cj = (base | bj).expand_as(valid)[valid]
    cij = (base | bi | bj).expand_as(valid)[valid]
    return c, ci, cj, cij


def is_convex(values: torch.Tensor, n: int, *, atol: float = 1e-6) -> torch.Tensor:
    """Convexity (Definition 5): ``v(C u D) + v(C n D) >= v(C) + v(D)`` for all ``C, D``.

    Checked through the equivalent local condition (supermodularity on the Boolean lattice):
    ``v(C+i+j) - v(C+j) >= v(C+i) - v(C)`` for every ``C`` and ``i != j`` outside ``C``, i.e.
    ``2**(n-2) * n(n-1)/2`` inequalities instead of ``4**n``, all in one gather.

    Args:
        values: ``[..., 2**n]``; atol: tolerance on each inequality.

    Returns:
        bool ``[...]``.
    """
    _check_n(n, exact=True)
    _check_values(values, n)
    if n < 2:
        return torch.ones(values.shape[:-1], dtype=torch.bool, device=values.device)
    c, ci, cj, cij = _pair_indices(n, values.device)
    gap = values[..., cij] - values[..., cj] - values[..., ci] + values[..., c]
    return (gap >= -atol).all(-1)


def in_core(phi: torch.Tensor, values: torch.Tensor, n: int, *, atol: float = 1e-6) -> torch.Tensor:
    """Core membership (Definition 1): ``x(C) >= v(C)`` for every ``C`` and ``x(N) = v(N)``.

    Args:
        phi: payoff vectors ``[..., n]``; values: ``[..., 2**n]`` with ``v(empty) = 0``.

    Returns:
        bool ``[...]``: True where ``phi`` is an efficient, coalitionally rational payoff.
    """
    _check_n(n, exact=True)
    _check_values(values, n)
    if phi.shape[-1] != n:
        raise ValueError(f"phi must have last dimension n={n}, got shape {tuple(phi.shape)}")
    masks = coalition_masks(n, device=values.device).to(values.dtype)
    payoff = phi.to(values.dtype) @ masks.T  # [..., 2**n], x(C_k)
    rational = (payoff >= values - atol).all(-1)
    efficient = (payoff[..., -1] - values[..., -1]).abs() <= atol
    return rational & efficient
