"""A scripted CAV policy scored on the evaluation episodes of a run: the reference a learned
policy has to beat (by default the scenario's own, on the freeway every CAV keeping its lane
under IDM)."""

from __future__ import annotations

import tempfile
from collections.abc import Callable
from typing import Any

from tensordict.nn import TensorDictModuleBase
from torchrl.envs import EnvBase

from mapets_rl.envs import ScriptedCAVPolicy
from mapets_rl.experiment.config import RunConfig
from mapets_rl.experiment.runner import Experiment, SystemRewardMetrics


class _ScriptedEvaluation(SystemRewardMetrics, Experiment):
    """An experiment that trains nothing; its evaluation policy is ``policy(self.env)``."""

    name = "scripted"
    Config = RunConfig

    def __init__(
        self,
        config: RunConfig,
        run_dir: Any,
        policy: Callable[[EnvBase], TensorDictModuleBase],
    ) -> None:
        super().__init__(config, run_dir)
        self.eval_policy = policy(self.env)

    def stateful_components(self) -> dict[str, Any]:
        return {}


def evaluate_scripted(
    config: RunConfig,
    policy: Callable[[EnvBase], TensorDictModuleBase] = ScriptedCAVPolicy,
) -> dict[str, float]:
    """Mean metrics of ``policy(env)`` (default :class:`~mapets_rl.envs.ScriptedCAVPolicy`; any
    factory of a module that writes ``("agents", "action")``) over the evaluation episodes
    of a run with ``config`` (its ``env``, ``env_config``, ``seed`` and ``eval_episodes``; any
    recipe's config): the runner re-seeds the evaluation env identically for every call, so
    these are the episodes that run's learned policy is scored on. The metrics are the
    recipes' (``return``, ``reward``, ``length``, ``system_return`` and the scenario's episode
    metrics). Nothing is written outside a temporary directory."""
    with tempfile.TemporaryDirectory(prefix="mapets_rl_scripted_") as tmp:
        return _ScriptedEvaluation(config, tmp, policy).evaluate()
