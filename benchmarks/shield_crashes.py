"""Which crashes get past the shield (issue 32): every CAV crash in the greedy evaluation of a
trained run (or of a scripted policy) on the shielded ``freeway-merge``, classified by what the
shield saw at the decision of the step in which it happened.

The shield (``BatchedFreeway.shield``) steps a copy of every road with the CAVs' proposed
decisions, then ``shield_horizon - 1`` steps of Keep Lane, and replaces every lane change or
emergency stop of a CAV that crashes in the copy by Keep Lane. Stepping is deterministic, so a
crash in step ``t`` falls in exactly one of:

- ``replaced``: the CAV's own decision was replaced and it crashed anyway (Keep Lane, the
  shield's backup, does not avoid it);
- ``kept, predicted``: the CAV proposed Keep Lane (perhaps in the middle of a lane change it
  began earlier: column ``mid change``) and the check predicted its crash: nothing it could
  have been given would have avoided it in the shield's model (rear-ended, cut in on);
- ``others replaced``: the check did not predict it, but other CAVs' decisions on its road were
  replaced, and the joint decision that ran is not the one checked (the replacements are not
  checked again together);
- ``unexplained``: not predicted and nothing replaced on its road; zero by construction (the
  check's first step is the real step: ``tests/envs/test_shield_and_exploration.py``).

Also per crash: with what (the obstacle at the ramp's end when no other vehicle on the road
crashed in the same step, a vehicle otherwise) and where (the ramp, i.e. the acceleration lane
and the lane before it; a mainline lane within ``cooperation_control.NEAR_MERGE`` metres before
the acceleration lane or along it; elsewhere on the mainline).

Each run is scored on the evaluation roads of its own seed (``EVAL_SEED_OFFSET + seed``, those of
``benchmarks/cooperation_control.py``); the scripted rows (keep lane, the cooperative merge rule)
on those of ``--seeds``, with the first run's scenario settings (shield, ``velocity_weight``).

    PYTHONPATH=.:benchmarks OMP_NUM_THREADS=1 python benchmarks/shield_crashes.py \\
        --runs RUN_DIR ... [--seeds 0 1] [--eval-roads 256] [--shield-passes 1] [--out DIR]

``--shield-passes N`` evaluates the same policies under a shield that checks its corrected
decisions again (``env_config.shield_passes``), up to ``N`` passes, so that no move runs that
the check predicts to crash beside the decisions that run: what gets through then are crashes
of CAVs that keep their lane (the classes stay those of the proposed decisions' check).

Prints a markdown table, the system reward and the crashes per episode in each class, over
the rows' seeds;
each row's counts are cached in ``DIR/<row>.json`` (a second call reads them).
"""

from __future__ import annotations

import argparse
import json
import re
from collections.abc import Callable
from functools import partial
from pathlib import Path
from typing import Any

import torch
import yaml
from cooperation_control import (
    EVAL_SEED_OFFSET,
    cached_json,
    cav_lanes,
    cooperative_rule,
    evaluation_env,
    near_merge,
    on_mainline,
)
from tensordict.nn import TensorDictModuleBase
from torchrl.envs import EnvBase
from torchrl.envs.utils import ExplorationType, set_exploration_type

from mapets_rl.app.plugins import load_recipe
from mapets_rl.envs import ScriptedCAVPolicy
from mapets_rl.envs.freeway import KL
from mapets_rl.experiment import latest_checkpoint
from mapets_rl.machine import machine_line

CLASSES = ("replaced", "kept, predicted", "others replaced", "unexplained")
"""What the shield saw at the crash's step (module docstring), in table order."""
DETAILS = ("mid change", "obstacle", "vehicle", "ramp", "mainline near merge", "mainline elsewhere")
"""The other columns: of the ``kept, predicted`` crashes those mid lane change; all crashes by
partner and by place."""


def decisions(env: EnvBase, td: Any) -> torch.Tensor:
    """The CAVs' decisions ``[roads, CAVs]`` (0..3) in ``td``'s action (one-hot or index)."""
    action = td.get(("agents", "action"))
    index = action if env.categorical_actions else action.argmax(-1)
    return index.reshape(env.sim.n_roads, -1).long()


