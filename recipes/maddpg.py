"""MADDPG baseline (Lowe et al. 2017): deterministic per-agent actors, a centralised critic.

config -> env -> modules (actors o_i -> a_i; critic Q_i(o_1..o_I, a_1..a_I) as a centralised
``MultiAgentMLP``) -> collector (annealed Gaussian exploration) -> replay buffer -> loss
(torchrl ``DDPGLoss``, TD(0) targets, target networks by ``SoftUpdate``) -> loop (shared
``Experiment.train``).

Discrete actions (freeway): the actor outputs logits and a Gumbel-softmax head
(:class:`~mapets_rl.modules.GumbelSoftmaxHead`) turns them into one-hot actions
that carry gradients — the greedy one-hot with the straight-through softmax gradient in the
actor update and evaluation. This is the discrete variant of the MADDPG paper (Gumbel-softmax),
chosen because it keeps the deterministic policy gradient through the centralised critic
unchanged. While collecting, ``exploration="gumbel"`` (default) draws a hard Gumbel sample at
temperature ``gumbel_tau`` (this is the exploration; the Gaussian noise applies to continuous
actions only); ``exploration="epsilon"`` plays the greedy action and replaces it, for each
agent with a probability annealed from ``epsilon_init`` to ``epsilon_end``, by a uniform draw
among ``exploration_actions`` (torchrl's ``EGreedyModule`` on the masked action spec; e.g.
``[0, 1, 2]`` on the freeways: lane changes but no random emergency stop).

M3DDPG (Li et al. 2019, the ``m3ddpg`` recipe, :class:`M3DDPG` below) is MADDPG whose critic
target and actor objective read each agent's critic at a one-gradient-step worst case of the
other agents' actions (:class:`~mapets_rl.objectives.M3DDPGLoss`, whose docstring gives the
equations); everything else is MADDPG's.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from typing import Any

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModule, TensorDictSequential
from torch import nn
from torchrl.data import TensorDictReplayBuffer
from torchrl.modules import AdditiveGaussianModule, TanhModule
from torchrl.objectives import SoftUpdate, ValueEstimators

from mapets_rl.experiment import Experiment, check
from mapets_rl.experiment.training import DiscreteExplorationConfig
from mapets_rl.modules import (
    ACTION,
    GROUP,
    LOSS_KEYS,
    MASK,
    OBS,
    OBS_NORM,
    Q_VALUE,
    TRANSITION_KEYS,
    AgentGroupSpec,
    GumbelSoftmaxHead,
    make_decentralised_mlp,
    make_discrete_actor,
    make_obs_norm,
    make_q_critic,
    sync_target_statistics,
)
from mapets_rl.modules.advantage_critic import make_advantage_q_critic
from mapets_rl.modules.storage import FilledTensorStorage
from mapets_rl.objectives.ddpg import PreactivationRegularisedDDPGLoss
from mapets_rl.objectives.m3ddpg import M3DDPGLoss
from mapets_rl.objectives.n_step import STEPS_TO_NEXT_OBS, n_step_transitions

PREACTIVATION = (GROUP, "param")
"""The actor's pre-activation [*, I, act]: the tanh input (continuous) or the logits (one-hot)."""

REPLAY_KEYS = (*TRANSITION_KEYS, STEPS_TO_NEXT_OBS)
"""What the replay buffer keeps of a collected step: the loss's inputs (the n-step count only
with ``n_steps > 1``)."""

