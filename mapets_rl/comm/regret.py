"""Group regret bound with limited-range communication (MA-PETS Theorem 1, eq. (21))."""

from __future__ import annotations

import math

__all__ = ["group_regret_bound"]


def _positive(name: str, value: float) -> float:
    value = float(value)
    if not value > 0 or math.isinf(value):
        raise ValueError(f"{name} must be a finite number > 0, got {value}")
    return value


def group_regret_bound(
    n_agents: int,
    T: float,
    S: int,
    A: int,
    D: float,
    chi: float,
    delta: float = 0.05,
    C1: float = 1.0,
    C2: float = 1.0,
) -> float:
    """Upper bound on the group regret after ``T`` steps, MA-PETS Theorem 1, eq. (21).

    Regret_G(T) <= sqrt(C1 I T log(8IT/delta)) + I sqrt(T) [1 + (1 + sqrt2) sqrt(SA)]
                   + D sqrt(4 C1 I T log(8IT/delta)) + D S A I log2(8T/(SA))
                   + (1 + sqrt2) D S sqrt(C2 chi I A T log(2AT/delta)),

    holding with probability at least ``1 - delta``. Only the last term depends on the
    communication graph, through its clique cover number ``chi`` (``1`` for the complete graph,
    ``I`` without communication).

    Args:
        n_agents: ``I >= 1``.
        T: number of steps, ``T >= 1`` and ``8T >= S A`` (the ``log2`` term is negative
            otherwise and the bound is vacuous).
        S: number of states ``>= 1``.
        A: number of actions ``>= 1``.
        D: MDP diameter ``>= 0``.
        chi: clique cover number ``chi_bar(G_d)`` in ``[1, I]``.
        delta: confidence in ``(0, 1)``.
        C1, C2: the theorem's positive constants.

    Returns:
        The bound (a float).
    """
    if isinstance(n_agents, bool) or int(n_agents) != n_agents or n_agents < 1:
        raise ValueError(f"n_agents must be an integer >= 1, got {n_agents}")
    n = int(n_agents)
    T = float(T)
    if not 1.0 <= T < math.inf:
        raise ValueError(f"T must be a finite number >= 1, got {T}")
    S = _positive("S", S)
    A = _positive("A", A)
    if S < 1:
        raise ValueError(f"S must be >= 1, got {S}")
    if A < 1:
        raise ValueError(f"A must be >= 1, got {A}")
    if 8.0 * T < S * A:
        raise ValueError(f"T must satisfy 8T >= S*A = {S * A}, got T={T}")
    D = float(D)
    if not 0.0 <= D < math.inf:
        raise ValueError(f"D must be a finite number >= 0, got {D}")
    chi = float(chi)
    if not 1.0 <= chi <= n:
        raise ValueError(f"chi must be in [1, n_agents={n}], got {chi}")
    delta = float(delta)
    if not 0.0 < delta < 1.0:
        raise ValueError(f"delta must be in (0, 1), got {delta}")
    C1 = _positive("C1", C1)
    C2 = _positive("C2", C2)

    sqrt2 = math.sqrt(2.0)
    log_it = math.log(8.0 * n * T / delta)
    bound = (
        math.sqrt(C1 * n * T * log_it)
        + n * math.sqrt(T) * (1.0 + (1.0 + sqrt2) * math.sqrt(S * A))
        + D * math.sqrt(4.0 * C1 * n * T * log_it)
        + D * S * A * n * math.log2(8.0 * T / (S * A))
        + (1.0 + sqrt2) * D * S * math.sqrt(C2 * chi * n * A * T * math.log(2.0 * A * T / delta))
    )  # eq. (21)
    return bound
