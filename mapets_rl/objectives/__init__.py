"""Losses (torchrl LossModules)."""

from mapets_rl.objectives.ensemble_nll import EnsembleNLLLoss, ensemble_optimizer, train_ensemble
from mapets_rl.objectives.shapley_actor_critic import ShapleyActorCriticLoss

__all__ = ["EnsembleNLLLoss", "ShapleyActorCriticLoss", "ensemble_optimizer", "train_ensemble"]
