"""Losses (torchrl LossModules)."""

from mapets_rl.objectives.ensemble_nll import EnsembleNLLLoss
from mapets_rl.objectives.shapley_actor_critic import ShapleyActorCriticLoss

__all__ = ["EnsembleNLLLoss", "ShapleyActorCriticLoss"]