OPENAI_MADDPG: tuple[str, ...] = (
    "update_interval=100",
    "updates_per_batch=1",
    "batch_size=1024",
    "lr_actor=0.01",
    "lr_critic=0.01",
    "gamma=0.95",
    "tau=0.01",
    "num_cells=[64, 64]",
    "max_grad_norm=0.5",
)
"""The update schedule of openai/maddpg (``experiments/train.py`` and
``maddpg/trainer/maddpg.py`` defaults), as config overrides of ``maddpg`` / ``m3ddpg``: one
gradient step per 100 frames with minibatches of 1,024 transitions, Adam at 1e-2 for actor and
critic, gamma 0.95, soft target updates at 0.01 (their polyak 0.99), two hidden layers of 64
units, gradient norms clipped at 0.5 (their actor's ``mean(p^2)`` penalty at 1e-3 is
``actor_preactivation_coef``'s default).

This is an inference, not a setting the Shapley paper (Han et al.) states: the paper gives no
update schedule, and its software versions match openai/maddpg's release, whose defaults these
are. What differs from openai/maddpg: one shared actor and one centralised critic take one step
for all agents (openai/maddpg steps each agent's own actor and critic in turn), updates start
once the buffer holds ``batch_size`` transitions (theirs wait for 25,600: ``batch_size`` times
their 25-step episodes) after ``init_random_frames`` of uniform random actions (torchrl rounds
them up to whole collected batches), and the replay keeps ``buffer_size`` (default 100,000)
transitions, not 10^6 (6.4 kB each at 30 CAVs: a 100,000-transition buffer is a 640 MB
checkpoint).

Python: ``MADDPGConfig(...).with_overrides(OPENAI_MADDPG)``; command line, on 256 roads of the
batched freeway (give runs of millions of frames ``eval_interval`` and ``checkpoint_interval``
of their own: the defaults, 1,000 frames, evaluate and checkpoint after every batch)::

    mapets-rl train maddpg --env freeway-merge \
        "env_config={backend: torch, num_envs: 256, n_vehicles: 30, cav_ratio: 1.0}" \
        frames_per_batch=1024 total_frames=4000000 eval_interval=100000 \
        checkpoint_interval=500000 update_interval=100 updates_per_batch=1 batch_size=1024 \
        lr_actor=0.01 lr_critic=0.01 gamma=0.95 tau=0.01 "num_cells=[64, 64]" \
        max_grad_norm=0.5
"""


@dataclasses.dataclass
class MADDPGConfig(DiscreteExplorationConfig):
    """MADDPG hyper-parameters; the shared off-policy fields (``gamma``, ``tau``, ``lr_actor``,
    ``lr_critic``, ``num_cells`` (actor and critic), ``share_params`` (the actor),
    ``buffer_size``, ``batch_size``, ``updates_per_batch``, ``init_random_frames``,
    ``max_grad_norm``) are those of :class:`~mapets_rl.experiment.training.OffPolicyConfig`,
    the exploration of discrete actions (``exploration``, ``gumbel_tau``, ``epsilon_*``,
    ``exploration_actions``) that of
    :class:`~mapets_rl.experiment.training.DiscreteExplorationConfig`.

    Attributes:
        init_random_frames: first frames of the run with uniformly random actions (>= 0).
        sigma_init, sigma_end: Gaussian exploration std as a fraction of the half action
            range, annealed linearly over ``sigma_anneal_frames`` (continuous actions).
        sigma_anneal_frames: frames (>= 1) over which the exploration std goes from
            ``sigma_init`` to ``sigma_end``.
        normalize_obs: standardise observations with running statistics of collected data
            (the target networks always use the current statistics).
        actor_preactivation_coef: weight (>= 0) of the actor pre-activation penalty
            ``mean(p^2)`` of the MADDPG reference code, which keeps the actor out of tanh
            saturation (see :mod:`mapets_rl.objectives.ddpg`).
        n_steps: look-ahead (>= 1) of the per-agent n-step returns of the critic's targets
            (:func:`~mapets_rl.objectives.n_step_transitions`; 1 = TD(0)).
        critic_share_params: one centralised critic network for all agents. It reads the same
            joint input for every agent, so it gives every agent the same ``Q``: the mean of
            their returns, which is each agent's own return only under a team reward. False
            (default, openai/maddpg's): one critic per agent, ``Q_i`` fitted to agent ``i``'s
            own rewards.
        critic_view: what each agent's critic reads. ``"all"`` (default, MADDPG's centralised
            critic): every agent's observation and action, ``Q_i(o_1..o_I, a_1..a_I)``;
            ``"own"``: its own, ``Q_i(o_i, a_i)`` (independent DDPG critics: a CAV's own move is
            4 of its critic's 28 inputs instead of 4 of 810 with 30 CAVs, and the other CAVs'
            actions become noise in its targets).
        critic_head: ``"joint"`` (default): one network of the critic's inputs,
            ``Q_i(o, a)``; ``"advantage"`` (discrete actions): a value of the critic's view
            plus an advantage head of the agent's own observation and action anchored at action
            0 (Keep Lane on the freeways), ``Q_i = V_i(o) + A_i(o_i, a_i) - A_i(o_i, 0)``
            (:mod:`mapets_rl.modules.advantage_critic`): the agent's own move enters only
            through its advantage, apart from the state's value.
    """

    sigma_init: float = 0.3
    sigma_end: float = 0.05
    sigma_anneal_frames: int = 3000
    normalize_obs: bool = True
    actor_preactivation_coef: float = 1e-3
    n_steps: int = 1
    critic_share_params: bool = False
    critic_view: str = "all"
    critic_head: str = "joint"

    @classmethod
    def upgrade_dict(cls, data: Mapping[str, Any]) -> dict[str, Any]:
        """A config written before ``critic_share_params`` existed trained one shared critic:
        it resumes with ``critic_share_params=True``, not today's default; one written before
        ``critic_view`` existed had the centralised critic (``"all"``), one written before
        ``critic_head`` the joint one (``"joint"``)."""
        data = super().upgrade_dict(data)
        data.setdefault("critic_share_params", True)
        data.setdefault("critic_view", "all")
        data.setdefault("critic_head", "joint")
        return data

    def __post_init__(self) -> None:
        super().__post_init__()
        check(
            self.actor_preactivation_coef >= 0,
            "actor_preactivation_coef",
            ">= 0",
            self.actor_preactivation_coef,
        )
        check(self.n_steps >= 1, "n_steps", ">= 1", self.n_steps)
        check(self.critic_view in ("all", "own"), "critic_view", "'all' or 'own'", self.critic_view)
        check(
            self.critic_head in ("joint", "advantage"),
            "critic_head",
            "'joint' or 'advantage'",
            self.critic_head,
        )
        check(
            0 <= self.sigma_end <= self.sigma_init,
            "sigma_end",
            "in [0, sigma_init]",
            self.sigma_end,
        )
        check(
            self.sigma_anneal_frames >= 1, "sigma_anneal_frames", ">= 1", self.sigma_anneal_frames
        )


