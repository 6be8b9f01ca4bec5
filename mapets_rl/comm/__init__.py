"""Communication-range data sharing between CAVs (MA-PETS sec. III-B, V-B2, VI).

- :class:`CommunicationRange`: TorchRL transform writing the range-``d`` communication graph.
- :class:`NeighbourDatasets`: per-agent datasets ``D(i)+`` with end-of-episode exchange and
  overhead accounting, over one shared torchrl storage.
- :func:`clique_cover`, :func:`clique_cover_number`: (minimum) clique cover of the graph.
- :func:`group_regret_bound`: Theorem 1, eq. (21).
- :func:`plan_schedule`: the neighbours' broadcast plans as known future speeds
  (``comm.share_plans``).
- :class:`FederatedConsensus`: FIRL's gradient consensus over the graph and periodic parameter
  averaging of independent learners, with their bytes.
"""

from mapets_rl.comm.clique import (
    EXACT_MAX_NODES,
    CliqueCover,
    clique_cover,
    clique_cover_number,
)
from mapets_rl.comm.config import CommConfig
from mapets_rl.comm.consensus import FederatedConsensus
from mapets_rl.comm.datasets import ExchangeStats, NeighbourDatasets
from mapets_rl.comm.plans import plan_schedule
from mapets_rl.comm.regret import group_regret_bound
from mapets_rl.comm.transform import CommunicationRange, communication_graph

__all__ = [
    "CommConfig",
    "EXACT_MAX_NODES",
    "CliqueCover",
    "CommunicationRange",
    "ExchangeStats",
    "FederatedConsensus",
    "NeighbourDatasets",
    "clique_cover",
    "clique_cover_number",
    "communication_graph",
    "group_regret_bound",
    "plan_schedule",
]
