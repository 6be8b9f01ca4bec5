"""Independent (per-agent) DQN baseline (Mnih et al. 2015; double DQN, van Hasselt et al. 2016),
the MA-PETS paper's ``DQN [59]``.

config -> env -> modules (per-agent Q(o_i, .) over a discrete action set; greedy choice by
torchrl's ``QValueModule``; on continuous scenarios an action map from the choice to the
continuous action) -> collector (epsilon-greedy on the choice, torchrl's ``EGreedyModule``) ->
replay buffer -> loss (torchrl ``DQNLoss``, double DQN: the online net picks the next action,
the target net values it; target net by ``SoftUpdate``) -> loop (shared ``Experiment.train``).

The discrete action set (:func:`~mapets_rl.modules.action_map.make_action_map`): on the
figure-eights the target speed takes ``speed_levels`` evenly spaced values in ``[0, 13.89]``
m/s (default 8, a level every 1.98 m/s: the resolution of the action grid of the library's
discretised MA-PETS, ``tile_coding.action_bins = 8``; the Q head grows with the level count,
and at 8 levels one step of the grid is ~14% of the top speed), and on two lanes each level
comes with the lane-change flag off or on (``2 * speed_levels`` actions). The paper does not say
how its DQN discretised the actions. Scenarios with one-hot actions (the freeways) use theirs.

Same observation and reward as the other baselines (the scenario's own). ``share_params`` as in
``sac`` and ``maddpg``: one Q network shared by all agents (each acts on its own observation;
default) or one per agent. The first ``init_random_frames`` frames are played at
``epsilon_init`` (1: uniformly random choices) and wait for updates; epsilon then anneals
linearly to ``epsilon_end`` over ``epsilon_anneal_frames``.
"""

from __future__ import annotations

import dataclasses

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModule, TensorDictSequential
from tensordict.utils import NestedKey
from torch import nn
from torchrl.data import OneHot, TensorDictReplayBuffer
from torchrl.modules import EGreedyModule, QValueModule
from torchrl.objectives import DQNLoss, SoftUpdate, ValueEstimators

from mapets_rl.experiment import Experiment, check
from mapets_rl.experiment.training import OffPolicyConfig, check_epsilon_schedule
from mapets_rl.modules import (
    ACTION,
    ACTION_VALUE,
    GROUP,
    LOSS_KEYS,
    MASK,
    OBS,
    OBS_NORM,
    TRANSITION_KEYS,
    AgentGroupSpec,
    make_decentralised_mlp,
    make_obs_norm,
    restricted_epsilon_greedy,
    sync_target_statistics,
)
from mapets_rl.modules.action_map import ACTION_CHOICE, make_action_map
from mapets_rl.modules.storage import FilledTensorStorage

CHOSEN_VALUE = (GROUP, "chosen_action_value")
"""Q(o_i, a_i) of the chosen action per agent [*, I, 1] (``QValueModule``'s third output)."""

_LR_ACTOR_DEFAULT = OffPolicyConfig.lr_actor


@dataclasses.dataclass
class DQNConfig(OffPolicyConfig):
    """DQN hyper-parameters; the shared off-policy fields (``gamma``, ``tau`` (the target net's
    soft update), ``num_cells`` (the Q network), ``share_params``, ``buffer_size``,
    ``batch_size``, ``updates_per_batch``, ``update_interval``, ``init_random_frames``,
    ``max_grad_norm``) are those of :class:`~mapets_rl.experiment.training.OffPolicyConfig`;
    ``lr_critic`` is the Q network's Adam learning rate (``lr_actor`` must be left out: DQN
    has no actor).

    Attributes:
        speed_levels: target-speed levels of the discrete action set on continuous scenarios
            (>= 2; see the module docstring).
        epsilon_init, epsilon_end: the probability (in [0, 1], end <= init) that an agent's
            choice is replaced by a uniform draw, from ``epsilon_init`` over the first
            ``init_random_frames`` frames, then linearly to ``epsilon_end`` over
            ``epsilon_anneal_frames``.
        epsilon_anneal_frames: frames (>= 1) of the annealing.
        normalize_obs: standardise observations with running statistics of collected data.
    """

    gamma: float = 0.99
    speed_levels: int = 8
    epsilon_init: float = 1.0
    epsilon_end: float = 0.05
    epsilon_anneal_frames: int = dataclasses.field(default=10_000, metadata={"unit": "frames"})
    normalize_obs: bool = True

    def __post_init__(self) -> None:
        super().__post_init__()
        check(
            self.lr_actor == _LR_ACTOR_DEFAULT,
            "lr_actor",
            "left out (dqn has no actor; lr_critic is the Q network's learning rate)",
            self.lr_actor,
        )
        check(self.speed_levels >= 2, "speed_levels", ">= 2", self.speed_levels)
        check_epsilon_schedule(self.epsilon_init, self.epsilon_end, self.epsilon_anneal_frames)


class FirstMaxQValueModule(QValueModule):
    """torchrl's ``QValueModule`` whose one-hot choice is the first action of highest value.
    torchrl's marks every action tied for the highest value, so a tie would choose several at
    once: their summed target speeds on the figure-eights (an action out of range) and their
    summed values in the double-DQN target."""

    @staticmethod
    def _one_hot(value: torch.Tensor) -> torch.Tensor:
        return torch.nn.functional.one_hot(value.argmax(-1), value.shape[-1])


def greedy_choice(choice_key: NestedKey = ACTION_CHOICE) -> QValueModule:
    """torchrl's ``QValueModule`` on the group (:class:`FirstMaxQValueModule`):
    ``ACTION_VALUE`` ``[*, I, K]`` -> the greedy one-hot choice at ``choice_key`` ``[*, I, K]``
    (one action, the first of the best) and its value ``CHOSEN_VALUE`` ``[*, I, 1]``."""
    return FirstMaxQValueModule(
        action_space="one-hot",
        action_value_key=ACTION_VALUE,
        out_keys=[choice_key, ACTION_VALUE, CHOSEN_VALUE],
    )


