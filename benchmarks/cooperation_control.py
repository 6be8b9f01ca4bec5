"""The positive control of the Shapley paper's claim (issue 32): with the ideal credit signal
(``team_reward``: every CAV is paid the CAVs' mean reward), can a learner find the cooperative
merge on ``freeway-merge`` at all?

Each variant is one controlled change (or one more) from the baseline: MADDPG with the
openai/maddpg schedule (``mapets_rl.recipes.maddpg.OPENAI_MADDPG``), the team reward, 30 CAVs
(ratio 1), trained on the batched freeway (``backend=torch``). The changes:

- ``epsilon``: epsilon-greedy exploration among Keep Lane / Change Left / Change Right (no
  random emergency stop), epsilon annealed 1 -> 0.05 over ``--anneal-frames``, instead of the
  Gumbel-softmax samples (which brake 21-25% of the time while the logits are flat);
- ``shield``: the model-predictive shield of the torch backend (``env_config.shield``: a lane
  change or stop that a copy of the road predicts to crash within 3 s is replaced by Keep Lane),
  in training and in evaluation;
- ``gamma99``: gamma 0.99 and 5-step returns (the gain of a yield comes steps later);
- ``w1``: a change of the task, not of the learner: the velocity weight ``w`` of the reward
  (eq. 10, ``w * velocity + comfort``) 1.0 instead of 0.1, so that a ramp vehicle left standing
  costs about ten times more against the one step of comfort a yield costs (the scripted rows
  are scored with the same reward);
- ``individual``: the credit question, once a learner can find the merge: every CAV is paid
  its own reward (``team_reward=false``, the Shapley paper's MADDPG baseline) instead of the
  team's;
- ``shared``: one critic network shared by all CAVs instead of one per CAV (MADDPG's default
  until 2026-11-27, which gives every CAV the same Q, the mean of their returns: under the
  individual reward the team's value). The MADDPG rows measured before then were trained this
  way: their variants with ``_shared`` reproduce them;
- ``shapley``: the Shapley actor-critic (the paper's method) instead of MADDPG, with the same
  schedule, networks and changes (:data:`SHAPLEY_SCHEDULE`), paid the individual rewards that
  it reallocates by Shapley value;
- ``uniform`` (Shapley AC): a timestep's coalition drawn with a size uniform over 1..n, then
  its members (``coalition_sizes=uniform``), instead of every CAV joining with probability 1/2:
  the critic is trained at every size at which the permutation estimate reads it, the singletons
  included; ``reg``: the actor's logits penalty of the recipe (0.1) instead of openai's 1e-3;
  ``embed``: a 64-wide nonlinear layer per CAV in the coalition critic before the members are
  summed (``critic_embed_cells=[64]``), so that its head sees each member's state and action
  together; ``member``: one critic output per CAV, ``v(C)`` their sum over the members, each
  fitted to its own member's reward (``critic_member_heads=true``) instead of one output fitted
  to the coalition's summed reward;
- ``mappo``: MAPPO (GAE, gamma 0.99) with the team reward, the on-policy reference, one PPO
  update per 40 steps of every road; ``short``: one per 4 steps (10x the updates);
- ``coma``: COMA (TD(lambda) critic on the team reward, counterfactual advantage, gamma 0.99),
  the paper's other comparator, on MAPPO's schedule of batches (``short`` alike).

Every trained policy is scored greedily on ``--eval-roads`` roads of the same evaluation seeds
as the scripted keep-lane policy and the cooperative merge rule
(``benchmarks/freeway_headroom.py``'s ``CooperativeMerge``), each with the variant's shield and
reward settings. The system reward of a road is the CAVs' rewards summed over CAVs and the 40 steps
(the same under the team and the individual reward).

``--explored`` adds, for each epsilon variant, the scores of its final collection policy
(greedy plus the last epsilon of random moves), to tell a policy that merges only when its
co-players are perturbed from one that does not merge, and keep lane with random moves at the
variant's ``epsilon_end`` (what the moves alone give, once epsilon has annealed).

``--score-every FRAMES`` also scores each run's greedy policy every ``FRAMES`` training frames
(a table per variant: gain over keep lane per seed and stage): the run trains in stages of
``FRAMES``, each resumed from the last one's checkpoint, and keeps one checkpoint on disk. A
new run then checkpoints every ``FRAMES`` frames, so the stages are exactly one uninterrupted
run with that checkpoint interval (the collector restarts its episodes at every checkpoint).
Does a greedy policy settle, or swing between checkpoints while its training return holds? A
stage that a run had gone past before it was asked for is marked ``-``.

Run (resumable: finished runs and every evaluation, scripted ones included, are kept under
``--out``):

    OMP_NUM_THREADS=1 python benchmarks/cooperation_control.py \\
        --variants maddpg maddpg_epsilon maddpg_shield maddpg_epsilon_shield mappo \\
        --seeds 0 1 2 3 4 --frames 400000 --out outputs/cooperation_control

Prints a markdown table (per variant: system reward relative to keep-lane, per seed and mean
with a bootstrap 95% interval over seeds; ramp vehicles stuck, collisions, shield
interventions, comfort and the CAVs' lane changes between mainline lanes near the merge and
elsewhere, per episode), then per variant the training episodes
(``train_episodes.jsonl``) in windows of ``--window-frames``: when, in training, the merge
appears. Writes them with the per-seed numbers to ``<out>/control.md`` and
``<out>/control.json``.
"""

