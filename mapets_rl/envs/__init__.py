"""Traffic scenarios of the papers, as gymnasium, PettingZoo and TorchRL environments."""

from gymnasium.envs.registration import register, registry

from mapets_rl.envs.factory import (
    SCENARIOS,
    TrafficPettingZooWrapper,
    make_env,
    make_parallel_env,
    wrap_parallel_env,
)
from mapets_rl.envs.figure_eight import (
    FigureEightEnv,
    figure_eight_collision,
    figure_eight_observation_bounds,
    figure_eight_reward,
)
from mapets_rl.envs.freeway import ACTION_NAMES, FreewayEnv
from mapets_rl.envs.freeway_merge import FreewayMergeEnv, FreewayMergeParallelEnv
from mapets_rl.envs.parallel import FigureEightParallelEnv, FreewayParallelEnv, TrafficParallelEnv
from mapets_rl.envs.scripted import ScriptedCAVPolicy, traffic_env
from mapets_rl.envs.traffic import MultiAgentTrafficEnv

__all__ = [
    "ACTION_NAMES",
    "GYM_IDS",
    "SCENARIOS",
    "ScriptedCAVPolicy",
    "FigureEightEnv",
    "FigureEightParallelEnv",
    "FreewayEnv",
    "FreewayMergeEnv",
    "FreewayMergeParallelEnv",
    "FreewayParallelEnv",
    "MultiAgentTrafficEnv",
    "TrafficParallelEnv",
    "TrafficPettingZooWrapper",
    "figure_eight_collision",
    "figure_eight_observation_bounds",
    "figure_eight_reward",
    "make_env",
    "make_parallel_env",
    "traffic_env",
    "wrap_parallel_env",
]

GYM_IDS = {
    "figure-eight": "mapets_rl/FigureEight-v0",
    "figure-eight-multilane": "mapets_rl/FigureEightMultiLane-v0",
    "freeway": "mapets_rl/Freeway-v0",
    "freeway-merge": "mapets_rl/FreewayMerge-v0",
}
"""Scenario name -> gymnasium id of its raw (array-valued) highway-env environment."""

for _name, _id in GYM_IDS.items():
    if _id not in registry:
        _cls = SCENARIOS[_name][0].env_class
        register(
            id=_id,
            entry_point=f"{_cls.__module__}:{_cls.__name__}",
            kwargs={"config": dict(SCENARIOS[_name][1])},
        )
