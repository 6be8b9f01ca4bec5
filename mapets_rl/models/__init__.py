"""Dynamics models: per-agent probabilistic ensembles (MA-PETS sec. IV-A)."""

from mapets_rl.models.config import EnsembleConfig
from mapets_rl.models.ensemble import ProbabilisticEnsemble

__all__ = ["EnsembleConfig", "ProbabilisticEnsemble"]