from __future__ import annotations

import argparse
import json
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import torch
from freeway_headroom import CooperativeMerge
from tensordict.nn import TensorDictModuleBase, TensorDictSequential
from torchrl.envs import EnvBase
from torchrl.envs.utils import ExplorationType, set_exploration_type

from mapets_rl.app.plugins import load_recipe
from mapets_rl.envs import FreewayMergeEnv, ScriptedCAVPolicy, make_env
from mapets_rl.envs.torch_freeway.simulator import BatchedFreeway
from mapets_rl.experiment import (
    atomic_write_text,
    checkpoint_frames,
    latest_checkpoint,
    read_train_episodes,
)
from mapets_rl.machine import machine_line
from mapets_rl.modules.exploration import restricted_epsilon_greedy
from mapets_rl.recipes.maddpg import OPENAI_MADDPG
from mapets_rl.statistics import bootstrap_interval

ENV = "freeway-merge"
CHECKPOINT_FRAMES = 100_000
"""A run checkpoints at least this often, so that a stopped run resumes close to where it was
(one 1M-frame Shapley seed takes hours)."""
EVAL_SEED_OFFSET = 10_000
"""Evaluation roads are drawn with seed ``EVAL_SEED_OFFSET + seed``: the same for every
variant and the scripted rules."""

CHANGES: dict[str, list[str]] = {
    "epsilon": ["exploration=epsilon", "exploration_actions=[0, 1, 2]"],
    "shield": ["env_config.shield=true"],
    "gamma99": ["gamma=0.99", "n_steps=5"],
    "w1": ["env_config.velocity_weight=1.0"],
    "individual": ["env_config.team_reward=false"],
    "shared": ["critic_share_params=true"],
    "uniform": ["coalition_sizes=uniform"],
    "reg": ["logits_reg=0.1"],
    "embed": ["critic_embed_cells=[64]"],
    "member": ["critic_member_heads=true"],
}
"""The controlled changes, as config overrides (``uniform``, ``reg``, ``embed`` and ``member`` are
Shapley AC's)."""
RECIPES = {"maddpg": "maddpg", "shapley": "shapley_ac", "mappo": "mappo", "coma": "coma"}
"""A variant's first word and the recipe it trains."""
SHAPLEY_SCHEDULE: tuple[str, ...] = (
    "critic_cells=[64, 64]",
    "logits_reg=0.001",
    "num_permutations=8",
    "shapley_chunk_states=32",
    "shapley_bf16=true",
)
"""What the Shapley arm sets beyond the openai schedule: its critic and its logits penalty as
MADDPG's (openai's 2x64 networks, ``p_reg`` 1e-3), so that the two differ in the credit only,
and the Shapley estimate that one core affords at 1M frames (4 antithetic pairs of orderings per
minibatch, bf16 autocast: about 0.7 s per update here, against 2.4 s at the recipe's 32
orderings in fp32)."""
RECIPE_CHANGES: dict[str, tuple[str, ...]] = {
    "maddpg": ("epsilon", "shield", "gamma99", "w1", "individual", "shared"),
    "shapley": ("epsilon", "shield", "w1", "uniform", "reg", "embed", "member"),
    "mappo": ("shield", "short", "w1"),
    "coma": ("shield", "short", "w1"),
}
"""The controlled changes of each recipe (MAPPO's and COMA's ``short``: ``frames_per_batch`` of
4 steps per road; Shapley AC is always paid the individual rewards it reallocates and has no n-step
targets)."""


