"""Losses (torchrl LossModules)."""

from mapets_rl.objectives.coma import COMACritic, COMALoss, counterfactual_advantage
from mapets_rl.objectives.ensemble_nll import EnsembleNLLLoss, train_ensemble
from mapets_rl.objectives.shapley_actor_critic import ShapleyActorCriticLoss

__all__ = [
    "COMACritic",
    "COMALoss",
    "EnsembleNLLLoss",
    "ShapleyActorCriticLoss",
    "counterfactual_advantage",
    "train_ensemble",
]
