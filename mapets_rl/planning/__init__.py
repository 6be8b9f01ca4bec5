"""Planning: batched multi-agent CEM with trajectory sampling (MA-PETS sec. IV-B).

Three pieces, as mbrl-lib splits PETS: :class:`CEMOptimizer` and its :class:`ICEMOptimizer`
subclass (pure optimisers over action sequences, chosen by
:meth:`PlannerConfig.make_optimizer`), :func:`trajectory_sampling_returns` (scores of candidate
sequences through any :class:`DynamicsModel`) and :class:`TrajectorySamplingCEM` (the policy
module that composes them, keeps its frozen :class:`PlannerConfig` and the warm start);
:class:`PlanSharingPlanner` makes its agents plan with each other's broadcast plans.
"""

from mapets_rl.planning.cem import CEMOptimizer, ICEMOptimizer, ScoreFn
from mapets_rl.planning.config import CPU_PRESET, PAPER_PRESET, PRESETS, PlannerConfig, Preset
from mapets_rl.planning.mpc import TrajectorySamplingCEM
from mapets_rl.planning.precision import DTYPE_CHOICES, resolve_dtype
from mapets_rl.planning.shared_plans import PlanSharingPlanner
from mapets_rl.planning.trajectory_sampling import (
    PROPAGATIONS,
    DynamicsModel,
    RewardFn,
    TerminationFn,
    expected_trajectory,
    trajectory_sampling_returns,
)

__all__ = [
    "CEMOptimizer",
    "ICEMOptimizer",
    "DynamicsModel",
    "ScoreFn",
    "TrajectorySamplingCEM",
    "RewardFn",
    "TerminationFn",
    "trajectory_sampling_returns",
    "expected_trajectory",
    "PlanSharingPlanner",
    "PlannerConfig",
    "Preset",
    "PAPER_PRESET",
    "CPU_PRESET",
    "PRESETS",
    "PROPAGATIONS",
    "DTYPE_CHOICES",
    "resolve_dtype",
]