def variant_overrides(variant: str, args: argparse.Namespace) -> tuple[str, list[str]]:
    """The recipe and config overrides of ``variant`` (``maddpg[_change...]``,
    ``shapley[_change...]``, ``mappo[_change...]`` or ``coma[_change...]``); ValueError naming
    the variant otherwise."""
    token, *changes = variant.split("_")
    recipe = RECIPES.get(token)
    if recipe is None or any(c not in RECIPE_CHANGES[token] for c in changes):
        raise ValueError(
            f"--variants: {variant!r} is not "
            + " or ".join(f"{t}[_{'|_'.join(RECIPE_CHANGES[t])}...]" for t in RECIPES)
        )
    roads = args.train_roads
    overrides = [
        "env_config.backend=torch",
        f"env_config.num_envs={roads}",
        f"env_config.n_vehicles={args.n_vehicles}",
        "env_config.cav_ratio=1.0",
        # Shapley AC reallocates the CAVs' own rewards (the paper's setting)
        f"env_config.team_reward={'false' if token == 'shapley' else 'true'}",
        f"total_frames={args.frames}",
        f"eval_interval={args.frames}",
        f"checkpoint_interval={min(max(args.frames // 4, 1), CHECKPOINT_FRAMES)}",
        "logger=csv",
        "progress=false",
        "keep_last=1",
    ]
    if token in ("maddpg", "shapley"):
        overrides += [*OPENAI_MADDPG, f"frames_per_batch={4 * roads}"]
        overrides.append(f"epsilon_anneal_frames={args.anneal_frames}")
        if token == "shapley":
            overrides += SHAPLEY_SCHEDULE
    else:
        batch = (4 if "short" in changes else 40) * roads
        minibatch = min(load_recipe(recipe).Config.minibatch_size, batch)
        overrides += [f"frames_per_batch={batch}", f"minibatch_size={minibatch}", "gamma=0.99"]
    for change in changes:
        overrides += CHANGES.get(change, [])  # "short" is the on-policy frames_per_batch
    # a change replaces the base's value of its key (gamma99's gamma=0.99 the schedule's 0.95)
    by_key = {item.split("=", 1)[0]: item for item in overrides}
    return recipe, list(by_key.values())


def env_settings(variant: str) -> dict[str, Any]:
    """The scenario settings that ``variant`` changes (``shield``, ``velocity_weight``): the
    scripted references it is compared with are scored with the same ones."""
    changes = variant.split("_")[1:]
    settings: dict[str, Any] = {"shield": "shield" in changes}
    if "w1" in changes:
        settings["velocity_weight"] = 1.0
    return settings


def settings_label(settings: dict[str, Any]) -> str:
    """``", shield, w=1.0"``-style suffix of a scripted row (empty for the base scenario)."""
    parts = ["shield"] if settings.get("shield") else []
    if "velocity_weight" in settings:
        parts.append(f"w={settings['velocity_weight']}")
    return "".join(f", {p}" for p in parts)


def train(variant: str, seed: int, args: argparse.Namespace, frames: int) -> tuple[Path, int]:
    """Train (or go on training) one run until it has done ``frames`` frames; returns its run
    directory and the frames it has done (a run that had done more already is left as it is;
    whole batches: a few more than ``frames``)."""
    recipe, overrides = variant_overrides(variant, args)
    cls = load_recipe(recipe)
    run_dir = Path(args.out) / "runs" / f"{variant}_seed{seed}"
    latest = latest_checkpoint(run_dir)
    if latest is not None:
        done = checkpoint_frames(latest)  # from its name: no checkpoint loaded to ask
        if done >= frames:
            return run_dir, done
        exp = cls.from_run_dir(run_dir, overrides=[f"total_frames={frames}"])
    else:
        # staged (--score-every): a checkpoint at every stage, as a resumed stage makes one
        # (the collector restarts its episodes at each), so the stages are one uninterrupted run
        budget = {"total_frames": frames}
        if args.score_every:
            budget["checkpoint_interval"] = args.score_every
        kept = [o for o in overrides if o.split("=", 1)[0] not in budget]
        config = cls.Config(env=ENV, seed=seed).with_overrides(
            [*kept, *(f"{key}={value}" for key, value in budget.items())]
        )
        exp = cls(config, run_dir)
    exp.train()
    return run_dir, exp.frames


