"""Per-agent SAC baseline (Haarnoja et al. 2018; discrete: Christodoulou 2019).

config -> env -> modules (per-agent stochastic actor; twin per-agent Q critics, decentralised)
-> collector (the stochastic actor explores) -> replay buffer -> loss (torchrl ``SACLoss`` for
continuous actions, ``DiscreteSACLoss`` for one-hot actions; learned temperature; target
critics by ``SoftUpdate``) -> loop (shared ``Experiment.train``).

``share_params`` switches between one actor/critic shared by all agents (parameter sharing,
agents still act on their own observation) and separate parameters per agent.
"""

from __future__ import annotations

import dataclasses

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModule, TensorDictSequential
from torch import nn
from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer
from torchrl.modules import MultiAgentMLP
from torchrl.objectives import DiscreteSACLoss, SACLoss, SoftUpdate, ValueEstimators

from mapets_rl.experiment import Experiment, ExperimentConfig, check
from mapets_rl.modules import (
    ACTION,
    ACTION_VALUE,
    LOSS_KEYS,
    MASK,
    OBS,
    OBS_ACTION,
    OBS_NORM,
    Q_VALUE,
    AgentGroupSpec,
    concat_last,
    make_obs_norm,
    make_stochastic_policy,
)


@dataclasses.dataclass
class SACConfig(ExperimentConfig):
    """SAC hyper-parameters (plus the shared :class:`ExperimentConfig` fields).

    Attributes:
        lr: Adam learning rate of actor, critics and temperature (> 0).
        gamma: discount in [0, 1].
        tau: soft target update rate in (0, 1].
        alpha_init: initial entropy temperature (> 0).
        buffer_size: replay capacity in transitions (>= batch_size).
        batch_size: transitions per gradient step (>= 1).
        updates_per_batch: gradient steps per collected batch (>= 1).
        init_random_frames: first frames of the run with uniformly random actions (>= 0).
        num_cells: hidden layer sizes of actor and critic MLPs.
        share_params: one actor and one critic shared by all agents (else per agent).
        normalize_obs: standardise observations with running statistics of collected data.
        max_grad_norm: gradient-norm clip (> 0).
    """

    lr: float = 3e-4
    gamma: float = 0.99
    tau: float = 0.005
    alpha_init: float = 1.0
    buffer_size: int = 100_000
    batch_size: int = 256
    updates_per_batch: int = 20
    init_random_frames: int = 200
    num_cells: list[int] = dataclasses.field(default_factory=lambda: [64, 64])
    share_params: bool = True
    normalize_obs: bool = True
    max_grad_norm: float = 1.0

    def __post_init__(self) -> None:
        super().__post_init__()
        for name in ("lr", "alpha_init", "max_grad_norm"):
            check(getattr(self, name) > 0, name, "> 0", getattr(self, name))
        check(0 <= self.gamma <= 1, "gamma", "in [0, 1]", self.gamma)
        check(0 < self.tau <= 1, "tau", "in (0, 1]", self.tau)
        check(self.batch_size >= 1, "batch_size", ">= 1", self.batch_size)
        check(
            self.buffer_size >= self.batch_size,
            "buffer_size",
            f">= batch_size={self.batch_size}",
            self.buffer_size,
        )
        check(self.updates_per_batch >= 1, "updates_per_batch", ">= 1", self.updates_per_batch)
        check(self.init_random_frames >= 0, "init_random_frames", ">= 0", self.init_random_frames)
        check(
            len(self.num_cells) >= 1 and min(self.num_cells) >= 1,
            "num_cells",
            "a non-empty list of positive layer sizes",
            self.num_cells,
        )


