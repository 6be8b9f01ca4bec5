"""Losses (torchrl LossModules) and the replay-data transforms they rely on."""

from mapets_rl.objectives.coma import COMACritic, COMALoss, counterfactual_advantage
from mapets_rl.objectives.ddpg import PreactivationRegularisedDDPGLoss
from mapets_rl.objectives.ensemble_nll import (
    EnsembleFit,
    EnsembleNLLLoss,
    ensemble_optimizer,
    fit_ensemble,
    holdout_split,
    read_transitions,
    train_ensemble,
)
from mapets_rl.objectives.m3ddpg import M3DDPGLoss, MinimaxCritic, minimax_action_perturbation
from mapets_rl.objectives.n_step import STEPS_TO_NEXT_OBS, n_step_transitions
from mapets_rl.objectives.shapley_actor_critic import ShapleyActorCriticLoss

__all__ = [
    "STEPS_TO_NEXT_OBS",
    "COMACritic",
    "COMALoss",
    "EnsembleFit",
    "EnsembleNLLLoss",
    "M3DDPGLoss",
    "MinimaxCritic",
    "PreactivationRegularisedDDPGLoss",
    "ShapleyActorCriticLoss",
    "counterfactual_advantage",
    "ensemble_optimizer",
    "fit_ensemble",
    "holdout_split",
    "minimax_action_perturbation",
    "n_step_transitions",
    "read_transitions",
    "train_ensemble",
]
