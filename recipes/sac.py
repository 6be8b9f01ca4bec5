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
from collections.abc import Mapping
from typing import ClassVar

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModule, TensorDictSequential
from torch import nn
from torchrl.data import TensorDictReplayBuffer
from torchrl.objectives import DiscreteSACLoss, SACLoss, SoftUpdate, ValueEstimators

from mapets_rl.experiment import Experiment, check
from mapets_rl.experiment.training import OffPolicyConfig
from mapets_rl.modules import (
    ACTION,
    ACTION_VALUE,
    LOSS_KEYS,
    MASK,
    OBS,
    OBS_NORM,
    Q_VALUE,
    TRANSITION_KEYS,
    AgentGroupSpec,
    make_decentralised_mlp,
    make_obs_norm,
    make_q_critic,
    make_stochastic_policy,
    sync_target_statistics,
)
from mapets_rl.modules.storage import FilledTensorStorage


@dataclasses.dataclass
class SACConfig(OffPolicyConfig):
    """SAC hyper-parameters; the shared off-policy fields (``gamma``, ``tau``, ``lr_actor``,
    ``lr_critic``, ``num_cells`` (actor and critics), ``share_params`` (actor and critics),
    ``buffer_size``, ``batch_size``, ``updates_per_batch``, ``init_random_frames``,
    ``max_grad_norm``) are those of :class:`~mapets_rl.experiment.training.OffPolicyConfig`.

    Attributes:
        lr_actor, lr_critic, lr_alpha: Adam learning rates of the actor, the twin critics and
            the entropy temperature (> 0; one optimiser with a parameter group each).
        init_random_frames: first frames of the run with uniformly random actions (>= 0).
        alpha_init: initial entropy temperature (> 0).
        normalize_obs: standardise observations with running statistics of collected data.
    """

    # run directories written when one ``lr`` drove actor, critics and temperature
    renamed_fields: ClassVar[Mapping[str, tuple[str, ...]]] = {
        "lr": ("lr_actor", "lr_critic", "lr_alpha"),
    }

    gamma: float = 0.99
    tau: float = 0.005
    lr_actor: float = 3e-4
    lr_critic: float = 3e-4
    lr_alpha: float = 3e-4
    alpha_init: float = 1.0
    normalize_obs: bool = True

    def __post_init__(self) -> None:
        super().__post_init__()
        for name in ("lr_alpha", "alpha_init"):
            check(getattr(self, name) > 0, name, "> 0", getattr(self, name))


class SAC(Experiment):
    """Independent (per-agent) SAC on any scenario (continuous or one-hot actions)."""

    name = "sac"
    Config = SACConfig

    def __init__(self, config: SACConfig, run_dir=None) -> None:
        super().__init__(config, run_dir)  # seeds, run dir, self.env
        spec = AgentGroupSpec.from_env(self.env)
        cells = config.num_cells

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
                    make_decentralised_mlp(spec, cells, config.share_params),
                    in_keys=[obs_key],
                    out_keys=[ACTION_VALUE],
                ),
            )
        else:
            self.qvalue = make_q_critic(
                spec,
                cells,
                centralized=False,
                share_params=config.share_params,
                obs_norm=norm_module,
            )

        # collector
        self.collector = self.make_collector(
            self.actor, init_random_frames=config.init_random_frames
        )
        self.eval_policy = self.actor

        # buffer
        self.buffer = TensorDictReplayBuffer(
            storage=FilledTensorStorage(config.buffer_size, device=self.device),
            batch_size=config.batch_size,
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
        # one optimiser, one parameter group per learning rate (actor, critics, temperature)
        lrs = {"actor": config.lr_actor, "qvalue": config.lr_critic, "alpha": config.lr_alpha}
        groups: dict[str, list[nn.Parameter]] = {key: [] for key in lrs}
        for name, param in self.loss.named_parameters():
            key = name.split("_network_params")[0] if "_network_params" in name else "alpha"
            groups[key].append(param)
        self.optim = torch.optim.Adam(
            [{"params": groups[key], "lr": lr} for key, lr in lrs.items() if groups[key]]
        )

    def train_step(self, batch: TensorDictBase) -> dict[str, float]:
        """Store the batch ``[*, T]`` (``[T]``, or ``[B, T]`` from ``B`` roads); the gradient
        steps due (:meth:`OffPolicyConfig.gradient_steps`), each a SAC step and a soft target
        update."""
        self.buffer.extend(batch.reshape(-1).select(*TRANSITION_KEYS))
        if self.obs_norm is not None:
            self.obs_norm.update(batch.get(OBS), batch.get(MASK, None))
            sync_target_statistics(self.loss, self.obs_norm)
        n = self.config.gradient_steps(self.frames - batch.numel(), self.frames)
        if len(self.buffer) < self.config.batch_size or n == 0:
            return {}
        keys = ("loss_actor", "loss_qvalue", "loss_alpha")
        logs = dict.fromkeys(keys, 0.0)
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

    def load_state_dict(self, state) -> None:
        """Also loads checkpoints written when the optimiser had one parameter group (one
        ``lr``): its state is split into the actor / critic / temperature groups."""
        optim = state.get("components", {}).get("optim")
        if optim is not None and len(optim["param_groups"]) == 1 < len(self.optim.param_groups):
            old = {id(p): i for i, p in enumerate(self.loss.parameters())}
            # the groups (and their lrs) of this config; the moments of the saved single group
            groups = [dict(group) for group in self.optim.state_dict()["param_groups"]]
            new_state, index = {}, 0
            for group, live in zip(groups, self.optim.param_groups, strict=True):
                group["params"] = []
                for param in live["params"]:
                    saved = optim["param_groups"][0]["params"][old[id(param)]]
                    if saved in optim["state"]:
                        new_state[index] = optim["state"][saved]
                    group["params"].append(index)
                    index += 1
            state = {
                **state,
                "components": {
                    **state["components"],
                    "optim": {"state": new_state, "param_groups": groups},
                },
            }
        super().load_state_dict(state)
