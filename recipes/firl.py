"""FIRL (Xu, Li, Zhao, Zhang, "Communication-efficient consensus mechanism for federated
reinforcement learning", IEEE ICC 2022, arXiv 2201.12718), the MA-PETS paper's ``FIRL [33]``:
independent learners in the federated paradigm.

config -> env -> modules (per-agent policy and per-agent value, each agent's parameters its own,
stacked along the agent dimension of a ``MultiAgentMLP`` with ``share_params=False``) ->
collector -> buffer (the last batch, minibatches without replacement) -> loss (torchrl
``IPPOLoss``, ``MultiAgentGAE``) -> each local update: backward, consensus of the local
gradients over the range-``d`` graph with link failures, per-agent gradient clip, Adam step; every
``averaging_period`` local updates the server averages the parameters
(:class:`~mapets_rl.comm.FederatedConsensus`) -> loop (shared ``Experiment.train``).

Base learner: PPO, one per agent (IPPO). The ICC paper's abstract says "independent
reinforcement learning (IRL) ... in the paradigm of federated learning" without naming the
learner; its journal version (arXiv 2103.13026, same authors, same consensus scheme) builds on
"the policy-based DRL algorithm (i.e., proximal policy optimization (PPO))", and the MA-PETS
paper's Table IV puts FIRL's decision time next to MAPPO's (7.6 against 8.0 x 1e-2 s), as a
policy network of the same size would.

What is not public (only the abstracts are) and chosen here, each a config field: the
consensus weights (Metropolis-Hastings on the graph of the batch's last step, see
:mod:`mapets_rl.comm.consensus`), ``consensus_rounds`` per local update (1), the
``averaging_period`` in local updates (10), that Adam's moments stay local (the server averages
parameters only), and the graph's range and link failures (``comm.comm_range`` 100 m as
MA-PETS's d, ``comm.p_fail`` 0). The communication is counted like MA-PETS's sharing: per
collected batch (one episode's worth of steps with the shipped configs, ``frames_per_batch``
= the horizon) ``bytes_consensus``, ``bytes_averaging`` and their sum ``bytes_shared``.

Observations are standardised with running statistics pooled over the agents' data, as in
every baseline (``normalize_obs``); these two ``obs_dim`` vectors are not counted as
communication.
"""

from __future__ import annotations

import dataclasses

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModule, TensorDictSequential
from torch import nn
from torchrl.objectives import ValueEstimators
from torchrl.objectives.multiagent import IPPOLoss

from mapets_rl.comm import CommConfig, FederatedConsensus
from mapets_rl.comm.consensus import (
    average_agents,
    set_stacked_gradients,
    stacked_gradients,
)
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
    make_decentralised_mlp,
    make_obs_norm,
    make_stochastic_policy,
)

LOSS_TERMS = ("loss_objective", "loss_critic", "loss_entropy")


@dataclasses.dataclass
class FIRLConfig(OnPolicyConfig):
    """FIRL hyper-parameters; the shared on-policy fields (``lr``, ``gamma``, ``lmbda``,
    ``epochs``, ``minibatch_size``, ``max_grad_norm`` (per agent), ``num_cells`` (policy and
    value)) are those of :class:`~mapets_rl.experiment.training.OnPolicyConfig`.

    Attributes:
        share_params: must stay ``False``: every learner keeps its own parameters (the
            averaging shares them, periodically).
        clip_epsilon, entropy_coeff, critic_coeff, normalize_obs: as ``mappo``'s.
        comm: the graph of the consensus (``comm_range`` d in metres, ``p_fail`` the link
            failure probability; ``share_plans`` must stay off: FIRL shares no plans).
        consensus_rounds: gradient-exchange rounds with the neighbours per local update (>= 0;
            0: periodic averaging alone, plain federated averaging).
        averaging_period: local updates between the server's parameter averagings (>= 1).

    One road per run (no ``env_config.num_envs``, ``collector_workers = 1``): learner ``i``
    drives CAV ``i``, and the consensus graph is that road's.
    """

    share_params: bool = False
    clip_epsilon: float = 0.2
    entropy_coeff: float = 0.01
    critic_coeff: float = 1.0
    normalize_obs: bool = True
    comm: CommConfig = dataclasses.field(default_factory=CommConfig)
    consensus_rounds: int = 1
    averaging_period: int = 10

    def __post_init__(self) -> None:
        super().__post_init__()
        check(
            not self.share_params,
            "share_params",
            "false (FIRL's learners are independent; averaging_period shares them)",
            self.share_params,
        )
        check(self.clip_epsilon > 0, "clip_epsilon", "> 0", self.clip_epsilon)
        check(self.entropy_coeff >= 0, "entropy_coeff", ">= 0", self.entropy_coeff)
        check(self.critic_coeff > 0, "critic_coeff", "> 0", self.critic_coeff)
        check(
            not self.comm.share_plans,
            "comm.share_plans",
            "false (FIRL exchanges gradients and parameters, no plans)",
            self.comm.share_plans,
        )
        one_road = "(firl's learner i drives CAV i of one road, whose graph the consensus uses)"
        check(
            self.env_batch_size is None,
            "env_config.num_envs",
            f"left out {one_road}",
            self.env_batch_size,
        )
        check(
            self.collector_workers == 1,
            "collector_workers",
            f"1 {one_road}",
            self.collector_workers,
        )
        check(self.consensus_rounds >= 0, "consensus_rounds", ">= 0", self.consensus_rounds)
        check(self.averaging_period >= 1, "averaging_period", ">= 1", self.averaging_period)


