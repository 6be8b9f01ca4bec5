"""M3DDPG baseline (Li et al. 2019): MADDPG whose critic target and actor objective read each
agent's critic at a one-gradient-step worst case of the other agents' actions
(:class:`~mapets_rl.objectives.M3DDPGLoss`, whose docstring gives the equations).

Everything else is :mod:`recipes.maddpg`'s: modules (deterministic actors, tanh-bounded or,
on the freeway's discrete actions, a Gumbel-softmax head whose one-hot actions the
perturbation moves like any action vector), collector, replay buffer, n-step targets, soft
target updates, checkpointed state.
"""

from __future__ import annotations

import dataclasses

from mapets_rl.experiment import check
from mapets_rl.modules import ACTION, Q_VALUE
from mapets_rl.objectives.m3ddpg import M3DDPGLoss
from recipes.maddpg import MADDPG, MADDPGConfig


@dataclasses.dataclass
class M3DDPGConfig(MADDPGConfig):
    """MADDPG's hyper-parameters (:class:`~recipes.maddpg.MADDPGConfig`) and the sizes of the
    adversarial steps, in the units of the actions (one-hot vectors on discrete scenarios).

    Attributes:
        epsilon_critic: step (finite, >= 0) that perturbs the other agents' target actions in
            the critic's target; 0 gives MADDPG's target.
        epsilon_actor: step (finite, >= 0) that perturbs the other agents' actions in the
            actor's objective; 0 gives MADDPG's actor loss.

    The defaults are those of the authors' code for cooperating agents (``--adv-eps 1e-3`` in
    the critic target; ``--adv-eps-s 1e-5`` for teammates in the actor).
    """

    epsilon_critic: float = 1e-3
    epsilon_actor: float = 1e-5

    def __post_init__(self) -> None:
        super().__post_init__()  # rejects non-finite numbers
        check(
            self.epsilon_critic >= 0, "epsilon_critic", "a finite number >= 0", self.epsilon_critic
        )
        check(self.epsilon_actor >= 0, "epsilon_actor", "a finite number >= 0", self.epsilon_actor)


class M3DDPG(MADDPG):
    """M3DDPG with a centralised critic on any scenario (continuous or one-hot actions)."""

    name = "m3ddpg"
    Config = M3DDPGConfig

    def make_loss(self, config: M3DDPGConfig) -> M3DDPGLoss:  # type: ignore[override]
        """MADDPG's loss with the minimax target and actor objective."""
        return super().make_loss(
            config,
            M3DDPGLoss,
            action_key=ACTION,
            value_key=Q_VALUE,
            epsilon_critic=config.epsilon_critic,
            epsilon_actor=config.epsilon_actor,
        )