@torch.no_grad()
def classify(policy: TensorDictModuleBase, env: EnvBase, seed: int) -> dict[str, float | int]:
    """One greedy episode of ``policy`` on every road of ``env`` (the evaluation roads of
    ``seed``): the number of CAV crashes in each class of :data:`CLASSES` and :data:`DETAILS`,
    the shield's interventions, the system reward (the CAVs' rewards summed over CAVs, steps and
    roads), the number of episodes (roads) and the env's own count of collisions (equal to the
    classes' sum)."""
    sim = env.sim
    counts = dict.fromkeys(CLASSES + DETAILS + ("shielded", "system_reward"), 0)
    env.set_seed(EVAL_SEED_OFFSET + seed)
    td = env.reset()
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        for _ in range(int(env.config["horizon"])):
            td = policy(td)
            proposed = decisions(env, td)
            slot = sim.state["agents"].get("slot")
            bodies = sim.state["bodies"]
            mid_change = bodies.get("lane").gather(1, slot) != bodies.get("target").gather(1, slot)
            lane, x = cav_lanes(sim)
            crashed_before = bodies.get("crashed").clone()  # the check steps these bodies
            predicted = sim.predicted_crashes(proposed)[0]
            td = env.step(td)
            crashed = td.get(("next", "agents", "info", "collided")).reshape(proposed.shape) > 0
            shielded = td.get(("next", "agents", "info", "shielded")).reshape(proposed.shape) > 0
            others_replaced = (shielded.sum(1, keepdim=True) - shielded.long()) > 0
            classes = {
                "replaced": crashed & shielded,
                "kept, predicted": crashed & ~shielded & predicted & (proposed == KL),
                "others replaced": crashed & ~shielded & ~predicted & others_replaced,
                "unexplained": crashed & ~shielded & ~predicted & ~others_replaced,
            }
            new_bodies = sim.state["bodies"].get("crashed") & ~crashed_before
            other_vehicle = (new_bodies.sum(1, keepdim=True) - crashed.long()) > 0
            mainline, by_merge = on_mainline(sim, lane), near_merge(sim, x)
            details = {
                "mid change": classes["kept, predicted"] & mid_change,
                "obstacle": crashed & ~other_vehicle,
                "vehicle": crashed & other_vehicle,
                "ramp": crashed & ~mainline,
                "mainline near merge": crashed & mainline & by_merge,
                "mainline elsewhere": crashed & mainline & ~by_merge,
            }
            for key, mask in {**classes, **details}.items():
                counts[key] += int(mask.sum())
            counts["shielded"] += int(shielded.sum())
            counts["system_reward"] += float(td.get(("next", "agents", "reward")).double().sum())
            td = td.get("next")
    counts["episodes"] = sim.n_roads
    counts["collisions"] = int(sum(e["collisions"] for e in env.pop_finished_episodes()))
    return counts


def checked_runs(paths: list[str]) -> list[tuple[Path, dict[str, Any], Path]]:
    """Each ``--runs`` directory with its ``run.json`` and newest checkpoint; ValueError naming
    ``--runs`` for one that is not a finished shielded run on the torch freeway (before any
    work starts)."""
    runs = []
    for path in map(Path, paths):
        checkpoint = latest_checkpoint(path) if (path / "run.json").is_file() else None
        if checkpoint is None:
            raise ValueError(f"--runs: {path} is not a run directory with a checkpoint")
        info = json.loads((path / "run.json").read_text())
        env_config = yaml.safe_load((path / "config.yaml").read_text()).get("env_config", {})
        if info.get("env") != "freeway-merge" or env_config.get("backend") != "torch":
            raise ValueError(f"--runs: {path} is not a run on the torch backend's freeway-merge")
        if not env_config.get("shield", False):
            raise ValueError(f"--runs: {path} was trained without the shield (env_config.shield)")
        runs.append((path, info, checkpoint))
    return runs


def row_name(run_dir: Path, checkpoint: Path) -> str:
    """A trained row's name: the run directory's, its seed dropped, with the checkpoint's frames
    in thousands (``shapley_..._member@300k``)."""
    frames = int(re.sub(r"\D", "", checkpoint.stem))
    variant = re.sub(r"_seed\d+.*$", "", run_dir.name)
    return f"{variant}@{round(frames / 1000)}k"


def has_system_reward(counts: dict[str, Any]) -> bool:
    """Whether cached ``counts`` are current (those kept before the system reward was added are
    computed again)."""
    return "system_reward" in counts


def trained_counts(run_dir: Path, info: dict[str, Any], roads: int, passes: int) -> dict[str, Any]:
    """:func:`classify` of the run's greedy policy on ``roads`` evaluation roads of its seed,
    with its own scenario settings and a shield of ``passes`` passes; the settings are returned
    under ``"settings"``."""
    exp = load_recipe(info["recipe"]).from_run_dir(run_dir)
    try:
        env_config = exp.config.env_config
        settings = {
            "shield": True,
            "shield_passes": passes,
            "velocity_weight": float(env_config.get("velocity_weight", 0.1)),
        }
        env = evaluation_env(roads, int(env_config["n_vehicles"]), settings)
        counts = classify(exp.eval_policy, env, int(info["seed"]))
        env.close()
    finally:
        exp.close()
    return {**counts, "settings": settings, "n_vehicles": int(env_config["n_vehicles"])}


