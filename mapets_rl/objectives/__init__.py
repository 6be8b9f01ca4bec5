"""Losses (torchrl LossModules)."""

from mapets_rl.objectives.ensemble_nll import EnsembleNLLLoss, train_ensemble
from mapets_rl.objectives.shapley_actor_critic import ShapleyActorCriticLoss

__all__ = ["EnsembleNLLLoss", "ShapleyActorCriticLoss", "train_ensemble"]