def score_stages(frames: int, every: int) -> list[int]:
    """The training frames at which a run's greedy policy is scored: every ``every`` frames
    (``--score-every``; 0: none) and at the end, ``frames``."""
    return [*range(every, frames, every), frames] if every else [frames]


NEAR_MERGE = 100.0
"""A mainline lane change counts as near the merge from this many metres before the
acceleration lane to its end (the cooperative rule's yields happen there)."""
BEHAVIOUR = ("mainline_changes_near_merge", "mainline_changes_elsewhere")
"""The per-episode behaviour counts of :func:`score` (a cached score without them is stale)."""


def cav_lanes(sim: BatchedFreeway) -> tuple[torch.Tensor, torch.Tensor]:
    """The lane ids and x [m] of the CAVs of the batched freeway, ``[roads, CAVs]`` each."""
    slot = sim.state["agents"].get("slot")
    bodies = sim.state["bodies"]
    return bodies.get("lane").gather(1, slot), bodies.get("x").gather(1, slot)


def on_mainline(sim: BatchedFreeway, lane: torch.Tensor) -> torch.Tensor:
    """bool, shaped like ``lane`` (lane ids): the lane is a mainline lane, not the ramp's."""
    return sim.geometry.table[lane] != sim.geometry.ramp_table


def near_merge(sim: BatchedFreeway, x: torch.Tensor) -> torch.Tensor:
    """bool, shaped like ``x`` [m]: from :data:`NEAR_MERGE` metres before the acceleration lane
    to its end."""
    geometry = sim.geometry
    return (x >= geometry.merge_start - NEAR_MERGE) & (x <= geometry.merge_end)


def mainline_change(sim: BatchedFreeway, before: torch.Tensor, after: torch.Tensor) -> torch.Tensor:
    """bool ``[roads, CAVs]``: the CAV moved from one mainline lane to another (a merge from
    the acceleration lane is not counted)."""
    return (before != after) & on_mainline(sim, before) & on_mainline(sim, after)


def evaluation_env(roads: int, n_vehicles: int, settings: dict[str, Any]) -> EnvBase:
    """``roads`` roads of the batched freeway-merge with ``n_vehicles`` vehicles, all CAVs,
    the scenario changed by ``settings`` (:func:`env_settings` and other config keys)."""
    return make_env(
        ENV, backend="torch", num_envs=roads, n_vehicles=n_vehicles, cav_ratio=1.0, **settings
    )


@torch.no_grad()
def score(
    policy: Callable[[EnvBase], TensorDictModuleBase],
    settings: dict[str, Any],
    seed: int,
    args: argparse.Namespace,
    exploration: ExplorationType = ExplorationType.DETERMINISTIC,
) -> dict[str, np.ndarray]:
    """Episodes of ``policy(env)`` (greedy unless ``exploration`` is ``RANDOM``) on
    ``--eval-roads`` roads of the evaluation seed of ``seed``, the scenario changed by
    ``settings`` (:func:`env_settings`): per road, the system reward and the scenario's
    episode metrics (``[roads]`` each)."""
    env = evaluation_env(args.eval_roads, args.n_vehicles, settings)
    actor = policy(env)
    env.set_seed(EVAL_SEED_OFFSET + seed)
    td = env.reset()
    system = torch.zeros(args.eval_roads, dtype=torch.float64)
    near = torch.zeros(args.eval_roads, dtype=torch.float64)
    elsewhere = torch.zeros(args.eval_roads, dtype=torch.float64)
    lane, x = cav_lanes(env.sim)
    with set_exploration_type(exploration):
        for _ in range(int(env.config["horizon"])):
            td = env.step(actor(td))
            system += td.get(("next", "agents", "reward")).double().sum((-2, -1))
            td = td.get("next")
            after, x_after = cav_lanes(env.sim)
            changed = mainline_change(env.sim, lane, after)
            by_merge = near_merge(env.sim, x)
            near += (changed & by_merge).sum(-1).double()
            elsewhere += (changed & ~by_merge).sum(-1).double()
            lane, x = after, x_after
    episodes = env.pop_finished_episodes()
    env.close()
    out = {
        "system_reward": system.numpy(),
        "mainline_changes_near_merge": near.numpy(),
        "mainline_changes_elsewhere": elsewhere.numpy(),
    }
    for key in episodes[0]:
        out[key] = np.array([e[key] for e in episodes], dtype=float)
    return out


