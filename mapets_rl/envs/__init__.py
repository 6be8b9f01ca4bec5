"""Traffic scenarios of the papers, as gymnasium, PettingZoo and TorchRL environments, and the
scenario registry (:mod:`mapets_rl.envs.registry`) that every part of the library looks
scenarios up in."""

from types import MappingProxyType

import pettingzoo
from gymnasium.envs import registration

from mapets_rl.envs.factory import make_env, make_parallel_env
from mapets_rl.envs.figure_eight import (
    FigureEightEnv,
    FigureEightPlannerReward,
    figure_eight_observation_bounds,
)
from mapets_rl.envs.freeway import ACTION_NAMES, FreewayEnv
from mapets_rl.envs.freeway_merge import FreewayMergeEnv, FreewayMergeParallelEnv
from mapets_rl.envs.highway_multi_agent import (
    HighwayMergePlannerReward,
    HighwayMultiAgentParallelEnv,
    HighwayPlannerReward,
)
from mapets_rl.envs.parallel import FigureEightParallelEnv, FreewayParallelEnv, TrafficParallelEnv
from mapets_rl.envs.pettingzoo_wrapper import (
    AgentsPettingZooWrapper,
    TrafficPettingZooWrapper,
    wrap_parallel_env,
    wrap_pettingzoo,
)
from mapets_rl.envs.planner_reward import PlannerReward
from mapets_rl.envs.registry import (
    Scenario,
    available_envs,
    build_env,
    builtin_envs,
    register_env,
    registered_scenario,
    scenario_defaults,
)
from mapets_rl.envs.scripted import ScriptedCAVPolicy, scenario_config, traffic_env
from mapets_rl.envs.traffic import MultiAgentTrafficEnv

__all__ = [
    "ACTION_NAMES",
    "AgentsPettingZooWrapper",
    "GYM_IDS",
    "Scenario",
    "ScriptedCAVPolicy",
    "FigureEightEnv",
    "FigureEightParallelEnv",
    "FreewayEnv",
    "FreewayMergeEnv",
    "FreewayMergeParallelEnv",
    "FreewayParallelEnv",
    "HighwayMultiAgentParallelEnv",
    "HighwayMergePlannerReward",
    "HighwayPlannerReward",
    "MultiAgentTrafficEnv",
    "TrafficParallelEnv",
    "TrafficPettingZooWrapper",
    "available_envs",
    "build_env",
    "builtin_envs",
    "FigureEightPlannerReward",
    "PlannerReward",
    "figure_eight_observation_bounds",
    "make_env",
    "make_parallel_env",
    "register_env",
    "registered_scenario",
    "scenario_config",
    "scenario_defaults",
    "traffic_env",
    "wrap_parallel_env",
    "wrap_pettingzoo",
]

GYM_IDS = MappingProxyType({name: registered_scenario(name).gym_id for name in builtin_envs()})
"""Built-in scenario name -> gymnasium id of its raw (array-valued) highway-env environment
(derived from the scenario registry when ``mapets_rl.envs`` is imported). The same ids name the
scenarios' PettingZoo ``ParallelEnv`` in PettingZoo's registry:
``pettingzoo.make("parallel", "mapets_rl/Freeway-v0", n_vehicles=10)``."""

for _name, _id in GYM_IDS.items():
    _scenario = registered_scenario(_name)
    _parallel = _scenario.parallel_env
    if _id not in registration.registry:
        registration.register(
            id=_id,
            entry_point=f"{_parallel.env_class.__module__}:{_parallel.env_class.__name__}",
            kwargs={"config": dict(_scenario.changes)},
        )
    if _id not in pettingzoo.parallel_registry:
        pettingzoo.register(
            "parallel",
            _id,
            entry_point=f"{_parallel.__module__}:{_parallel.__name__}",
            kwargs=dict(_scenario.changes),
        )