class SAC(Experiment):
    """Independent (per-agent) SAC on any scenario (continuous or one-hot actions)."""

    name = "sac"
    Config = SACConfig

    def __init__(self, config: SACConfig, run_dir=None) -> None:
        super().__init__(config, run_dir)  # seeds, run dir, self.env
        spec = AgentGroupSpec.from_env(self.env)
        depth, cells = len(config.num_cells), config.num_cells

        # modules: (observation normaliser ->) stochastic actor pi(a_i | o_i); per-agent
        # critics Q(o_i, a_i) (continuous) or Q(o_i, .) over the discrete actions
        self.obs_norm, norm_module = make_obs_norm(spec) if config.normalize_obs else (None, None)
        obs_key = OBS if norm_module is None else OBS_NORM
        front = [] if norm_module is None else [norm_module]
        self.actor = make_stochastic_policy(
            spec, cells, config.share_params, return_log_prob=False, obs_norm=norm_module
        )
        if spec.discrete:
            self.qvalue = TensorDictSequential(
                *front,
                TensorDictModule(
                    MultiAgentMLP(
                        n_agent_inputs=spec.obs_dim,
                        n_agent_outputs=spec.action_dim,
                        n_agents=spec.n_agents,
                        centralized=False,
                        share_params=config.share_params,
                        depth=depth,
                        num_cells=cells,
                        activation_class=nn.ReLU,
                    ),
                    in_keys=[obs_key],
                    out_keys=[ACTION_VALUE],
                ),
            )
        else:
            self.qvalue = TensorDictSequential(
                *front,
                TensorDictModule(concat_last, in_keys=[obs_key, ACTION], out_keys=[OBS_ACTION]),
                TensorDictModule(
                    MultiAgentMLP(
                        n_agent_inputs=spec.obs_dim + spec.action_dim,
                        n_agent_outputs=1,
                        n_agents=spec.n_agents,
                        centralized=False,
                        share_params=config.share_params,
                        depth=depth,
                        num_cells=cells,
                        activation_class=nn.ReLU,
                    ),
                    in_keys=[OBS_ACTION],
                    out_keys=[Q_VALUE],
                ),
            )

        # collector
        self.collector = self.make_collector(
            self.actor, init_random_frames=config.init_random_frames
        )
        self.eval_policy = self.actor

        # buffer
        self.buffer = TensorDictReplayBuffer(
            storage=LazyTensorStorage(config.buffer_size), batch_size=config.batch_size
        )

        # loss: twin-Q soft Bellman targets, learned temperature (target entropy per agent)
        if spec.discrete:
            self.loss = DiscreteSACLoss(
                self.actor,
                self.qvalue,
                action_space="one-hot",
                num_actions=spec.action_dim,
                num_qvalue_nets=2,
                alpha_init=config.alpha_init,
                loss_function="l2",
            )
            self.loss.set_keys(**LOSS_KEYS, action=ACTION, action_value=ACTION_VALUE)
        else:
            self.loss = SACLoss(
                self.actor,
                self.qvalue,
                num_qvalue_nets=2,
                alpha_init=config.alpha_init,
                loss_function="l2",
                target_entropy=-float(spec.action_dim),
            )
            self.loss.set_keys(**LOSS_KEYS, action=ACTION, state_action_value=Q_VALUE)
        self.loss.make_value_estimator(ValueEstimators.TD0, gamma=config.gamma)
        self.target_updater = SoftUpdate(self.loss, tau=config.tau)
        self.optim = torch.optim.Adam(self.loss.parameters(), lr=config.lr)

    def train_step(self, batch: TensorDictBase) -> dict[str, float]:
        """Store the batch; ``updates_per_batch`` SAC steps; soft target update."""
        self.buffer.extend(batch.reshape(-1))
        if self.obs_norm is not None:
            self.obs_norm.update(batch.get(OBS), batch.get(MASK, None))
        if len(self.buffer) < self.config.batch_size:
            return {}
        keys = ("loss_actor", "loss_qvalue", "loss_alpha")
        logs = dict.fromkeys(keys, 0.0)
        n = self.config.updates_per_batch
        for _ in range(n):
            out = self.loss(self.buffer.sample())
            self.optim.zero_grad()
            sum(out[k] for k in keys).backward()
            nn.utils.clip_grad_norm_(self.loss.parameters(), self.config.max_grad_norm)
            self.optim.step()
            self.target_updater.step()
            for k in keys:
                logs[k] += out[k].item() / n
        logs["alpha"] = out["alpha"].item()
        return logs

    def stateful_components(self) -> dict:
        return {"loss": self.loss, "optim": self.optim, "buffer": self.buffer}
