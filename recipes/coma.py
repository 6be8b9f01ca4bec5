"""COMA (Foerster et al. 2018), the comparator of Han et al.'s Table I, on the freeway.

config -> env -> modules (decentralised categorical policy o_a -> pi^a; centralised
counterfactual critic Q(s, u^{-a}, a, .)) -> collector (on-policy: the policy samples) ->
buffer (the last batch, minibatches without replacement) -> loss
(:class:`~mapets_rl.objectives.COMALoss`: TD(lambda) critic on the team reward, counterfactual
advantage for the actors) -> loop (shared ``Experiment.train``).

Discrete actions only: COMA's baseline sums over an agent's actions, so the recipe runs on the
freeway (one-hot KL/CL/CR/ES); the figure-eight's continuous accelerations are refused.

Usage::

    from mapets_rl.recipes.coma import COMA, COMAConfig
    COMA(COMAConfig(total_frames=4000, seed=1)).train()

or ``mapets-rl train coma env_config.cav_ratio=0.5``.
"""

from __future__ import annotations

import dataclasses
from typing import Any, ClassVar

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModule
from torch import nn
from torchrl.objectives import SoftUpdate

from mapets_rl.experiment import Experiment, SystemRewardMetrics, check
from mapets_rl.experiment.training import OnPolicyConfig, check_layer_sizes
from mapets_rl.modules import ACTION, ACTION_VALUE, OBS, AgentGroupSpec, make_stochastic_policy
from mapets_rl.objectives import COMACritic, COMALoss

TARGET = ("agents", "coma_target")


def _default_env_config() -> dict[str, Any]:
    # the same CPU scale as shapley_ac (8 vehicles of which 4 CAVs), so the two compare
    return {"n_vehicles": 8, "cav_ratio": 0.5}


@dataclasses.dataclass
class COMAConfig(OnPolicyConfig):
    """COMA hyper-parameters; the shared on-policy fields (``lr`` (actor), ``gamma``,
    ``lmbda`` (the critic's TD(lambda)), ``epochs``, ``minibatch_size``, ``max_grad_norm``,
    ``num_cells`` (actor), ``share_params`` (actor)) are those of
    :class:`~mapets_rl.experiment.training.OnPolicyConfig`.

    Attributes:
        lr_critic: Adam learning rate of the critic (> 0).
        critic_cells: hidden sizes of the centralised critic.
        entropy_coeff: entropy bonus weight (>= 0).
        reward_scale: multiplies the team reward in the critic target (> 0; the freeway's
            per-step team reward is in the tens at 4 CAVs).
        tau: soft target-critic update rate per gradient step, in (0, 1].
    """

    default_frames_per_batch: ClassVar[int] = 40  # one road's batch, see ExperimentConfig

    env: str = "freeway"
    env_config: dict[str, Any] = dataclasses.field(default_factory=_default_env_config)
    total_frames: int = 4000
    eval_interval: int = 400
    eval_episodes: int = 2
    minibatch_size: int = 40
    epochs: int = 1
    lmbda: float = 0.8
    lr: float = 5e-4
    lr_critic: float = 1e-3
    critic_cells: list[int] = dataclasses.field(default_factory=lambda: [128, 128])
    entropy_coeff: float = 0.01
    reward_scale: float = 0.1
    tau: float = 0.05

    def __post_init__(self) -> None:
        super().__post_init__()
        check(self.lr_critic > 0, "lr_critic", "> 0", self.lr_critic)
        check_layer_sizes("critic_cells", self.critic_cells, self.device)
        check(self.entropy_coeff >= 0, "entropy_coeff", ">= 0", self.entropy_coeff)
        check(self.reward_scale > 0, "reward_scale", "> 0", self.reward_scale)
        check(0 < self.tau <= 1, "tau", "in (0, 1]", self.tau)


class COMA(SystemRewardMetrics, Experiment):
    """Counterfactual multi-agent policy gradients with a centralised critic (discrete)."""

    name = "coma"
    Config = COMAConfig
    action_kinds = ("discrete",)
    action_kinds_reason = "its counterfactual baseline sums over an agent's one-hot actions"

    def __init__(self, config: COMAConfig, run_dir: Any = None) -> None:
        super().__init__(config, run_dir)
        spec = AgentGroupSpec.from_env(self.env)

        # modules: decentralised policy o_a -> pi^a (one-hot sample, logits kept);
        # counterfactual critic Q(s, u^{-a}, a, .)
        self.policy = make_stochastic_policy(
            spec, config.num_cells, config.share_params, return_log_prob=False
        )
        self.critic = TensorDictModule(
            COMACritic(
                spec.n_agents,
                spec.obs_dim,
                spec.action_dim,
                num_cells=config.critic_cells,
                activation_class=nn.ReLU,
                device=self.device,
            ),
            in_keys=[OBS, ACTION],
            out_keys=[ACTION_VALUE],
        )

        # collector (on-policy: the categorical policy explores; evaluation takes its mode)
        self.collector = self.make_collector(self.policy)
        self.eval_policy = self.policy

        # buffer: the latest batch, minibatches without replacement
        self.buffer = config.latest_batch_buffer(self.device)

        # loss + soft target-critic updates
        self.loss = COMALoss(
            self.policy,
            self.critic,
            gamma=config.gamma,
            lmbda=config.lmbda,
            entropy_coeff=config.entropy_coeff,
            reward_scale=config.reward_scale,
        ).to(self.device)
        self.updater = SoftUpdate(self.loss, tau=config.tau)
        self.actor_optim = torch.optim.Adam(
            self.loss.actor_network_params.values(True, True), lr=config.lr
        )
        self.critic_optim = torch.optim.Adam(
            self.loss.critic_network_params.values(True, True), lr=config.lr_critic
        )

    def train_step(self, batch: TensorDictBase) -> dict[str, float]:
        """TD(lambda) targets on the trajectory batch [*, T] (each road of [B, T] its own
        sequence), then ``epochs`` passes of minibatch actor and critic steps (the actor loss
        sees a detached critic: one backward)."""
        cfg = self.config
        batch = self.loss.value_targets(batch)
        steps = cfg.load_latest_batch(self.buffer, batch)
        keys = ("loss_actor", "loss_value", "loss_entropy", "advantage", "pred_value")
        logs = dict.fromkeys(keys, 0.0)
        for _ in range(steps):
            out = self.loss(self.buffer.sample())
            self.actor_optim.zero_grad()
            self.critic_optim.zero_grad()
            (out["loss_actor"] + out["loss_entropy"] + out["loss_value"]).backward()
            for optim in (self.actor_optim, self.critic_optim):
                params = [p for g in optim.param_groups for p in g["params"]]
                nn.utils.clip_grad_norm_(params, cfg.max_grad_norm)
                optim.step()
            self.updater.step()
            for key in keys:
                logs[key] += out[key].item() / steps
        return logs

    def stateful_components(self) -> dict[str, Any]:
        return {
            "loss": self.loss,
            "actor_optim": self.actor_optim,
            "critic_optim": self.critic_optim,
            "buffer": self.buffer,
        }