def cooperative_rule(n_vehicles: int) -> CooperativeMerge:
    """The cooperative merge rule of ``freeway_headroom.py`` on a road of ``n_vehicles``
    vehicles, with the settings of every scripted row here."""
    lanes = int(FreewayMergeEnv.resolved_config({"n_vehicles": n_vehicles})["lanes"])
    return CooperativeMerge(lanes, float("inf"), 60.0, 30.0, 15.0, 15.0, 1.5, torch.int64)


def cached_json(
    path: Path, compute: Callable[[], dict], current: Callable[[dict], bool] = lambda kept: True
) -> dict:
    """The JSON object kept at ``path`` when there is one and ``current(kept)`` holds (one kept
    before a field was added is stale), else ``compute()``'s, written there atomically."""
    if path.is_file():
        kept = json.loads(path.read_text())
        if current(kept):
            return kept
    result = compute()
    atomic_write_text(path, json.dumps(result))
    return result


def settings_tag(settings: dict[str, Any]) -> str:
    """``"_shield_w1.0"``-style part of a cached scripted row's file name."""
    return settings_label(settings).replace(", ", "_").replace("=", "")


def scripted(seed: int, settings: dict[str, Any], args: argparse.Namespace) -> dict[str, dict]:
    """Keep lane and the cooperative merge rule on the evaluation roads of ``seed``, cached in
    ``<out>/evals/``."""
    name = f"scripted_seed{seed}{settings_tag(settings)}_{args.n_vehicles}vehicles"
    path = Path(args.out) / "evals" / f"{name}_{args.eval_roads}roads.json"

    def compute() -> dict[str, dict]:
        rule = cooperative_rule(args.n_vehicles)
        result = {
            "keep lane": score(ScriptedCAVPolicy, settings, seed, args),
            "cooperative merge": score(lambda env: rule, settings, seed, args),
        }
        return {row: {k: v.tolist() for k, v in s.items()} for row, s in result.items()}

    return cached_json(path, compute, lambda kept: all(k in kept["keep lane"] for k in BEHAVIOUR))


def keep_lane_explored(
    seed: int, settings: dict[str, Any], args: argparse.Namespace, variant: str
) -> dict[str, list]:
    """Keep lane with the random moves of ``variant``'s collection policy once annealed (each
    CAV's decision replaced, with probability ``epsilon_end``, by one drawn uniformly from its
    ``exploration_actions``) on the evaluation roads of ``seed``, cached in ``<out>/evals/``:
    what the random moves alone give, beside a trained policy's ``explored`` row."""
    recipe, overrides = variant_overrides(variant, args)
    config = load_recipe(recipe).Config(env=ENV).with_overrides(overrides)
    epsilon, actions = float(config.epsilon_end), list(config.exploration_actions)
    moves = "".join(map(str, actions))
    name = f"keep_lane_explored_seed{seed}{settings_tag(settings)}_eps{epsilon}_moves{moves}"
    file = f"{args.n_vehicles}vehicles_{name}_{args.eval_roads}roads.json"
    path = Path(args.out) / "evals" / file

    def policy(env: EnvBase) -> TensorDictModuleBase:
        spec = env.full_action_spec[("agents", "action")]
        moves = restricted_epsilon_greedy(
            spec, actions, eps_init=epsilon, eps_end=epsilon, annealing_num_steps=1
        )
        return TensorDictSequential(ScriptedCAVPolicy(env), moves)

    def compute() -> dict[str, list]:
        torch.manual_seed(EVAL_SEED_OFFSET + seed)  # the random moves, as `evaluate` draws them
        scores = score(policy, settings, seed, args, ExplorationType.RANDOM)
        return {k: v.tolist() for k, v in scores.items()}

    return cached_json(path, compute)