class MADDPG(Experiment):
    """MADDPG with a centralised critic on any scenario (continuous or one-hot actions)."""

    name = "maddpg"
    Config = MADDPGConfig

    def __init__(self, config: MADDPGConfig, run_dir=None) -> None:
        super().__init__(config, run_dir)  # seeds, run dir, self.env
        config.check_shield_penalty(self.env)
        spec = AgentGroupSpec.from_env(self.env)
        cells = config.num_cells

        # modules: (observation normaliser ->) actor o_i -> a_i (bounded by tanh, or one-hot
        # by Gumbel-softmax)
        self.obs_norm, norm_module = make_obs_norm(spec) if config.normalize_obs else (None, None)
        obs_key = OBS if norm_module is None else OBS_NORM
        front = [] if norm_module is None else [norm_module]
        if spec.discrete:
            epsilon = config.exploration == "epsilon"
            head = GumbelSoftmaxHead(config.gumbel_tau, return_logits=True, sample=not epsilon)
            self.actor = make_discrete_actor(
                spec,
                cells,
                config.share_params,
                head,
                logits_key=PREACTIVATION,
                obs_norm=norm_module,
                initial_logits=config.actor_initial_logits,
            )
            self.exploration = config.epsilon_greedy(self.env.full_action_spec_unbatched[ACTION])
            collection_policy = (
                TensorDictSequential(self.actor, self.exploration) if epsilon else self.actor
            )
        else:
            if config.actor_initial_logits:
                raise ValueError(
                    f"actor_initial_logits is for discrete actions; {config.env!r} has "
                    "continuous ones"
                )
            if config.exploration != "gumbel":
                raise ValueError(
                    f"exploration={config.exploration!r} is for discrete actions; "
                    f"{config.env!r} has continuous ones (their exploration is Gaussian noise)"
                )
            actor_mlp = make_decentralised_mlp(spec, cells, config.share_params)
            self.actor = TensorDictSequential(
                *front,
                TensorDictModule(actor_mlp, in_keys=[obs_key], out_keys=[PREACTIVATION]),
                TanhModule(in_keys=[PREACTIVATION], out_keys=[ACTION], spec=spec.action_spec),
            )
            self.exploration = AdditiveGaussianModule(
                spec=self.env.full_action_spec_unbatched,
                sigma_init=config.sigma_init,
                sigma_end=config.sigma_end,
                annealing_num_steps=config.sigma_anneal_frames,
                std=spec.action_half_range.tolist(),  # torchrl builds its buffer from a list
                action_key=ACTION,
            )
            collection_policy = TensorDictSequential(self.actor, self.exploration)
        # centralised critic Q_i(o_1..o_I, a_1..a_I) (or Q_i(o_i, a_i)), one output per agent
        critic_view = {
            "centralized": config.critic_view == "all",
            "share_params": config.critic_share_params,
            "obs_norm": norm_module,
        }
        if config.critic_head == "advantage":
            if not spec.discrete:
                raise ValueError(
                    f"critic_head='advantage' needs discrete actions; {config.env!r} has "
                    "continuous ones"
                )
            self.critic = make_advantage_q_critic(spec, cells, baseline_action=0, **critic_view)
        else:
            self.critic = make_q_critic(spec, cells, **critic_view)

        # collector
        self.collector = self.make_collector(
            collection_policy, init_random_frames=config.init_random_frames
        )
        self.eval_policy = self.actor

        # buffer
        self.buffer = TensorDictReplayBuffer(
            storage=FilledTensorStorage(config.buffer_size, device=self.device),
            batch_size=config.batch_size,
        )

        # loss: DDPG with per-agent TD(0) targets through target actor and critic
        self.loss = self.make_loss(config)
        self.loss.set_keys(**LOSS_KEYS, state_action_value=Q_VALUE)
        self.loss.make_value_estimator(ValueEstimators.TD0, gamma=config.gamma)
        self.loss.value_estimator.set_keys(steps_to_next_obs=STEPS_TO_NEXT_OBS)
        self.target_updater = SoftUpdate(self.loss, tau=config.tau)
        self.optim_actor = torch.optim.Adam(
            self.loss.actor_network_params.values(True, True), lr=config.lr_actor
        )
        self.optim_critic = torch.optim.Adam(
            self.loss.value_network_params.values(True, True), lr=config.lr_critic
        )

    def make_loss(
        self,
        config: MADDPGConfig,
        loss_class: type[PreactivationRegularisedDDPGLoss] = PreactivationRegularisedDDPGLoss,
        **kwargs,
    ) -> PreactivationRegularisedDDPGLoss:
        """The loss on ``self.actor`` and ``self.critic``, with target copies of both:
        ``loss_class`` (a :class:`PreactivationRegularisedDDPGLoss`) built with MADDPG's
        options and ``kwargs`` (M3DDPG passes its loss and epsilons)."""
        return loss_class(
            actor_network=self.actor,
            value_network=self.critic,
            preactivation_key=PREACTIVATION,
            preactivation_coef=config.actor_preactivation_coef,
            delay_actor=True,
            delay_value=True,
            loss_function="l2",
            **kwargs,
        )

    def train_step(self, batch: TensorDictBase) -> dict[str, float]:
        """Store the batch ``[*, T]`` (time last: ``[T]``, or ``[B, T]`` from ``B`` roads);
        the gradient steps due (:meth:`OffPolicyConfig.gradient_steps`), each a critic + actor
        step and a soft target update."""
        batch = self.config.stored_transitions(batch)
        if self.config.n_steps > 1:
            batch = n_step_transitions(batch, self.config.gamma, self.config.n_steps)
        self.buffer.extend(batch.reshape(-1).select(*REPLAY_KEYS, strict=False))
        if self.obs_norm is not None:
            self.obs_norm.update(batch.get(OBS), batch.get(MASK, None))
            sync_target_statistics(self.loss, self.obs_norm)
        if self.exploration is not None:
            self.exploration.step(batch.numel())
        n = self.config.gradient_steps(self.frames - batch.numel(), self.frames)
        if len(self.buffer) < self.config.batch_size or n == 0:
            return {}
        logs = {"loss_actor": 0.0, "loss_actor_reg": 0.0, "loss_value": 0.0}
        for _ in range(n):
            out = self.loss(self.buffer.sample())
            # the actor loss sees detached critic params, so one backward serves both
            self.optim_actor.zero_grad()
            self.optim_critic.zero_grad()
            self.loss.total(out).backward()
            for optim in (self.optim_actor, self.optim_critic):
                params = [p for g in optim.param_groups for p in g["params"]]
                nn.utils.clip_grad_norm_(params, self.config.max_grad_norm)
                optim.step()
            for key in logs:
                logs[key] += out[key].item() / n
            self.target_updater.step()
        return logs

    def stateful_components(self) -> dict:
        parts = {
            "loss": self.loss,
            "optim_actor": self.optim_actor,
            "optim_critic": self.optim_critic,
            "buffer": self.buffer,
        }
        if self.exploration is not None:
            parts["exploration"] = self.exploration
        return parts


@dataclasses.dataclass
class M3DDPGConfig(MADDPGConfig):
    """MADDPG's hyper-parameters (:class:`MADDPGConfig`) and the sizes of the
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
