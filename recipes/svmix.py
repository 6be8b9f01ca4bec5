"""SVMIX (Xiao, Li, Wang et al., "Stochastic graph neural network-based value decomposition for
MARL in Internet of Vehicles", IEEE TVT 73(2) 2023, arXiv 2303.13213), the MA-PETS paper's
baseline [13], on the figure-eights.

config -> env -> modules (decentralised TanhNormal policy o_i -> a_i; critic: the
communication graph of range ``d`` with link failures -> per-agent values V_i(o_i) -> the
graph mixer V_tot) -> collector (on-policy: the policy samples) -> buffer (the last batch,
minibatches without replacement) -> loss (:class:`~mapets_rl.objectives.svmix.SVMIXLoss`: GAE
of the team reward on V_tot, the clipped policy gradient with the team advantage) -> loop
(shared ``Experiment.train``).

What is the paper's (its abstract, the only public text the search tool holds, and the MA-PETS
paper's sec. II): a value decomposition of the global feedback into the agents' contributions,
inside a multi-agent actor-critic, whose mixer is a stochastic graph neural network over the
vehicles' time-varying topology (movement and wireless link failures).

What is chosen here, each a config field where it is a setting:

- **Values, not Q-values** ("VMIX" read as mixing state values): the per-agent critics are
  ``V_i(o_i)`` and the mixer gives ``V_tot(s)``, trained on the team reward ``sum_i r_i``
  (``reward_scale`` times); every actor is improved with the one advantage of ``V_tot``, as in
  VDAC-mix (Su, Adams and Beling, AAAI 2021), the value-decomposition actor-critic that mixes
  state values. The policy gradient is PPO's clipped surrogate (``clip_epsilon``) rather than
  VDAC's plain A2C step, so that several epochs per batch (``epochs``) are sound at MA-PETS's
  small budget, the schedule the MAPPO baseline runs with.
- **Continuous actions**: the figure-eight's target speed stays continuous (a TanhNormal policy
  within the action bounds), as for MAPPO, MADDPG and SAC. The mixer mixes state values, so
  nothing in the method needs a discrete action set (a Q-mixer would need one for its argmax),
  and discretising would change the task the other baselines solve. Discrete scenarios work
  too (a one-hot categorical policy).
- **The mixer** (:class:`~mapets_rl.modules.graph_mixer.GraphValueMixer`): node features are
  the agents' (normalised) observations, ``gnn_layers`` rounds of mean-aggregation message
  passing of width ``gnn_hidden``, and per agent QMIX's monotone two-layer mixing (width
  ``mixing_embed``) whose non-negative weights a hypernetwork reads from the agent's node
  embedding; ``V_tot`` is the sum of the agents' contributions, so ``dV_tot/dV_i >= 0``.
- **Stochastic edges**: the graph links the CAVs within ``comm.comm_range`` (``d``, 100 m as
  in the MA-PETS paper's comparison) of each other, from their positions as
  :func:`mapets_rl.comm.communication_graph` builds it; every link fails independently with
  probability ``comm.p_fail`` (0.1 by default: the paper's rate is not public), drawn anew at
  every evaluation of the critic (each transition of each pass sees its own failures, the
  random edge sampling of stochastic graph neural networks). The mixer is the critic only:
  acting needs no communication, so the decision time is the actor's.

Usage::

    from mapets_rl.recipes.svmix import SVMIX, SVMIXConfig
    SVMIX(SVMIXConfig(total_frames=3000, seed=1)).train()

or ``mapets-rl train svmix --env figure-eight comm.p_fail=0.2``, or the published
``mapets-rl train --config figure-eight/svmix``.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModule, TensorDictSequential
from torch import nn

from mapets_rl.comm import CommConfig, communication_graph
from mapets_rl.experiment import Experiment, check
from mapets_rl.experiment.training import OnPolicyConfig, check_layer_sizes
from mapets_rl.modules import (
    GROUP,
    MASK,
    OBS,
    OBS_NORM,
    VALUE,
    AgentGroupSpec,
    make_obs_norm,
    make_stochastic_policy,
    make_value_mlp,
)
from mapets_rl.modules.graph_mixer import GraphValueMixer
from mapets_rl.objectives.svmix import SVMIXLoss

POSITION = (GROUP, "position")
"""Where each agent is, ``[*, I, 2]`` metres (the scenario's)."""
NEIGHBOURS = (GROUP, "svmix_neighbors")
"""The critic's sampled communication graph ``[*, I, I]`` bool (links that did not fail)."""
JOINT_VALUE = "joint_value"
"""The mixed value ``V_tot`` ``[*, 1]``."""
CONTRIBUTION = (GROUP, "mixing_contribution")
"""Each agent's contribution ``c_i`` to ``V_tot`` ``[*, I, 1]``."""
MIXING_WEIGHT = (GROUP, "mixing_weight")
"""Each agent's first-layer mixing weights ``|w1(h_i)|`` ``[*, I, E]``."""


def _default_comm() -> CommConfig:
    return CommConfig(comm_range=100.0, p_fail=0.1)


@dataclasses.dataclass
class SVMIXConfig(OnPolicyConfig):
    """SVMIX hyper-parameters; the shared on-policy fields (``lr`` (actor and critic),
    ``gamma``, ``lmbda`` (GAE), ``epochs``, ``minibatch_size``, ``max_grad_norm``,
    ``num_cells`` (policy and per-agent values), ``share_params`` (the policy)) are those of
    :class:`~mapets_rl.experiment.training.OnPolicyConfig`.

    Attributes:
        comm: the critic's communication graph: ``comm_range`` ``d`` in metres (``inf``: every
            CAV linked, ``0``: none, the mixer then mixes each agent alone) and ``p_fail``,
            the probability that a link fails, drawn per link at every evaluation of the critic
            (chosen: 0.1; the paper's is not public). ``share_plans`` must stay off.
        gnn_hidden: width of the mixer's node embeddings (>= 1).
        gnn_layers: rounds of message passing of the mixer (>= 1).
        mixing_embed: width of each agent's monotone mixing layer (>= 1).
        clip_epsilon: the policy ratio clip (> 0).
        entropy_coeff: entropy bonus weight (>= 0).
        critic_coeff: critic loss weight (> 0).
        reward_scale: multiplies the team reward ``sum_i r_i`` (> 0; the figure-eight's is
            about 20 per CAV and step, 160 for 8 CAVs: 0.001 keeps ``V_tot`` of a 200-step
            episode near 10).
        normalize_obs: standardise observations with running statistics of collected data.
        normalize_advantage: standardise the team advantage over each minibatch.
    """

    comm: CommConfig = dataclasses.field(default_factory=_default_comm)
    gnn_hidden: int = 32
    gnn_layers: int = 2
    mixing_embed: int = 8
    clip_epsilon: float = 0.2
    entropy_coeff: float = 0.01
    critic_coeff: float = 1.0
    reward_scale: float = 0.001
    normalize_obs: bool = True
    normalize_advantage: bool = True

    def __post_init__(self) -> None:
        super().__post_init__()
        check(not self.comm.share_plans, "comm.share_plans", "false (SVMIX plans nothing)", True)
        check(self.gnn_hidden >= 1, "gnn_hidden", ">= 1", self.gnn_hidden)
        check(self.gnn_layers >= 1, "gnn_layers", ">= 1", self.gnn_layers)
        check_layer_sizes("gnn_hidden", [self.gnn_hidden] * (self.gnn_layers + 1), self.device)
        check(self.mixing_embed >= 1, "mixing_embed", ">= 1", self.mixing_embed)
        check(self.clip_epsilon > 0, "clip_epsilon", "> 0", self.clip_epsilon)
        check(self.entropy_coeff >= 0, "entropy_coeff", ">= 0", self.entropy_coeff)
        check(self.critic_coeff > 0, "critic_coeff", "> 0", self.critic_coeff)
        check(self.reward_scale > 0, "reward_scale", "> 0", self.reward_scale)


class StochasticCommunicationGraph(nn.Module):
    """The communication graph with link failures: ``position [*, I, 2]`` and an optional
    ``mask [*, I]`` -> ``[*, I, I]`` bool (:func:`mapets_rl.comm.communication_graph`, its
    failures drawn from torch's global generator, so a checkpoint's RNG state replays them)."""

    def __init__(self, comm_range: float, p_fail: float) -> None:
        super().__init__()
        self.comm_range = comm_range
        self.p_fail = p_fail

    def forward(self, position: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
        return communication_graph(position, self.comm_range, self.p_fail, mask=mask)

    def extra_repr(self) -> str:
        return f"comm_range={self.comm_range}, p_fail={self.p_fail}"


class SVMIX(Experiment):
    """SVMIX: a value-decomposition actor-critic whose mixer is a graph network over the
    vehicles' communication graph with link failures (see the module docstring)."""

    name = "svmix"
    Config = SVMIXConfig

    def __init__(self, config: SVMIXConfig, run_dir: Any = None) -> None:
        super().__init__(config, run_dir)  # seeds, run dir, self.env
        spec = AgentGroupSpec.from_env(self.env)
        if POSITION not in self.env.full_observation_spec_unbatched.keys(True):
            self.env.close()
            raise ValueError(
                f"svmix needs the agents' positions {POSITION} for its communication graph; "
                f"scenario {config.env!r} has none"
            )

        # modules: (observation normaliser ->) decentralised policy o_i -> pi_i; critic: the
        # sampled graph, per-agent values V_i(o_i), the graph mixer -> V_tot
        self.obs_norm, norm_module = make_obs_norm(spec) if config.normalize_obs else (None, None)
        obs_key = OBS if norm_module is None else OBS_NORM
        self.policy = make_stochastic_policy(
            spec, config.num_cells, config.share_params, obs_norm=norm_module
        )
        values = make_value_mlp(
            spec, config.num_cells, centralized=False, share_params=True, activation=nn.Tanh
        )
        mixer = GraphValueMixer(
            spec.obs_dim,
            hidden=config.gnn_hidden,
            layers=config.gnn_layers,
            embed=config.mixing_embed,
        )
        self.critic = TensorDictSequential(
            *([] if norm_module is None else [norm_module]),
            TensorDictModule(
                StochasticCommunicationGraph(config.comm.comm_range, config.comm.p_fail),
                in_keys=[POSITION, MASK],
                out_keys=[NEIGHBOURS],
            ),
            TensorDictModule(values, in_keys=[obs_key], out_keys=[VALUE]),
            TensorDictModule(
                mixer,
                in_keys=[VALUE, obs_key, NEIGHBOURS, MASK],
                out_keys=[JOINT_VALUE, CONTRIBUTION, MIXING_WEIGHT],
            ),
        )

        # collector (on-policy: the stochastic policy explores; evaluation takes its mode)
        self.collector = self.make_collector(self.policy)
        self.eval_policy = self.policy

        # buffer: the latest batch, minibatches without replacement
        self.buffer = config.latest_batch_buffer(self.device)

        # loss: GAE of the team reward on V_tot, clipped policy gradient, critic regression
        self.loss = SVMIXLoss(
            self.policy,
            self.critic,
            gamma=config.gamma,
            lmbda=config.lmbda,
            clip_epsilon=config.clip_epsilon,
            entropy_coeff=config.entropy_coeff,
            critic_coeff=config.critic_coeff,
            reward_scale=config.reward_scale,
            normalize_advantage=config.normalize_advantage,
        ).to(self.device)
        self.loss.set_keys(value=JOINT_VALUE)
        self.optim = torch.optim.Adam(self.loss.parameters(), lr=config.lr)

    def train_step(self, batch: TensorDictBase) -> dict[str, float]:
        """GAE along time on the batch [*, T] (each road its own sequence), then ``epochs``
        passes of minibatch updates of the policy and the mixed critic."""
        cfg = self.config
        batch = self.loss.value_targets(batch)
        steps = cfg.load_latest_batch(self.buffer, batch)
        keys = ("loss_objective", "loss_critic", "loss_entropy", "pred_value")
        logs = dict.fromkeys(keys, 0.0)
        for _ in range(steps):
            out = self.loss(self.buffer.sample())
            total = out["loss_objective"] + out["loss_critic"] + out["loss_entropy"]
            self.optim.zero_grad()
            total.backward()
            nn.utils.clip_grad_norm_(self.loss.parameters(), cfg.max_grad_norm)
            self.optim.step()
            for key in keys:
                logs[key] += out[key].item() / steps
        if self.obs_norm is not None:  # new statistics apply from the next batch on
            self.obs_norm.update(batch.get(OBS), batch.get(MASK, None))
        return logs

    def stateful_components(self) -> dict[str, Any]:
        return {"loss": self.loss, "optim": self.optim, "buffer": self.buffer}