class FIRL(Experiment):
    """Independent PPO learners with gradient consensus over the communication graph and
    periodic parameter averaging, on any scenario whose agents report a position."""

    name = "firl"
    Config = FIRLConfig

    def __init__(self, config: FIRLConfig, run_dir=None) -> None:
        super().__init__(config, run_dir)  # seeds, run dir, self.env
        spec = AgentGroupSpec.from_env(self.env)
        position = ("agents", "position")
        if position not in self.env.full_observation_spec.keys(True, True):
            self.env.close()
            raise ValueError(
                f"firl needs the agents' positions {position} for its communication graph; "
                f"env {config.env!r} reports none"
            )

        # modules: (observation normaliser ->) per-agent policy pi_i(a | o_i) and value V_i(o_i)
        self.obs_norm, norm_module = make_obs_norm(spec) if config.normalize_obs else (None, None)
        self.policy = make_stochastic_policy(
            spec, config.num_cells, share_params=False, obs_norm=norm_module
        )
        self.critic = TensorDictModule(
            make_decentralised_mlp(spec, config.num_cells, False, n_out=1, activation=nn.Tanh),
            in_keys=[OBS if norm_module is None else OBS_NORM],
            out_keys=[VALUE],
        )
        if norm_module is not None:
            self.critic = TensorDictSequential(norm_module, self.critic)

        # collector (on-policy: the stochastic policy explores; evaluation takes its mode)
        self.collector = self.make_collector(self.policy)
        self.eval_policy = self.policy

        # buffer: the latest batch, minibatches without replacement
        self.buffer = config.latest_batch_buffer(self.device)

        # loss: each agent's clipped surrogate + value + entropy on its own data (IPPO)
        self.loss = IPPOLoss(
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

        # the federation: every learner starts from the same parameters (the server's first
        # broadcast, not counted), then consensus and periodic averaging
        self.federation = FederatedConsensus(
            list(self.loss.parameters()),
            config.comm.comm_range,
            config.comm.p_fail,
            config.consensus_rounds,
            config.averaging_period,
            seed=config.seed,
        )
        average_agents(self.federation.params)

    def train_step(self, batch: TensorDictBase) -> dict[str, float]:
        """GAE along time on the batch ``[T]``, then ``epochs`` passes of minibatch updates,
        each a local update of every learner with the consensus of its gradient (on the graph
        of the batch's last step) and, when due, the server's averaging."""
        with torch.no_grad():
            self.loss.value_estimator(
                batch,
                params=self.loss.critic_network_params,
                target_params=self.loss.target_critic_network_params,
            )
        logs = dict.fromkeys((*LOSS_TERMS, "bytes_consensus", "bytes_averaging"), 0.0)
        steps = self.config.load_latest_batch(self.buffer, batch)
        for _ in range(steps):
            out = self.loss(self.buffer.sample())
            self.optim.zero_grad()
            sum(out[key] for key in LOSS_TERMS).backward()
            logs["bytes_consensus"] += self.federation.local_update(batch)["bytes_consensus"]
            self._clip_per_agent()
            self.optim.step()
            logs["bytes_averaging"] += self.federation.after_step()["bytes_averaging"]
            for key in LOSS_TERMS:
                logs[key] += out[key].item() / steps
        logs["bytes_shared"] = logs["bytes_consensus"] + logs["bytes_averaging"]
        if self.obs_norm is not None:  # new statistics apply from the next batch on
            self.obs_norm.update(batch.get(OBS), batch.get(MASK, None))
        return logs

    def _clip_per_agent(self) -> None:
        """Clip each learner's whole gradient to norm ``max_grad_norm`` (one norm per agent,
        so no learner's step depends on another's gradient size)."""
        params = self.federation.params
        grads = stacked_gradients(params)  # [I, P]
        norms = torch.linalg.vector_norm(grads, dim=1, keepdim=True)
        scale = (self.config.max_grad_norm / (norms + 1e-6)).clamp(max=1.0)
        set_stacked_gradients(params, grads * scale)

    def stateful_components(self) -> dict:
        return {
            "loss": self.loss,
            "optim": self.optim,
            "buffer": self.buffer,
            "federation": self.federation,
        }
