"""MAPPO (Yu et al. 2022) and IPPO (de Witt et al. 2020) baselines.

config -> env -> modules (per-agent policy, centralised or per-agent value) -> collector ->
buffer (the last batch, sampled without replacement in minibatches) -> loss (torchrl
``MAPPOLoss`` / ``IPPOLoss`` with ``MultiAgentGAE``) -> loop (shared ``Experiment.train``).

Continuous actions (figure-eight) use a TanhNormal head bounded by the action spec; discrete
actions (freeway, one-hot KL/CL/CR/ES) use a one-hot categorical head.
"""

from __future__ import annotations

import dataclasses

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModule, TensorDictSequential
from torch import nn
from torchrl.objectives import ValueEstimators
from torchrl.objectives.multiagent import IPPOLoss, MAPPOLoss

from mapets_rl.experiment import Experiment, check
from mapets_rl.experiment.training import OnPolicyConfig
from mapets_rl.modules import (
    ACTION,
    LOG_PROB,
    LOSS_KEYS,
    MASK,
    OBS,
    OBS_NORM,
    VALUE,
    AgentGroupSpec,
    make_obs_norm,
    make_stochastic_policy,
    make_value_mlp,
)


@dataclasses.dataclass
class MAPPOConfig(OnPolicyConfig):
    """MAPPO / IPPO hyper-parameters; the shared on-policy fields (``lr``, ``gamma``,
    ``lmbda``, ``epochs``, ``minibatch_size``, ``max_grad_norm``, ``num_cells`` (policy and
    value), ``share_params`` (the policy)) are those of
    :class:`~mapets_rl.experiment.training.OnPolicyConfig`.

    Attributes:
        clip_epsilon: PPO ratio clip (> 0).
        entropy_coeff: entropy bonus weight (>= 0).
        critic_coeff: value-loss weight (> 0).
        normalize_obs: standardise observations with running statistics of collected data.
        ippo: decentralised per-agent values (IPPO) instead of the centralised value (MAPPO).
    """

    clip_epsilon: float = 0.2
    entropy_coeff: float = 0.01
    critic_coeff: float = 1.0
    normalize_obs: bool = True
    ippo: bool = False

    def __post_init__(self) -> None:
        super().__post_init__()
        check(self.clip_epsilon > 0, "clip_epsilon", "> 0", self.clip_epsilon)
        check(self.entropy_coeff >= 0, "entropy_coeff", ">= 0", self.entropy_coeff)
        check(self.critic_coeff > 0, "critic_coeff", "> 0", self.critic_coeff)


class MAPPO(Experiment):
    """MAPPO (centralised value) or IPPO (``ippo=True``) on any scenario."""

    name = "mappo"
    Config = MAPPOConfig

    def __init__(self, config: MAPPOConfig, run_dir=None) -> None:
        super().__init__(config, run_dir)  # seeds, run dir, self.env
        spec = AgentGroupSpec.from_env(self.env)

        # modules: (observation normaliser ->) decentralised policy; value V(o_1..o_I) per
        # agent (MAPPO) or V(o_i) (IPPO)
        self.obs_norm, norm_module = make_obs_norm(spec) if config.normalize_obs else (None, None)
        self.policy = make_stochastic_policy(
            spec, config.num_cells, config.share_params, obs_norm=norm_module
        )
        value_mlp = make_value_mlp(
            spec,
            config.num_cells,
            centralized=not config.ippo,
            share_params=True,
            activation=nn.Tanh,
        )
        self.critic = TensorDictModule(
            value_mlp, in_keys=[OBS if norm_module is None else OBS_NORM], out_keys=[VALUE]
        )
        if norm_module is not None:
            self.critic = TensorDictSequential(norm_module, self.critic)

        # collector (on-policy: the stochastic policy explores; evaluation takes its mode)
        self.collector = self.make_collector(self.policy)
        self.eval_policy = self.policy

        # buffer: the latest batch, minibatches without replacement
        self.buffer = config.latest_batch_buffer(self.device)

        # loss: clipped surrogate + value + entropy, advantages by MultiAgentGAE
        loss_cls = IPPOLoss if config.ippo else MAPPOLoss
        self.loss = loss_cls(
            self.policy,
            self.critic,
            clip_epsilon=config.clip_epsilon,
            entropy_coeff=config.entropy_coeff,
            critic_coeff=config.critic_coeff,
        )
        self.loss.set_keys(**LOSS_KEYS, action=ACTION, value=VALUE, sample_log_prob=LOG_PROB)
        self.loss.make_value_estimator(
            ValueEstimators.MAGAE, gamma=config.gamma, lmbda=config.lmbda
        )
        self.optim = torch.optim.Adam(self.loss.parameters(), lr=config.lr)

    def train_step(self, batch: TensorDictBase) -> dict[str, float]:
        """GAE along time on the batch [*, T] (each road of [B, T] its own sequence), then
        ``epochs`` passes of minibatch PPO updates."""
        with torch.no_grad():
            self.loss.value_estimator(
                batch,
                params=self.loss.critic_network_params,
                target_params=self.loss.target_critic_network_params,
            )
        logs: dict[str, float] = {}
        steps = self.config.load_latest_batch(self.buffer, batch)
        for _ in range(steps):
            out = self.loss(self.buffer.sample())
            total = out["loss_objective"] + out["loss_critic"] + out["loss_entropy"]
            self.optim.zero_grad()
            total.backward()
            nn.utils.clip_grad_norm_(self.loss.parameters(), self.config.max_grad_norm)
            self.optim.step()
            for key in ("loss_objective", "loss_critic", "loss_entropy"):
                logs[key] = logs.get(key, 0.0) + out[key].item() / steps
        if self.obs_norm is not None:  # new statistics apply from the next batch on
            self.obs_norm.update(batch.get(OBS), batch.get(MASK, None))
        return logs

    def stateful_components(self) -> dict:
        return {"loss": self.loss, "optim": self.optim, "buffer": self.buffer}
