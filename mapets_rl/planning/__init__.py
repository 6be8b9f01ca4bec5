"""Planning: batched multi-agent CEM with trajectory sampling (MA-PETS sec. IV-B)."""

from mapets_rl.planning.cem import RewardFn, TerminationFn, TrajectorySamplingCEM
from mapets_rl.planning.config import CPU_PRESET, PAPER_PRESET, PRESETS, PROPAGATIONS, PlannerConfig

__all__ = [
    "TrajectorySamplingCEM",
    "RewardFn",
    "TerminationFn",
    "PlannerConfig",
    "PAPER_PRESET",
    "CPU_PRESET",
    "PRESETS",
    "PROPAGATIONS",
]
