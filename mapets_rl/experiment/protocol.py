"""The evaluation protocol of a study: a run's greedy policy and named reference policies
scored on the same evaluation roads, the gain over each reference, the behaviour metrics.

On a scenario with a batched backend (the freeways) the policy plays one episode on each of
``roads`` roads of a batched env (``backend="torch"``, ``num_envs=roads``), the roads drawn
from the evaluation seed ``seed + ROAD_EVAL_SEED_OFFSET``: disjoint from the run's training
seeds (``seed + 7,919 k``, see :data:`~mapets_rl.experiment.runner.BOUNDARY_SEED_STRIDE`) and
the same for every policy of the run's seed, so a policy and its references drive the same
roads. Elsewhere (the figure-eights) it plays ``roads`` episodes of the run's evaluation env
(:meth:`Experiment.evaluate`, the same episodes for the references, played in place of the
run's ``eval_policy``).

The system reward of an episode is the CAVs' rewards summed over CAVs and steps (the same under
the team and the individual reward); the gain over a reference is
``100 * (mean system reward / the reference's - 1)`` percent. The behaviour metrics are the
scenario's episode metrics (ramp vehicles stuck, lane changes near the merge, forced merges,
shield interventions, collisions, ...), averaged over episodes.
"""

from __future__ import annotations

import dataclasses
import json
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tensordict.nn import TensorDictModuleBase
from torchrl.envs import EnvBase
from torchrl.envs.utils import ExplorationType, set_exploration_type

from mapets_rl.envs import build_env
from mapets_rl.envs.factory import has_batched_backend
from mapets_rl.envs.references import check_reference_names, make_reference, reference_names
from mapets_rl.experiment.config import MAX_EVAL_ROADS, RunConfig
from mapets_rl.experiment.files import atomic_write_text

ROAD_EVAL_SEED_OFFSET = 10_000
"""The evaluation roads of a run of seed ``s`` are drawn with seed ``s + 10,000`` (no multiple
of the training seeds' stride, 7,919, so never one of the run's training seeds)."""
PROTOCOL_FILE = "evaluation_protocol.json"
"""The protocol's result in a run directory."""


@dataclasses.dataclass(frozen=True)
class RoadScores:
    """The scores of one policy on the evaluation roads.

    Attributes:
        system_reward: ``[roads]`` per road (or episode), the CAVs' rewards summed over CAVs
            and steps.
        metrics: the scenario's episode metrics, each the mean over the episodes.
    """

    system_reward: np.ndarray
    metrics: dict[str, float]

    def mean(self) -> float:
        """The mean system reward per episode."""
        return float(np.mean(self.system_reward))

    def to_json(self) -> dict[str, Any]:
        return {
            "system_reward_mean": self.mean(),
            "system_reward": self.system_reward.tolist(),
            "metrics": self.metrics,
        }


def check_roads(roads: int) -> None:
    """ValueError naming ``roads`` unless it is an int in ``[1, MAX_EVAL_ROADS]``."""
    if isinstance(roads, bool) or not isinstance(roads, int) or not 1 <= roads <= MAX_EVAL_ROADS:
        raise ValueError(f"roads must be an integer in [1, {MAX_EVAL_ROADS}], got {roads!r}")


def evaluation_env(config: RunConfig, roads: int) -> EnvBase:
    """``roads`` roads of the batched backend of ``config``'s scenario, with the run's
    scenario settings (its ``env_config`` without the training's road count). The CAVs are
    paid their own rewards (``team_reward`` off): their sum, the system reward, is what the
    team reward shares out, and so every arm's references score the same to the last bit."""
    env_config = {**config.unbatched_env_config(), "backend": "torch", "num_envs": roads}
    if "team_reward" in env_config:
        env_config["team_reward"] = False
    return build_env(config.env, env_config)


@torch.no_grad()
def score_roads(
    config: RunConfig,
    policy: Callable[[EnvBase], TensorDictModuleBase],
    roads: int,
    exploration: ExplorationType = ExplorationType.DETERMINISTIC,
) -> RoadScores:
    """One episode of ``policy(env)`` on each of ``roads`` evaluation roads of ``config``'s
    scenario (batched backend, seed ``config.seed + ROAD_EVAL_SEED_OFFSET``), greedy unless
    ``exploration`` says otherwise."""
    check_roads(roads)
    env = evaluation_env(config, roads)
    try:
        actor = policy(env)
        env.set_seed(config.seed + ROAD_EVAL_SEED_OFFSET)
        td = env.reset()
        system = torch.zeros(roads, dtype=torch.float64)
        with set_exploration_type(exploration):
            for _ in range(int(env.config["horizon"])):
                td = env.step(actor(td))
                system += td.get(("next", "agents", "reward")).double().sum((-2, -1))
                td = td.get("next")
        episodes = env.pop_finished_episodes()
    finally:
        env.close()
    if len(episodes) != roads:
        raise RuntimeError(
            f"{len(episodes)} episodes ended on {roads} evaluation roads: the scenario's "
            "episodes must last its horizon"
        )
    metrics = {key: float(np.mean([e[key] for e in episodes])) for key in episodes[0]}
    return RoadScores(system.numpy(), metrics)