def evaluate(
    variant: str,
    seed: int,
    run_dir: Path,
    args: argparse.Namespace,
    *,
    explored: bool = False,
    stage: int | None = None,
) -> dict:
    """The greedy scores of the run's newest checkpoint, cached in ``<out>/evals/``;
    ``explored``: the scores of its final epsilon-greedy collection policy instead (the actions
    its last training episodes took); ``stage``: cached as the scores at ``stage`` training
    frames (:func:`score_stages`) rather than at the end."""

    def compute() -> dict[str, list]:
        recipe, _ = variant_overrides(variant, args)
        exp = load_recipe(recipe).from_run_dir(run_dir)
        try:
            settings = env_settings(variant)
            if explored:
                torch.manual_seed(EVAL_SEED_OFFSET + seed)  # the random moves, reproducibly
                policy = TensorDictSequential(exp.eval_policy, exp.exploration)
                scores = score(lambda env: policy, settings, seed, args, ExplorationType.RANDOM)
            else:
                scores = score(lambda env: exp.eval_policy, settings, seed, args)
            return {k: v.tolist() for k, v in scores.items()}
        finally:
            exp.close()

    path = evaluation_path(variant, seed, args, explored=explored, stage=stage)
    return cached_json(path, compute, lambda kept: all(key in kept for key in BEHAVIOUR))


def evaluation_path(
    variant: str,
    seed: int,
    args: argparse.Namespace,
    *,
    explored: bool = False,
    stage: int | None = None,
) -> Path:
    """Where :func:`evaluate` keeps the scores of the run of ``variant`` and ``seed``."""
    at = "" if stage is None else f"_at{stage}"
    name = f"{variant}_seed{seed}_{args.eval_roads}roads{at}{'_explored' if explored else ''}"
    return Path(args.out) / "evals" / f"{name}.json"


