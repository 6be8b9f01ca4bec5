"""Shapley-value reward reallocation actor-critic (Han et al., Algorithm 1) on the freeway.

Reads top to bottom: config -> modules (coalition sampler, actors on ``s^C``, coalition critic)
-> collector -> replay buffer -> loss + target updater -> optimisers -> ``train_step``.

Every collected step carries a fresh random coalition ``C`` (Algorithm 1 line 6, written by
:class:`~mapets_rl.shapley.RandomCoalition` into ``("agents", "coalition")``); agent ``i``'s actor
sees ``s^C`` (line 7); the transition ``(s, a, C, r, s')`` is replayed to train the
characteristic function ``v(s, a, C)`` on ``R(C) = sum_{i in C} r_i`` and the actors on the
Shapley value ``phi_i`` (lines 9-15, :class:`~mapets_rl.objectives.ShapleyActorCriticLoss`).
Evaluation uses the grand coalition (all CAVs cooperate), as the paper reports.

Usage::

    from mapets_rl.recipes.shapley_ac import ShapleyAC, ShapleyACConfig
    ShapleyAC(ShapleyACConfig(total_frames=4000, seed=1)).train()

or ``mapets-rl train shapley_ac env_config.cav_ratio=0.5``.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from typing import Any, ClassVar

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictSequential
from torchrl.data import TensorDictReplayBuffer
from torchrl.objectives import SoftUpdate

from mapets_rl.experiment import Experiment, SystemRewardMetrics, check
from mapets_rl.experiment.training import DiscreteExplorationConfig, check_layer_sizes
from mapets_rl.modules import (
    ACTION,
    MASK,
    OBS,
    OBS_NORM,
    AgentGroupSpec,
    GumbelSoftmaxHead,
    make_discrete_actor,
    make_obs_norm,
    sync_target_statistics,
)
from mapets_rl.modules.storage import FilledTensorStorage
from mapets_rl.objectives import ShapleyActorCriticLoss
from mapets_rl.shapley import CoalitionCritic, RandomCoalition, make_coalition_actor

COALITION = ("agents", "coalition")
LOGITS = ("agents", "logits")
REPLAY_KEYS = [
    OBS,
    ACTION,
    COALITION,
    MASK,
    ("next", "agents", "observation"),
    ("next", "agents", "reward"),
    ("next", "agents", "terminated"),
]


def _default_env_config() -> dict[str, Any]:
    # CPU scale: 8 vehicles of which 4 CAVs (paper: 30 CAVs); see ShapleyACConfig.
    return {"n_vehicles": 8, "cav_ratio": 0.5}


@dataclasses.dataclass
class ShapleyACConfig(DiscreteExplorationConfig):
    """Shapley actor-critic hyper-parameters; the shared off-policy fields (``gamma``, ``tau``,
    ``lr_actor``, ``lr_critic``, ``num_cells``, ``share_params``, ``buffer_size``,
    ``batch_size``, ``updates_per_batch``, ``init_random_frames``, ``max_grad_norm``) are
    those of :class:`~mapets_rl.experiment.training.OffPolicyConfig`; how the actors explore
    while collecting (``exploration``: ``gumbel`` samples, default, or ``epsilon``-greedy over
    ``exploration_actions``) and ``gumbel_tau`` (also the temperature of the actor gradient's
    relaxation) are those of :class:`~mapets_rl.experiment.training.DiscreteExplorationConfig`.

    Attributes:
        num_cells: hidden sizes of the per-agent actors (``critic_cells``: of the critic).
        share_params: one actor for all CAVs instead of one per CAV (default True, with
            ``ego_first``); one actor per CAV sees 1/n of the data each. Measured in
            docs/results/history.md#fig-2-at-30-cavs-on-the-freeway-shapley-ac-maddpg-coma-mappo.
        init_random_frames: transitions in the buffer before the first update; they are
            collected with the policy (its coalitions are random), not with random actions.
        critic_cells: hidden sizes of the coalition critic.
        critic_embed_cells: hidden sizes of a nonlinear per-agent network in the coalition
            critic before its members are summed (``CoalitionCritic(embed_cells=...)``; empty,
            the default: the paper's MLP on the zero-masked joint input, whose first layer pools
            the members' linear terms). Results:
            docs/results/history.md#which-of-the-three-changes-are-needed-and-five-seeds-at-300k-frames.
        critic_member_heads: the coalition critic ends in one output per CAV and ``v(C)`` is
            the sum of its members' outputs, each fitted to its own member's reward
            (``CoalitionCritic(member_heads=True)``; the TD targets summed over ``C`` are the
            paper's). False, the default: one output fitted to ``R(C)``, the paper's.
        join_prob: probability that a CAV joins the random coalition of a timestep
            (``coalition_sizes="binomial"``).
        coalition_sizes: how a timestep's coalition is drawn while collecting: ``binomial``
            (every CAV joins with ``join_prob``, the paper's Algorithm 1) or ``uniform`` (size
            uniform over 1..alive CAVs, then the members: the sizes at which the permutation
            estimator reads the critic; see :class:`~mapets_rl.shapley.RandomCoalition`).
        eval_coalition: coalition used in evaluation: ``grand``, ``empty`` or ``random``.
        logits_reg: weight of the squared-logits penalty in the actor loss (keeps the discrete
            policies from saturating early; 0.1 suits the freeway, whose values are in the
            hundreds; docs/results/history.md#fig-2-at-4-cavs-on-the-freeway).
        actor_view: what each CAV's actor reads: ``coalition`` (the paper's ``pi_i(s^C)``: a
            Tanh MLP on the zero-masked joint observation of the timestep's coalition, ordered
            by ``ego_first``) or ``own`` (MADDPG's actor,
            :func:`~mapets_rl.modules.make_discrete_actor`: a ReLU MLP on the CAV's own
            observation, whatever the coalition). With ``own`` and
            ``normalize_obs`` the actors of the two recipes are built alike, so the arms differ
            in the critic and the credit only, and the greedy policy reads what it read while
            collecting (no grand-coalition view it never trained on).
        normalize_obs: standardise the actor's observations with running statistics
            (:func:`~mapets_rl.modules.make_obs_norm`, MADDPG's default), updated from every
            collected batch; the critic reads raw observations.
        exact_max_agents: Shapley exact up to this many CAVs, permutation sampling beyond.
        num_permutations: orderings per update on the sampled path (even, >= 4: antithetic
            pairs, shared by the whole minibatch; the standard error is logged as
            ``shapley_stderr``).
        reward_scale: multiplies the coalition reward ``R(C)`` in the critic target (> 0).
        ego_first: every actor's coalition view lists its own observation first (needed for
            ``share_params``: one actor for all CAVs must know which slot is its own).
        shapley_chunk_states: states per pass of the Shapley computation (None: all at once).
            Timings:
            docs/results/performance.md#shapley-values-batched-against-loops-benchmarksshapleypy.
        shapley_value_states: states of each minibatch whose Shapley values are computed in
            full for the reported actor loss, ``shapley_value`` and ``shapley_stderr`` (None:
            all); the actor's gradient uses every state either way (the loss's
            ``value_states``: it skips the coalitions without the agent elsewhere).
        shapley_bf16: evaluate the Shapley critic passes under bf16 autocast (pays on CPUs with
            AVX512-BF16/AMX and on GPUs; about 9x slower on AVX2-only CPUs).
    """

    # run directories written before the shared off-policy names read under the new ones
    renamed_fields: ClassVar[Mapping[str, tuple[str, ...]]] = {
        "actor_lr": ("lr_actor",),
        "critic_lr": ("lr_critic",),
        "actor_cells": ("num_cells",),
        "share_actor_params": ("share_params",),
        "warmup_frames": ("init_random_frames",),
        "gumbel_temperature": ("gumbel_tau",),
    }

    default_frames_per_batch: ClassVar[int] = 40  # one road's batch, see ExperimentConfig

    env: str = "freeway"
    env_config: dict[str, Any] = dataclasses.field(default_factory=_default_env_config)
    total_frames: int = 4000
    eval_interval: int = 400
    eval_episodes: int = 2
    checkpoint_interval: int = 1000
    share_params: bool = True
    batch_size: int = 128
    updates_per_batch: int = 10
    critic_cells: list[int] = dataclasses.field(default_factory=lambda: [128, 128])
    critic_embed_cells: list[int] = dataclasses.field(default_factory=list)
    critic_member_heads: bool = False
    join_prob: float = 0.5
    coalition_sizes: str = "binomial"
    eval_coalition: str = "grand"
    exact_max_agents: int = 10
    num_permutations: int = 32
    logits_reg: float = 0.1
    reward_scale: float = 1.0
    ego_first: bool = True
    shapley_chunk_states: int | None = 8
    shapley_bf16: bool = False
    shapley_value_states: int | None = None
    actor_view: str = "coalition"
    normalize_obs: bool = False

    @classmethod
    def upgrade_dict(cls, data: Mapping[str, Any]) -> dict[str, Any]:
        """A ``config.yaml`` written before ego-first views existed trained actors that see the
        agents in index order: it resumes with ``ego_first=False``, not today's default; one
        written before ``critic_embed_cells`` or ``critic_member_heads`` existed trained the
        paper's critic (no per-agent layer, one output), today's default; one written before
        ``actor_view``, ``normalize_obs`` or ``shapley_value_states`` existed trained the
        coalition-view actor, unnormalised, on full Shapley values."""
        data = super().upgrade_dict(data)
        data.setdefault("ego_first", False)
        data.setdefault("critic_embed_cells", [])
        data.setdefault("critic_member_heads", False)
        data.setdefault("actor_view", "coalition")  # before MADDPG's actor was an option
        data.setdefault("normalize_obs", False)
        data.setdefault("shapley_value_states", None)
        return data

    def __post_init__(self) -> None:
        super().__post_init__()
        check_layer_sizes("critic_cells", self.critic_cells, self.device)
        if self.critic_embed_cells:
            check_layer_sizes("critic_embed_cells", self.critic_embed_cells, self.device)
        check(0.0 <= self.join_prob <= 1.0, "join_prob", "in [0, 1]", self.join_prob)
        check(
            self.coalition_sizes in ("binomial", "uniform"),
            "coalition_sizes",
            "one of binomial, uniform",
            self.coalition_sizes,
        )
        check(
            self.eval_coalition in ("grand", "empty", "random"),
            "eval_coalition",
            "one of grand, empty, random",
            self.eval_coalition,
        )
        check(
            1 <= self.exact_max_agents <= 20,
            "exact_max_agents",
            "in [1, 20]",
            self.exact_max_agents,
        )
        check(
            self.num_permutations >= 4 and self.num_permutations % 2 == 0,
            "num_permutations",
            "an even int >= 4",
            self.num_permutations,
        )
        check(
            self.actor_view in ("coalition", "own"),
            "actor_view",
            "one of coalition, own",
            self.actor_view,
        )
        check(
            self.actor_view == "own" or not self.actor_initial_logits,
            "actor_initial_logits",
            "empty unless actor_view='own' (the coalition actor has no such output layer)",
            self.actor_initial_logits,
        )
        check(self.logits_reg >= 0, "logits_reg", ">= 0", self.logits_reg)
        check(self.reward_scale > 0, "reward_scale", "> 0", self.reward_scale)
        check(
            self.shapley_value_states is None or self.shapley_value_states >= 1,
            "shapley_value_states",
            "None or an int >= 1",
            self.shapley_value_states,
        )
        check(
            self.shapley_chunk_states is None or self.shapley_chunk_states >= 1,
            "shapley_chunk_states",
            "None or an int >= 1",
            self.shapley_chunk_states,
        )


class ShapleyAC(SystemRewardMetrics, Experiment):
    """Cooperative policy learning with Shapley value reward reallocation (Algorithm 1)."""

    name = "shapley_ac"
    Config = ShapleyACConfig
    action_kinds = ("discrete",)

    def __init__(self, config: ShapleyACConfig, run_dir: Any = None) -> None:
        super().__init__(config, run_dir)
        config.check_shield_penalty(self.env)
        group = AgentGroupSpec.from_env(self.env)
        n, device = group.n_agents, self.device

        # modules: coalition of the timestep -> actors on s^C (-> epsilon-greedy while
        # collecting, else the actors' Gumbel samples); coalition critic v(s, a, C)
        self.exploration = config.epsilon_greedy(self.env.full_action_spec_unbatched[ACTION])
        self.coalition = RandomCoalition(
            n,
            join_prob=config.join_prob,
            eval_mode=config.eval_coalition,
            sizes=config.coalition_sizes,
        )
        self.obs_norm, norm_module = make_obs_norm(group) if config.normalize_obs else (None, None)
        sample = self.exploration is None
        if config.actor_view == "own":
            head = GumbelSoftmaxHead(config.gumbel_tau, return_logits=True, sample=sample)
            self.actor = make_discrete_actor(
                group,
                config.num_cells,
                config.share_params,
                head,
                logits_key=LOGITS,
                obs_norm=norm_module,
                initial_logits=config.actor_initial_logits,
            ).to(device)
        else:
            coalition_actor = make_coalition_actor(
                n,
                group.obs_dim,
                group.action_dim,
                discrete=True,
                num_cells=config.num_cells,
                share_params=config.share_params,
                ego_first=config.ego_first,
                action_head=GumbelSoftmaxHead(config.gumbel_tau, sample=sample),
                observation_key=OBS if norm_module is None else OBS_NORM,
                device=device,
            )
            front = [] if norm_module is None else [norm_module.to(device)]
            self.actor = TensorDictSequential(*front, coalition_actor) if front else coalition_actor
        self.critic = CoalitionCritic(
            n,
            group.obs_dim,
            group.action_dim,
            num_cells=config.critic_cells,
            embed_cells=config.critic_embed_cells,
            member_heads=config.critic_member_heads,
            device=device,
        )
        self.policy = TensorDictSequential(self.coalition, self.actor)

        # collector (no random warm-up phase: the coalition is written by the policy)
        self.collector = self.make_collector(
            self.policy
            if self.exploration is None
            else TensorDictSequential(self.policy, self.exploration)
        )
        self.eval_policy = self.policy

        self.buffer = TensorDictReplayBuffer(
            storage=FilledTensorStorage(config.buffer_size, device=device),
            batch_size=config.batch_size,
        )

        # loss + soft target updates
        self.loss = ShapleyActorCriticLoss(
            self.actor,
            self.critic,
            action_space="discrete",
            gamma=config.gamma,
            exact_max_agents=config.exact_max_agents,
            num_permutations=config.num_permutations,
            gumbel_temperature=config.gumbel_tau,
            logits_reg=config.logits_reg,
            chunk_states=config.shapley_chunk_states,
            autocast_bf16=config.shapley_bf16,
            value_states=config.shapley_value_states,
            reward_scale=config.reward_scale,
        ).to(device)  # its coalition tables are buffers built on the CPU
        self.updater = SoftUpdate(self.loss, tau=config.tau)
        self.actor_optim = torch.optim.Adam(
            self.loss.actor_network_params.values(True, True), lr=config.lr_actor
        )
        self.critic_optim = torch.optim.Adam(
            self.loss.critic_network_params.values(True, True), lr=config.lr_critic
        )

    def train_step(self, batch: TensorDictBase) -> dict[str, float]:
        """Store the transitions of the batch ``[*, T]`` (``[T]``, or ``[B, T]`` from ``B``
        roads); once the buffer holds ``max(init_random_frames, batch_size)`` of them, the
        gradient steps due (:meth:`OffPolicyConfig.gradient_steps`), each a critic step, an
        actor step on the Shapley values and a soft target update."""
        cfg = self.config
        batch = cfg.stored_transitions(batch)
        self.buffer.extend(batch.reshape(-1).select(*REPLAY_KEYS).to(self.device))
        if self.obs_norm is not None:
            self.obs_norm.update(batch.get(OBS), batch.get(MASK, None))
            sync_target_statistics(self.loss, self.obs_norm)
        if self.exploration is not None:
            self.exploration.step(batch.numel())
        steps = cfg.gradient_steps(self.frames - batch.numel(), self.frames)
        if len(self.buffer) < max(cfg.init_random_frames, cfg.batch_size) or steps == 0:
            return {}
        logs: dict[str, float] = {}
        for _ in range(steps):
            sample = self.buffer.sample()
            loss_value, meta = self.loss.loss_value(sample)
            self.critic_optim.zero_grad()
            loss_value.backward()
            torch.nn.utils.clip_grad_norm_(
                self.critic_optim.param_groups[0]["params"], cfg.max_grad_norm
            )
            self.critic_optim.step()
            loss_actor, meta_actor = self.loss.loss_actor(sample)
            self.actor_optim.zero_grad()
            loss_actor.backward()
            torch.nn.utils.clip_grad_norm_(
                self.actor_optim.param_groups[0]["params"], cfg.max_grad_norm
            )
            self.actor_optim.step()
            self.updater.step()
            step = {
                "loss_value": loss_value.item(),
                "loss_actor": loss_actor.item(),
                **{k: v.item() for k, v in {**meta, **meta_actor}.items()},
            }
            for key, val in step.items():
                logs[key] = logs.get(key, 0.0) + val / steps
        return logs

    def stateful_components(self) -> dict[str, Any]:
        parts = {
            "loss": self.loss,
            "actor_optim": self.actor_optim,
            "critic_optim": self.critic_optim,
            "buffer": self.buffer,
        }
        if self.exploration is not None:
            parts["exploration"] = self.exploration
        return parts