def _unbatched_scores(metrics: Mapping[str, float]) -> RoadScores:
    """The means of :meth:`Experiment.evaluate` as scores: the system return, or for a recipe
    that reports none (MA-PETS) the mean CAV return, which gives the same gains for a fixed
    number of CAVs."""
    metrics = dict(metrics)
    key = "system_return" if "system_return" in metrics else "return"
    if key not in metrics:
        raise ValueError(
            f"the evaluation reports no system_return or return (metrics: {', '.join(metrics)})"
        )
    system = np.array([metrics.pop(key)])
    return RoadScores(system, metrics)


def gain_percent(scores: RoadScores, reference: RoadScores) -> float:
    """``scores``' mean system reward over ``reference``'s on the same roads, in percent."""
    return float(100.0 * (scores.mean() / reference.mean() - 1.0))


def evaluate_protocol(
    exp: Any,
    roads: int,
    references: Sequence[str] = (),
    *,
    write: bool = True,
    reference_cache: dict[str, RoadScores] | None = None,
) -> dict[str, Any]:
    """Score the greedy policy of the experiment ``exp`` (its ``eval_policy``) and the
    reference policies named in ``references`` (empty: every one registered for the scenario)
    on the same ``roads`` evaluation roads (or episodes), both checked before any is played;
    returns, and with ``write`` writes atomically to ``run_dir/`` +
    :data:`PROTOCOL_FILE`: ``frames``, ``roads``, ``eval_seed``, ``batched``, ``policy`` and
    ``references`` (each :meth:`RoadScores.to_json`) and ``gain_percent`` (per reference).
    ``reference_cache`` (name -> scores, on the batched path) keeps the references' scores
    between calls of one run: they drive the same roads every time."""
    config = exp.config
    check_roads(roads)
    references = list(references) or reference_names(config.env)
    check_reference_names(config.env, references)
    batched = has_batched_backend(config.env)
    if batched:
        policy = score_roads(config, lambda env: exp.eval_policy, roads)
        cache = {} if reference_cache is None else reference_cache
        for name in references:
            if name not in cache:
                cache[name] = score_roads(config, _reference(config.env, name), roads)
        scored = {name: cache[name] for name in references}
        eval_seed = config.seed + ROAD_EVAL_SEED_OFFSET
    else:
        policy = _unbatched_scores(exp.evaluate(episodes=roads))
        scored = {name: _played_by(exp, _reference(config.env, name), roads) for name in references}
        eval_seed = None
    result = {
        "frames": int(exp.frames),
        "env": config.env,
        "seed": int(config.seed),
        "roads": roads,
        "batched": batched,
        "eval_seed": eval_seed,
        "policy": policy.to_json(),
        "references": {name: s.to_json() for name, s in scored.items()},
        "gain_percent": {name: gain_percent(policy, s) for name, s in scored.items()},
    }
    if write:
        atomic_write_text(Path(exp.run_dir) / PROTOCOL_FILE, json.dumps(result, indent=1))
    return result


def protocol_metrics(result: Mapping[str, Any]) -> dict[str, float]:
    """The flat metrics of a protocol result, as an evaluation logs them: ``system_return``
    (mean per episode), the policy's episode metrics and ``gain_vs_<reference>`` [%]."""
    return {
        "system_return": result["policy"]["system_reward_mean"],
        **result["policy"]["metrics"],
        **{
            f"gain_vs_{name.replace('-', '_')}": gain
            for name, gain in result["gain_percent"].items()
        },
    }


def _played_by(
    exp: Any, policy: Callable[[EnvBase], TensorDictModuleBase], episodes: int
) -> RoadScores:
    """The scores of ``policy(exp.env)`` on the episodes the run's own evaluation plays (the
    same env, re-seeded alike), its ``eval_policy`` put back afterwards."""
    trained = exp.eval_policy
    exp.eval_policy = policy(exp.env)
    try:
        return _unbatched_scores(exp.evaluate(episodes=episodes))
    finally:
        exp.eval_policy = trained


def _reference(scenario: str, name: str) -> Callable[[EnvBase], TensorDictModuleBase]:
    """The factory ``env -> reference policy name of scenario``."""
    return lambda env: make_reference(scenario, name, env)


def read_protocol(run_dir: str | Path) -> dict[str, Any] | None:
    """The protocol result written in ``run_dir`` (None when it has none)."""
    path = Path(run_dir) / PROTOCOL_FILE
    if not path.is_file():
        return None
    return json.loads(path.read_text())