def training_windows(run_dir: Path, window_frames: int, frames: int) -> list[tuple[float, float]]:
    """The run's training episodes (``train_episodes.jsonl``, the Shapley paper's Fig. 2
    quantity) in windows of ``window_frames`` frames up to ``frames``: per window, the mean
    system return and the mean ramp vehicles stuck per episode (NaN for a window without an
    ended episode)."""
    episodes = read_train_episodes(run_dir)
    bins = (episodes["frames"] - 1) // window_frames
    stuck = episodes.get("ramp_stuck", np.full(len(bins), np.nan))
    out = []
    for index in range(-(-frames // window_frames)):
        inside = bins == index
        if not inside.any():
            out.append((float("nan"), float("nan")))
            continue
        out.append((float(episodes["system_return"][inside].mean()), float(stuck[inside].mean())))
    return out


def windows_table(name: str, windows: dict[int, list[tuple[float, float]]], width: int) -> str:
    """A markdown table of :func:`training_windows` per seed (one row per seed)."""
    count = max(len(w) for w in windows.values())
    heads = [f"{i * width // 1000}k-{(i + 1) * width // 1000}k" for i in range(count)]
    lines = [
        f"{name}: mean training system reward / ramp vehicles stuck per episode, per "
        f"{width} frames",
        "",
        "| seed | " + " | ".join(heads) + " |",
        "|---|" + "---|" * count,
    ]
    for seed, rows in windows.items():
        cells = [f"{reward:.0f} / {stuck:.1f}" for reward, stuck in rows]
        lines.append(f"| {seed} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def gain_percent(run: dict, reference: dict) -> float:
    """The system reward of ``run``'s roads over ``reference``'s (keep lane on the same roads),
    in percent above it."""
    return float(100 * (np.mean(run["system_reward"]) / np.mean(reference["system_reward"]) - 1))


def frames_label(frames: int) -> str:
    """``"1M"`` for 1,000,000 frames, ``"75k"`` for 75,000, the number itself when it is not
    whole thousands."""
    if frames and frames % 1_000_000 == 0:
        return f"{frames // 1_000_000}M"
    return f"{frames // 1000}k" if frames % 1000 == 0 else str(frames)


def stages_table(name: str, gains: dict[int, dict[int, float | None]]) -> str:
    """A markdown table of the greedy gain over keep lane per seed (rows) at each scored stage
    (columns, :func:`score_stages`); ``-`` where a stage was not scored (the run had gone past
    it before ``--score-every`` asked for it)."""
    stages = sorted({stage for row in gains.values() for stage in row})
    lines = [
        f"{name}: greedy system reward vs keep lane at every scored stage of training",
        "",
        "| seed | " + " | ".join(frames_label(stage) for stage in stages) + " |",
        "|---|" + "---|" * len(stages),
    ]
    for seed, row in gains.items():
        cells = ["-" if row.get(s) is None else f"{row[s]:+.1f}%" for s in stages]
        lines.append(f"| {seed} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def summarise(name: str, runs: list[dict], references: list[dict]) -> tuple[dict, str]:
    """Summary fields and the table row of ``runs`` (one per seed) against keep lane on the
    same roads (``references``)."""
    gains = np.array([gain_percent(r, k) for r, k in zip(runs, references, strict=True)])
    _, low, high = bootstrap_interval(gains)

    def per_episode(key: str) -> float:
        return float(np.mean([np.mean(r[key]) for r in runs])) if key in runs[0] else 0.0

    fields = {
        "gain_percent_per_seed": gains.tolist(),
        "gain_percent_mean": float(gains.mean()),
        "gain_percent_ci95": [low, high],
        "system_reward": float(np.mean([np.mean(r["system_reward"]) for r in runs])),
        **{key: per_episode(key) for key in ("ramp_stuck", "collisions", "shielded")},
        **{key: per_episode(key) for key in BEHAVIOUR},
        "average_comfort": per_episode("average_comfort"),
    }
    row = (
        f"| {name} | {fields['system_reward']:.1f} | {gains.mean():+.1f}% [{low:+.1f}, "
        f"{high:+.1f}] | {', '.join(f'{g:+.1f}' for g in gains)} | {fields['ramp_stuck']:.1f} "
        f"| {fields['mainline_changes_near_merge']:.1f} "
        f"| {fields['mainline_changes_elsewhere']:.1f} "
        f"| {fields['collisions']:.2f} | {fields['shielded']:.1f} "
        f"| {fields['average_comfort']:.3f} |"
    )
    return fields, row


def main(argv: list[str] | None = None) -> dict[str, Any]:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--variants", nargs="+", default=["maddpg"])
    parser.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2, 3, 4])
    parser.add_argument("--frames", type=int, default=400_000)
    parser.add_argument("--anneal-frames", type=int, default=200_000)
    parser.add_argument("--train-roads", type=int, default=256)
    parser.add_argument("--eval-roads", type=int, default=256)
    parser.add_argument("--n-vehicles", type=int, default=30)
    parser.add_argument("--out", default="outputs/cooperation_control")
    parser.add_argument(
        "--window-frames",
        type=int,
        default=0,
        help="frames per window of the training-episode table (0: a tenth of --frames)",
    )
    parser.add_argument(
        "--explored",
        action="store_true",
        help="also score each epsilon variant's final collection policy (greedy + its final "
        "epsilon of random moves): does the policy merge only when its co-players are perturbed?",
    )
    parser.add_argument(
        "--score-every",
        type=int,
        default=0,
        help="also score each run's greedy policy every this many training frames (0: only "
        "at the end): the run trains in stages of this many frames, resuming from its "
        "checkpoint, and keeps one checkpoint on disk",
    )
    args = parser.parse_args(argv)
    for name in ("frames", "anneal_frames", "train_roads", "eval_roads", "n_vehicles"):
        if getattr(args, name) < 1:
            parser.error(f"--{name.replace('_', '-')} must be >= 1, got {getattr(args, name)}")
    for name in ("window_frames", "score_every"):
        if getattr(args, name) < 0:
            parser.error(f"--{name.replace('_', '-')} must be >= 0, got {getattr(args, name)}")
    for variant in args.variants:  # a bad name fails before any training
        variant_overrides(variant, args)
    print(f"# {machine_line()}")
    # the scripted rows of the scenarios the variants are scored in
    scenarios = {settings_label(env_settings(v)): env_settings(v) for v in args.variants}
    references = {
        label: [scripted(seed, settings, args) for seed in args.seeds]
        for label, settings in scenarios.items()
    }
    summary: dict[str, Any] = {"args": vars(args)}
    header = [
        f"{ENV}, {args.n_vehicles} CAVs (ratio 1), team reward (individual: each CAV's own "
        f"reward), {args.frames} training frames "
        f"per run, greedy evaluation on {args.eval_roads} roads per seed (seeds "
        f"{' '.join(map(str, args.seeds))}); gain = system reward vs keep lane on the same "
        "roads, mean over seeds [bootstrap 95% interval]",
        "",
        "| policy | system reward / episode | vs keep lane | per seed | ramp vehicles stuck "
        f"| mainline lane changes near the merge ({NEAR_MERGE:.0f} m before it to its end) "
        "| mainline lane changes elsewhere | collisions | shield interventions | comfort |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    rows = []
    for suffix, reference in references.items():
        keep = [r["keep lane"] for r in reference]
        for name in ("keep lane", "cooperative merge"):
            label = f"{name} (scripted{suffix})"
            fields, row = summarise(label, [r[name] for r in reference], keep)
            summary[label] = fields
            rows.append(row)
    width = args.window_frames or max(args.frames // 10, 1)
    training = []
    stages = score_stages(args.frames, args.score_every)
    for variant in args.variants:
        runs, windows, run_dirs, staged = [], {}, {}, {}
        keep = [r["keep lane"] for r in references[settings_label(env_settings(variant))]]
        for seed, reference in zip(args.seeds, keep, strict=True):
            print(f"{variant} seed {seed} ...", flush=True)
            staged[seed] = {}
            for stage, following in zip(stages[:-1], stages[1:], strict=True):
                run_dirs[seed], done = train(variant, seed, args, stage)
                # scored from the newest checkpoint: one written at this stage, before the next
                fresh = done < following
                if fresh or evaluation_path(variant, seed, args, stage=stage).is_file():
                    scores = evaluate(variant, seed, run_dirs[seed], args, stage=stage)
                    staged[seed][stage] = gain_percent(scores, reference)
                else:
                    staged[seed][stage] = None
            run_dirs[seed], _ = train(variant, seed, args, args.frames)
            runs.append(evaluate(variant, seed, run_dirs[seed], args))
            staged[seed][args.frames] = gain_percent(runs[-1], reference)
            windows[seed] = training_windows(run_dirs[seed], width, args.frames)
        summary[f"{variant} training windows"] = {str(k): v for k, v in windows.items()}
        training.append(windows_table(variant, windows, width))
        if args.score_every:
            summary[f"{variant} greedy gain by stage"] = {
                str(seed): {str(k): v for k, v in row.items()} for seed, row in staged.items()
            }
            training.append(stages_table(variant, staged))
        summary[variant], row = summarise(variant, runs, keep)
        rows.append(row)
        if args.explored and "epsilon" in variant.split("_"):
            label = f"{variant} (its final epsilon-greedy)"
            explored = [
                evaluate(variant, seed, run_dir, args, explored=True)
                for seed, run_dir in run_dirs.items()
            ]
            summary[label], row = summarise(label, explored, keep)
            rows.append(row)
            settings = env_settings(variant)
            label = f"keep lane + random moves at {variant}'s epsilon_end (scripted)"
            noisy = [keep_lane_explored(seed, settings, args, variant) for seed in args.seeds]
            summary[label], row = summarise(label, noisy, keep)
            rows.append(row)
    table = "\n\n".join(["\n".join([*header, *rows]), *training])
    out = Path(args.out)
    atomic_write_text(out / "control.md", table + "\n")
    atomic_write_text(out / "control.json", json.dumps(summary, indent=1))
    print(table)
    return summary


if __name__ == "__main__":
    from mapets_rl import quiet_dependencies

    quiet_dependencies()
    main()
