"""Traffic scenarios of the papers, as gymnasium, PettingZoo and TorchRL environments."""

from gymnasium.envs.registration import register, registry

from mapets_rl.envs.factory import SCENARIOS, make_env, make_parallel_env
from mapets_rl.envs.figure_eight import (
    FigureEightEnv,
    figure_eight_collision,
    figure_eight_reward,
)
from mapets_rl.envs.freeway import ACTION_NAMES, FreewayEnv
from mapets_rl.envs.parallel import FigureEightParallelEnv, FreewayParallelEnv, TrafficParallelEnv
from mapets_rl.envs.scripted import ScriptedCAVPolicy, traffic_env

__all__ = [
    "ACTION_NAMES",
    "SCENARIOS",
    "ScriptedCAVPolicy",
    "FigureEightEnv",
    "FigureEightParallelEnv",
    "FreewayEnv",
    "FreewayParallelEnv",
    "TrafficParallelEnv",
    "figure_eight_collision",
    "figure_eight_reward",
    "make_env",
    "make_parallel_env",
    "traffic_env",
]

_IDS = {
    "mapets_rl/FigureEight-v0": ("mapets_rl.envs.figure_eight:FigureEightEnv", {}),
    "mapets_rl/FigureEightMultiLane-v0": (
        "mapets_rl.envs.figure_eight:FigureEightEnv",
        {"config": {"lanes": 2, "n_cavs": 22, "horizon": 400}},
    ),
    "mapets_rl/Freeway-v0": ("mapets_rl.envs.freeway:FreewayEnv", {}),
}
for _id, (_entry, _kwargs) in _IDS.items():
    if _id not in registry:
        register(id=_id, entry_point=_entry, kwargs=_kwargs)
