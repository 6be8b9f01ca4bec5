"""Building blocks that the recipes share (as torchrl's ``modules``): the ``"agents"`` group's
keys and spec, the masked mean over driving agents, running observation normalisation, one-hot
action heads (greedy and Gumbel-softmax), epsilon-greedy exploration over some actions, the
baselines' stochastic policy and tile coding (MA-PETS's discretised variant).

Recipes import these from here, never from each other."""

from mapets_rl.modules.agents import AgentGroupSpec, masked_mean
from mapets_rl.modules.exploration import restricted_epsilon_greedy
from mapets_rl.modules.heads import GumbelSoftmaxHead, gumbel_one_hot, one_hot_argmax
from mapets_rl.modules.keys import (
    ACTION,
    ACTION_VALUE,
    DONE,
    GROUP,
    LOG_PROB,
    LOSS_KEYS,
    MASK,
    OBS,
    OBS_ACTION,
    OBS_NORM,
    Q_VALUE,
    REWARD,
    TERMINATED,
    TRANSITION_KEYS,
    VALUE,
)
from mapets_rl.modules.normalization import RunningObsNorm, make_obs_norm, sync_target_statistics
from mapets_rl.modules.policies import (
    concat_last,
    make_decentralised_mlp,
    make_discrete_actor,
    make_q_critic,
    make_stochastic_policy,
    make_value_mlp,
)
from mapets_rl.modules.tile_coding import (
    TileCodedObservation,
    TileCoder,
    TileCodingConfig,
    action_quantiser,
)

__all__ = [
    "ACTION",
    "ACTION_VALUE",
    "DONE",
    "GROUP",
    "LOG_PROB",
    "LOSS_KEYS",
    "MASK",
    "OBS",
    "OBS_ACTION",
    "OBS_NORM",
    "Q_VALUE",
    "REWARD",
    "TERMINATED",
    "TRANSITION_KEYS",
    "VALUE",
    "AgentGroupSpec",
    "GumbelSoftmaxHead",
    "RunningObsNorm",
    "TileCodedObservation",
    "TileCoder",
    "TileCodingConfig",
    "action_quantiser",
    "concat_last",
    "gumbel_one_hot",
    "make_obs_norm",
    "make_decentralised_mlp",
    "make_discrete_actor",
    "make_q_critic",
    "make_stochastic_policy",
    "make_value_mlp",
    "restricted_epsilon_greedy",
    "masked_mean",
    "one_hot_argmax",
    "sync_target_statistics",
]
