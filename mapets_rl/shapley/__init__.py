"""Shapley-value reward reallocation (Han et al.): TU-game core, coalition critic, actors."""

from mapets_rl.shapley.actor import CoalitionObservation, make_coalition_actor
from mapets_rl.shapley.coalition import RandomCoalition, uniform_size_coalition
from mapets_rl.shapley.critic import CoalitionCritic
from mapets_rl.shapley.game import (
    MAX_EXACT_AGENTS,
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

__all__ = [
    "CoalitionCritic",
    "CoalitionObservation",
    "make_coalition_actor",
    "RandomCoalition",
    "uniform_size_coalition",
    "MAX_EXACT_AGENTS",
    "coalition_masks",
    "exact_shapley",
    "in_core",
    "is_convex",
    "is_efficient",
    "permutation_prefix_masks",
    "prefixes_with_agents",
    "sample_permutations",
    "sampled_shapley",
    "shapley_matrix",
]
