"""The training blocks the model-free recipes share, with one set of names.

:class:`ModelFreeConfig` holds what every model-free recipe has (discount, gradient clip,
network sizes, parameter sharing); :class:`OffPolicyConfig` adds replay and target-network
fields for the replay-buffer recipes (``maddpg``, ``sac``, ``shapley_ac``) and
:class:`OnPolicyConfig` the PPO fields of ``mappo``; :class:`DiscreteExplorationConfig` adds
how the one-hot actors of ``maddpg`` and ``shapley_ac`` explore. Every shared field is
validated once, here; a recipe's config subclasses a block, adds only its own fields and
changes a shared default by re-declaring the field (e.g. ``gamma: float = 0.99`` in
``SACConfig``).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from typing import Any

import torch
from tensordict import TensorDictBase
from torchrl.data import TensorDictReplayBuffer, TensorSpec
from torchrl.data.replay_buffers.samplers import SamplerWithoutReplacement
from torchrl.envs import EnvBase
from torchrl.modules import EGreedyModule

from mapets_rl.config import ConfigError, check
from mapets_rl.envs.torch_freeway.env import PROPOSED_ACTION
from mapets_rl.experiment.config import ExperimentConfig
from mapets_rl.experiment.shield_punishment import punish_shielded_moves
from mapets_rl.modules import restricted_epsilon_greedy
from mapets_rl.modules.storage import FilledTensorStorage
from mapets_rl.planning.memory import available_memory


def check_layer_sizes(field: str, widths: list[int], device: str = "cpu") -> None:
    """ConfigError (one line naming ``field``) unless ``widths`` is a non-empty list of ints
    >= 1 whose hidden-to-hidden weights can fit: ``sum(w_i * w_(i+1))`` parameters, each with a
    gradient and Adam's two moments (4 x 4 bytes), is a lower bound of any network with these
    layers, so a refusal never stops a network that would fit."""
    check(
        len(widths) >= 1 and min(widths) >= 1,
        field,
        "a non-empty list of positive layer sizes",
        widths,
    )
    need = 16 * sum(a * b for a, b in zip(widths[:-1], widths[1:], strict=False))
    free = available_memory(device)
    check(
        free is None or need <= free,
        field,
        f"layers whose weights fit in memory (at least {need / 2**30:.1f} GiB with Adam's "
        f"state; {0 if free is None else free / 2**30:.1f} GiB available on {device})",
        widths,
    )


def check_epsilon_schedule(epsilon_init: float, epsilon_end: float, anneal_frames: int) -> None:
    """``ConfigError`` unless the epsilon-greedy schedule is valid: ``epsilon_init`` in
    [0, 1], ``epsilon_end`` in [0, epsilon_init], ``epsilon_anneal_frames`` >= 1."""
    check(0 <= epsilon_init <= 1, "epsilon_init", "in [0, 1]", epsilon_init)
    check(0 <= epsilon_end <= epsilon_init, "epsilon_end", "in [0, epsilon_init]", epsilon_end)
    check(anneal_frames >= 1, "epsilon_anneal_frames", ">= 1", anneal_frames)


@dataclasses.dataclass
class ModelFreeConfig(ExperimentConfig):
    """Fields every model-free recipe shares (plus :class:`ExperimentConfig`).

    Attributes:
        gamma: discount in [0, 1].
        max_grad_norm: gradient-norm clip (> 0).
        num_cells: hidden layer sizes of the actor / policy MLPs (and of the critics where the
            recipe has no field of its own for them), a non-empty list of ints >= 1.
        share_params: one actor / policy network shared by all agents (else one per agent).
    """

    gamma: float = 0.95
    max_grad_norm: float = 1.0
    num_cells: list[int] = dataclasses.field(default_factory=lambda: [64, 64])
    share_params: bool = True

    def __post_init__(self) -> None:
        super().__post_init__()
        check(0 <= self.gamma <= 1, "gamma", "in [0, 1]", self.gamma)
        check(self.max_grad_norm > 0, "max_grad_norm", "> 0", self.max_grad_norm)
        check_layer_sizes("num_cells", self.num_cells, self.device)


DEFAULT_INIT_RANDOM_FRAMES = 200
"""The random frames of :class:`OffPolicyConfig` left to its default, before rounding up to
whole collected batches."""


@dataclasses.dataclass
class OffPolicyConfig(ModelFreeConfig):
    """Replay-buffer actor-critic training (plus :class:`ModelFreeConfig`).

    The update-to-data ratio is set by ``updates_per_batch``, ``update_interval`` and
    ``batch_size``, not by ``frames_per_batch``: with ``update_interval = 0`` (default) every
    collected batch is followed by ``updates_per_batch`` gradient steps; with
    ``update_interval = N > 0`` by ``updates_per_batch`` gradient steps for every multiple of
    ``N`` that the run's frame count passed during the batch (counted over the whole run,
    resumes included), i.e. ``updates_per_batch / N`` gradient steps per frame whatever
    ``frames_per_batch`` and ``env_config.num_envs`` are (see :meth:`gradient_steps`).

    Attributes:
        tau: soft target update rate in (0, 1].
        buffer_size: replay capacity in transitions (>= batch_size).
        batch_size: transitions per gradient step (>= 1).
        updates_per_batch: gradient steps per update round (>= 1): after each collected batch
            (``update_interval = 0``) or every ``update_interval`` frames.
        update_interval: frames between update rounds (>= 0; 0: one round per collected
            batch). openai/maddpg's schedule is one gradient step per 100 frames:
            ``update_interval=100, updates_per_batch=1``.
        init_random_frames: frames collected before the first update (>= 0); ``maddpg`` and
            ``sac`` act uniformly at random during them, ``shapley_ac`` acts with its policy
            (see the recipe). Updates start after whole collected batches, so left out
            (``None``) it is 200 rounded up to a multiple of ``frames_per_batch`` (what the
            collector would round 200 to; 200 with the default batches on one road).
        lr_actor, lr_critic: Adam learning rates of the actor(s) and the critic(s) (> 0).
    """

    tau: float = 0.01
    buffer_size: int = dataclasses.field(default=100_000, metadata={"unit": "transitions"})
    batch_size: int = dataclasses.field(default=256, metadata={"unit": "transitions"})
    updates_per_batch: int = 20
    update_interval: int = dataclasses.field(default=0, metadata={"unit": "frames"})
    init_random_frames: int | None = dataclasses.field(default=None, metadata={"unit": "frames"})
    lr_actor: float = 1e-3
    lr_critic: float = 1e-3

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.init_random_frames is None:
            batch = self.frames_per_batch
            self.derive("init_random_frames", -(-DEFAULT_INIT_RANDOM_FRAMES // batch) * batch)
        check(0 < self.tau <= 1, "tau", "in (0, 1]", self.tau)
        check(self.batch_size >= 1, "batch_size", ">= 1", self.batch_size)
        check(
            self.buffer_size >= self.batch_size,
            "buffer_size",
            f">= batch_size={self.batch_size}",
            self.buffer_size,
        )
        check(self.updates_per_batch >= 1, "updates_per_batch", ">= 1", self.updates_per_batch)
        check(self.update_interval >= 0, "update_interval", ">= 0", self.update_interval)
        self._check_an_update_round()
        check(self.init_random_frames >= 0, "init_random_frames", ">= 0", self.init_random_frames)
        check(self.lr_actor > 0, "lr_actor", "> 0", self.lr_actor)
        check(self.lr_critic > 0, "lr_critic", "> 0", self.lr_critic)

    def _check_an_update_round(self) -> None:
        """ConfigError naming ``update_interval`` when no update round of the run falls at or
        after the batch whose end first fills the replay buffer with ``batch_size``
        transitions (one per frame): such a run would make no gradient step. (A budget too
        short to fill the buffer at all is left to the recipe: tiny runs that check the
        plumbing make no step either.)"""
        batch, interval = self.frames_per_batch, self.update_interval
        last = -(-self.total_frames // batch) * batch  # the frame count after the last batch
        ready = -(-self.batch_size // batch) * batch  # ... after the batch that fills the buffer
        if interval == 0 or ready > last:
            return
        check(
            last // interval > (ready - batch) // interval,
            "update_interval",
            f"a number of frames with a multiple between frame {ready - batch + 1} and frame "
            f"{last} (the replay buffer first holds batch_size={self.batch_size} transitions "
            f"after the batch ending at frame {ready}, the last batch ends at frame {last}); "
            "else the run makes no gradient step",
            interval,
        )

    @classmethod
    def upgrade_dict(cls, data: Mapping[str, Any]) -> dict[str, Any]:
        """A config written before ``update_interval`` existed updated after every batch:
        ``update_interval = 0``."""
        data = super().upgrade_dict(data)
        data.setdefault("update_interval", 0)
        return data

    def gradient_steps(self, frames_before: int, frames_after: int) -> int:
        """Gradient steps due after a batch took the run's frame count from ``frames_before``
        to ``frames_after``: ``updates_per_batch`` (``update_interval = 0``), else
        ``updates_per_batch`` times the multiples of ``update_interval`` in
        ``(frames_before, frames_after]``."""
        if self.update_interval == 0:
            return self.updates_per_batch
        rounds = frames_after // self.update_interval - frames_before // self.update_interval
        return self.updates_per_batch * rounds


@dataclasses.dataclass
class DiscreteExplorationConfig(OffPolicyConfig):
    """How a deterministic one-hot actor explores while collecting (plus
    :class:`OffPolicyConfig`; ``maddpg``, ``m3ddpg``, ``shapley_ac``).

    Attributes:
        gumbel_tau: Gumbel-softmax temperature (> 0) of the actor's one-hot head.
        exploration: ``"gumbel"`` (a hard Gumbel-softmax sample of the actor's logits) or
            ``"epsilon"`` (the greedy action, replaced for each agent with probability epsilon
            by a uniform draw among ``exploration_actions``;
            :func:`~mapets_rl.modules.restricted_epsilon_greedy`).
        epsilon_init, epsilon_end: the epsilon-greedy probability (in [0, 1], end <= init) of
            a random action per agent, annealed linearly over ``epsilon_anneal_frames``.
        epsilon_anneal_frames: frames (>= 1) over which epsilon goes from init to end.
        exploration_actions: the action indices an epsilon-greedy draw picks from (empty:
            all; the freeways' are 0 KL, 1 CL, 2 CR, 3 ES).
        actor_initial_logits: the actor's output biases at construction, one per action
            (empty: the random initialisation). ``[3, 0, 0, 0]`` on the freeways starts the
            greedy actor at Keep Lane in every state, so with a small epsilon the first data
            come from keep lane with random moves, the behaviour under which a critic's
            advantage head resolves a CAV's move (issue 50; ``docs/results/shapley.md``).
        shield_penalty: under the freeways' shield, what the learner stores where the shield
            replaced a move: None (default) the transition that ran (Keep Lane); a number
            ``p >= 0`` the proposed move with the agent's reward lowered by ``p`` (post-posed
            shielding with punishment, :mod:`mapets_rl.experiment.shield_punishment`).
    """

    gumbel_tau: float = 1.0
    exploration: str = "gumbel"
    epsilon_init: float = 1.0
    epsilon_end: float = 0.05
    epsilon_anneal_frames: int = dataclasses.field(default=100_000, metadata={"unit": "frames"})
    exploration_actions: list[int] = dataclasses.field(default_factory=list)
    actor_initial_logits: list[float] = dataclasses.field(default_factory=list)
    shield_penalty: float | None = None

    def __post_init__(self) -> None:
        super().__post_init__()
        check(self.gumbel_tau > 0, "gumbel_tau", "> 0", self.gumbel_tau)
        check(
            all(math.isfinite(v) for v in self.actor_initial_logits),
            "actor_initial_logits",
            "finite numbers, one per action (or empty)",
            self.actor_initial_logits,
        )
        check(
            self.shield_penalty is None or self.shield_penalty >= 0,
            "shield_penalty",
            "None or a number >= 0",
            self.shield_penalty,
        )
        check(
            self.exploration in ("gumbel", "epsilon"),
            "exploration",
            "'gumbel' or 'epsilon'",
            self.exploration,
        )
        check_epsilon_schedule(self.epsilon_init, self.epsilon_end, self.epsilon_anneal_frames)
        check(
            all(a >= 0 for a in self.exploration_actions)
            and len(set(self.exploration_actions)) == len(self.exploration_actions),
            "exploration_actions",
            "distinct action indices >= 0",
            self.exploration_actions,
        )

    @classmethod
    def upgrade_dict(cls, data: Mapping[str, Any]) -> dict[str, Any]:
        """A config written before ``actor_initial_logits`` or ``shield_penalty`` existed had
        the random initialisation (``[]``) and stored the transition that ran (``None``)."""
        data = super().upgrade_dict(data)
        data.setdefault("actor_initial_logits", [])
        data.setdefault("shield_penalty", None)
        return data

    def check_shield_penalty(self, env: EnvBase) -> None:
        """Refuse ``shield_penalty`` (before any training) where ``env`` keeps no proposal
        under ``("agents", "proposed_action")``: an env without the shield."""
        if self.shield_penalty is not None and PROPOSED_ACTION not in env.full_state_spec.keys(
            include_nested=True
        ):
            raise ConfigError(
                f"shield_penalty={self.shield_penalty} needs the shield's proposals: "
                f"{self.env!r} must be the torch freeway with env_config shield: true"
            )

    def stored_transitions(self, batch: TensorDictBase) -> TensorDictBase:
        """The collected ``batch [*]`` as the learner stores it: with ``shield_penalty`` set,
        every move the shield replaced restored and punished
        (:func:`~mapets_rl.experiment.shield_punishment.punish_shielded_moves`)."""
        if self.shield_penalty is None:
            return batch
        return punish_shielded_moves(batch, self.shield_penalty)

    def epsilon_greedy(self, action_spec: TensorSpec) -> EGreedyModule | None:
        """The epsilon-greedy module that follows the actor while collecting
        (``exploration="epsilon"``; ``action_spec``: the group's one-hot action spec
        ``[n_agents, action_dim]``), or ``None`` (``"gumbel"``: the actor's head samples)."""
        if self.exploration != "epsilon":
            return None
        return restricted_epsilon_greedy(
            action_spec,
            self.exploration_actions,
            eps_init=self.epsilon_init,
            eps_end=self.epsilon_end,
            annealing_num_steps=self.epsilon_anneal_frames,
        )


@dataclasses.dataclass
class OnPolicyConfig(ModelFreeConfig):
    """PPO-style on-policy training on the last collected batch (plus :class:`ModelFreeConfig`).

    Attributes:
        lr: Adam learning rate of policy and value, one optimiser (> 0).
        lmbda: GAE lambda in [0, 1].
        epochs: passes over each collected batch (>= 1).
        minibatch_size: transitions per gradient step (1 .. frames_per_batch).
    """

    gamma: float = 0.99
    lr: float = 3e-4
    lmbda: float = 0.95
    epochs: int = 4
    minibatch_size: int = 100

    def __post_init__(self) -> None:
        super().__post_init__()
        check(self.lr > 0, "lr", "> 0", self.lr)
        check(0 <= self.lmbda <= 1, "lmbda", "in [0, 1]", self.lmbda)
        check(self.epochs >= 1, "epochs", ">= 1", self.epochs)
        check(
            1 <= self.minibatch_size <= self.frames_per_batch,
            "minibatch_size",
            f"in [1, frames_per_batch={self.frames_per_batch}]",
            self.minibatch_size,
        )

    def latest_batch_buffer(self, device: torch.device | str | None) -> TensorDictReplayBuffer:
        """The on-policy buffer: room for the latest collected batch (``frames_per_batch``
        transitions, on ``device``), sampled in minibatches of ``minibatch_size`` without
        replacement (fill it with :meth:`load_latest_batch`)."""
        return TensorDictReplayBuffer(
            storage=FilledTensorStorage(self.frames_per_batch, device=device),
            sampler=SamplerWithoutReplacement(),
            batch_size=self.minibatch_size,
        )

    def load_latest_batch(self, buffer: TensorDictReplayBuffer, batch: TensorDictBase) -> int:
        """Replaces the contents of ``buffer`` (from :meth:`latest_batch_buffer`) by the
        transitions of ``batch [*]`` (flattened) and returns the number of minibatch gradient
        steps of ``epochs`` passes over them: ``epochs * max(batch.numel() // minibatch_size,
        1)``."""
        buffer.empty()
        buffer.extend(batch.reshape(-1))
        return self.epochs * max(batch.numel() // self.minibatch_size, 1)