def make_dqn_loss(
    value_network: TensorDictModule,
    choice_spec: OneHot,
    gamma: float,
    choice_key: NestedKey = ACTION_CHOICE,
) -> DQNLoss:
    """torchrl's double-DQN loss on the ``"agents"`` group: TD(0) targets
    ``r_i + gamma * (1 - terminated_i) * Q_target(o'_i, argmax_a Q(o'_i, a))`` per agent,
    squared error against ``Q(o_i, a_i)`` of the replayed choice at ``choice_key`` (one-hot;
    ``ACTION`` on scenarios with one-hot actions), averaged over transitions and agents.

    Args:
        value_network: ``OBS`` -> ``ACTION_VALUE`` ``[*, I, K]``, ``choice_key`` (greedy
            one-hot) and ``CHOSEN_VALUE`` ``[*, I, 1]`` (e.g. a Q network followed by
            :func:`greedy_choice`).
        choice_spec: the one-hot spec ``[I, K]`` of the choice.
        gamma: discount in [0, 1].
    """
    loss = DQNLoss(
        value_network,
        action_space=choice_spec,
        delay_value=True,
        double_dqn=True,
        loss_function="l2",
    )
    loss.set_keys(**LOSS_KEYS, action=choice_key, action_value=ACTION_VALUE, value=CHOSEN_VALUE)
    loss.make_value_estimator(ValueEstimators.TD0, gamma=gamma)
    return loss


class DQN(Experiment):
    """Independent DQN (double DQN, soft target updates) on any scenario: continuous actions
    through a discrete action set, one-hot actions as they are."""

    name = "dqn"
    Config = DQNConfig

    def __init__(self, config: DQNConfig, run_dir=None) -> None:
        super().__init__(config, run_dir)  # seeds, run dir, self.env
        spec = AgentGroupSpec.from_env(self.env)

        # the discrete action set: the scenario's one-hot actions, or a grid over its
        # continuous ones with the map from a choice to its continuous action
        if spec.discrete:
            choice_key, choice_spec, action_map = ACTION, spec.action_spec, []
        else:
            mapping, choice_spec, _table = make_action_map(spec, config.speed_levels)
            choice_key, action_map = ACTION_CHOICE, [mapping]
        n_actions = choice_spec.shape[-1]

        # modules: (observation normaliser ->) Q(o_i, .) per agent -> greedy one-hot choice
        self.obs_norm, norm_module = make_obs_norm(spec) if config.normalize_obs else (None, None)
        front = [] if norm_module is None else [norm_module]
        q_net = TensorDictModule(
            make_decentralised_mlp(spec, config.num_cells, config.share_params, n_out=n_actions),
            in_keys=[OBS if norm_module is None else OBS_NORM],
            out_keys=[ACTION_VALUE],
        )
        self.value_network = TensorDictSequential(*front, q_net, greedy_choice(choice_key))
        self.exploration: EGreedyModule = restricted_epsilon_greedy(
            choice_spec,
            [],
            eps_init=config.epsilon_init,
            eps_end=config.epsilon_end,
            annealing_num_steps=config.epsilon_anneal_frames,
            action_key=choice_key,
        )

        # collector: epsilon-greedy choices (the random frames too: epsilon_init); evaluation
        # takes the greedy choice
        self.collector = self.make_collector(
            TensorDictSequential(self.value_network, self.exploration, *action_map)
        )
        self.eval_policy = TensorDictSequential(self.value_network, *action_map)

        # buffer
        self.replay_keys = (*TRANSITION_KEYS, choice_key)
        self.buffer = TensorDictReplayBuffer(
            storage=FilledTensorStorage(config.buffer_size, device=self.device),
            batch_size=config.batch_size,
        )

        # loss: double DQN, TD(0) targets, soft target updates
        self.loss = make_dqn_loss(self.value_network, choice_spec, config.gamma, choice_key)
        self.target_updater = SoftUpdate(self.loss, tau=config.tau)
        self.optim = torch.optim.Adam(self.loss.parameters(), lr=config.lr_critic)

    def train_step(self, batch: TensorDictBase) -> dict[str, float]:
        """Store the batch ``[*, T]``; anneal epsilon once ``init_random_frames`` have passed;
        then the gradient steps due (:meth:`OffPolicyConfig.gradient_steps`), each a double-DQN
        step and a soft target update."""
        self.buffer.extend(batch.reshape(-1).select(*self.replay_keys))
        if self.obs_norm is not None:
            self.obs_norm.update(batch.get(OBS), batch.get(MASK, None))
            sync_target_statistics(self.loss, self.obs_norm)
        start = self.config.init_random_frames
        self.exploration.step(max(self.frames - max(self.frames - batch.numel(), start), 0))
        n = self.config.gradient_steps(self.frames - batch.numel(), self.frames)
        if len(self.buffer) < self.config.batch_size or self.frames < start or n == 0:
            return {}
        total = 0.0
        for _ in range(n):
            loss = self.loss(self.buffer.sample())["loss"]
            self.optim.zero_grad()
            loss.backward()
            nn.utils.clip_grad_norm_(self.loss.parameters(), self.config.max_grad_norm)
            self.optim.step()
            self.target_updater.step()
            total += loss.item() / n
        return {"loss_value": total, "epsilon": float(self.exploration.eps)}

    def stateful_components(self) -> dict:
        return {
            "loss": self.loss,
            "optim": self.optim,
            "buffer": self.buffer,
            "exploration": self.exploration,
        }
