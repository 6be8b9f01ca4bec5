"""The scenario's scripted CAV policy scored on the evaluation episodes of a run: the reference
a learned policy has to beat (on the freeway, every CAV keeping its lane under IDM)."""

from __future__ import annotations

import tempfile
from typing import Any

from mapets_rl.envs import ScriptedCAVPolicy
from mapets_rl.experiment.config import RunConfig
from mapets_rl.experiment.runner import Experiment, SystemRewardMetrics


class _ScriptedEvaluation(SystemRewardMetrics, Experiment):
    """An experiment that trains nothing; its evaluation policy is the scripted one."""

    name = "scripted"
    Config = RunConfig

    def __init__(self, config: RunConfig, run_dir: Any) -> None:
        super().__init__(config, run_dir)
        self.eval_policy = ScriptedCAVPolicy(self.env)

    def stateful_components(self) -> dict[str, Any]:
        return {}


def evaluate_scripted(config: RunConfig) -> dict[str, float]:
    """Mean metrics of :class:`~mapets_rl.envs.ScriptedCAVPolicy` over the evaluation episodes
    of a run with ``config`` (its ``env``, ``env_config``, ``seed`` and ``eval_episodes``; any
    recipe's config): the runner re-seeds the evaluation env identically for every call, so
    these are the episodes that run's learned policy is scored on. The metrics are the
    recipes' (``return``, ``reward``, ``length``, ``system_return`` and the scenario's episode
    metrics). Nothing is written outside a temporary directory."""
    with tempfile.TemporaryDirectory(prefix="mapets_rl_scripted_") as tmp:
        return _ScriptedEvaluation(config, tmp).evaluate()
