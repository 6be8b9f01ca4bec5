"""Losses (torchrl LossModules)."""

from mapets_rl.objectives.ensemble_nll import EnsembleNLLLoss

__all__ = ["EnsembleNLLLoss"]