def scripted_counts(
    policy: Callable[[EnvBase], TensorDictModuleBase],
    seed: int,
    vehicles: int,
    settings: dict[str, Any],
    roads: int,
) -> dict[str, Any]:
    """:func:`classify` of the scripted ``policy(env)`` on ``roads`` evaluation roads of
    ``seed`` with ``vehicles`` vehicles and the scenario ``settings``."""
    env = evaluation_env(roads, vehicles, settings)
    counts = classify(policy(env), env, seed)
    env.close()
    return counts


def table(rows: dict[str, list[dict[str, Any]]]) -> str:
    """Markdown: per row, the system reward and the crashes per episode (all seeds' episodes
    pooled) in each class."""
    columns = ("system reward", "crashes", *CLASSES, *DETAILS, "shielded")
    lines = [
        "| policy | seeds | " + " | ".join(columns) + " |",
        "|---|---|" + "---|" * len(columns),
    ]
    for name, seeds in rows.items():
        episodes = sum(c["episodes"] for c in seeds)
        total = {k: sum(c[k] for c in seeds) for k in CLASSES + DETAILS + ("shielded",)}
        total["crashes"] = sum(total[k] for k in CLASSES)
        total["system reward"] = sum(c["system_reward"] for c in seeds)
        cells = " | ".join(
            f"{total[k] / episodes:.{1 if k == 'system reward' else 3}f}" for k in columns
        )
        lines.append(f"| {name} | {len(seeds)} | {cells} |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> dict[str, list[dict[str, Any]]]:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--runs", nargs="*", default=[], help="trained run directories")
    parser.add_argument("--seeds", type=int, nargs="*", default=[0], help="scripted rows' seeds")
    parser.add_argument("--eval-roads", type=int, default=256)
    parser.add_argument("--n-vehicles", type=int, default=30, help="scripted rows without --runs")
    parser.add_argument(
        "--shield-passes",
        type=int,
        default=1,
        help="the evaluation's shield_passes (1: the shield the runs trained with; more: the "
        "corrected decisions are checked again until nothing is replaced)",
    )
    parser.add_argument("--out", default="outputs/shield_crashes")
    args = parser.parse_args(argv)
    if args.eval_roads < 1:
        parser.error(f"--eval-roads must be >= 1, got {args.eval_roads}")
    if not 1 <= args.shield_passes <= 40:
        parser.error(f"--shield-passes must be in [1, 40], got {args.shield_passes}")
    if any(s < 0 for s in args.seeds):
        parser.error(f"--seeds must be >= 0, got {args.seeds}")
    runs = checked_runs(args.runs)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    print(machine_line())
    passes = args.shield_passes
    suffix = f", {passes} shield passes" if passes > 1 else ""
    rows: dict[str, list[dict[str, Any]]] = {}
    for run_dir, info, checkpoint in runs:
        name = row_name(run_dir, checkpoint) + suffix
        key = f"{name}_seed{info['seed']}_{args.eval_roads}roads".replace(", ", "_")
        counts = cached_json(
            out / f"{key}.json",
            partial(trained_counts, run_dir, info, args.eval_roads, passes),
            has_system_reward,
        )
        rows.setdefault(name, []).append(counts)
    first = rows and next(iter(rows.values()))[0]
    default = {"shield": True, "shield_passes": passes, "velocity_weight": 1.0}
    settings = first["settings"] if first else default
    vehicles = first["n_vehicles"] if first else args.n_vehicles
    label = f"w{settings['velocity_weight']}_{vehicles}vehicles_{args.eval_roads}roads"
    label += f"_{passes}passes" if passes > 1 else ""
    scripted = {
        "keep lane": ScriptedCAVPolicy,
        "cooperative merge": lambda env: cooperative_rule(vehicles),
    }
    for name, policy in scripted.items():
        for seed in args.seeds:
            key = f"{name.replace(' ', '_')}_seed{seed}_{label}"
            counts = cached_json(
                out / f"{key}.json",
                partial(scripted_counts, policy, seed, vehicles, settings, args.eval_roads),
                has_system_reward,
            )
            rows.setdefault(name + suffix, []).append(counts)
    print(table(rows))
    return rows


if __name__ == "__main__":
    main()
