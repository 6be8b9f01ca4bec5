"""Which crashes get past the shield (issue 32): every CAV crash in the greedy evaluation of
trained ``freeway-merge`` runs (and of the reference policies), classified by what the shield
(``BatchedFreeway.shield``: a copy of the road stepped with the proposed decisions, then Keep
Lane; a lane change or stop that crashes there becomes Keep Lane) saw in the crash's step:

- ``replaced``: the CAV's decision was replaced and it crashed anyway;
- ``kept, predicted``: it proposed Keep Lane (column ``mid change``: in a lane change begun
  earlier) and the check predicted its crash (rear-ended, cut in on);
- ``others replaced``: not predicted, but other CAVs' decisions on its road were replaced, and
  the joint decision that ran is not the one checked;
- ``unexplained``: neither; zero by construction (the check's first step is the real step).

Also per crash: with what (the obstacle at the ramp's end, or a vehicle) and where (the ramp;
the mainline from 100 m before the acceleration lane to its end; elsewhere). Each run plays the
evaluation roads of its seed (``mapets-rl evaluate RUN --roads``) with its own settings; the
references play those of the first arm's runs. ``--shield-passes N``: a shield that checks its
corrected decisions again, up to ``N`` passes (``env_config.shield_passes``).

    OMP_NUM_THREADS=1 python benchmarks/shield_crashes.py \\
        --runs RUN_DIR ... [--eval-roads 256] [--shield-passes 1] [--out DIR]

Prints a markdown table: the system reward and the crashes per episode in each class, over the
rows' seeds; each row's counts are cached in ``DIR/<row>.json``.
"""

from __future__ import annotations

import argparse
import json
import re
from pathlib import Path
from typing import Any

import torch
from tensordict.nn import TensorDictModuleBase
from torchrl.envs import EnvBase
from torchrl.envs.utils import ExplorationType, set_exploration_type

from mapets_rl.app.plugins import load_recipe
from mapets_rl.envs.freeway import KL
from mapets_rl.envs.references import make_reference
from mapets_rl.envs.torch_freeway.counterfactuals import cav_lanes, near_merge, on_mainline
from mapets_rl.experiment import atomic_write_text, latest_checkpoint, run_recipe_name
from mapets_rl.experiment.protocol import ROAD_EVAL_SEED_OFFSET, evaluation_env
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
    env.set_seed(seed + ROAD_EVAL_SEED_OFFSET)
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


def counts(run: Path, policy: str, passes: int, args: argparse.Namespace) -> dict[str, Any]:
    """:func:`classify` of ``run``'s greedy policy (``policy="trained"``) or of a reference
    policy on ``--eval-roads`` evaluation roads of its seed, with its scenario settings and a
    shield of ``passes`` passes; cached in ``<out>/``. ValueError naming ``--runs`` for a run
    that is not a shielded run on the torch backend's freeway-merge."""
    checkpoint = latest_checkpoint(run)
    frames = round(int(re.sub(r"\D", "", checkpoint.stem)) / 1000) if checkpoint else 0
    path = Path(args.out) / f"{run.name}@{frames}k_{policy}_{args.eval_roads}roads_{passes}.json"
    if path.is_file():
        return json.loads(path.read_text())
    exp = load_recipe(run_recipe_name(run)).from_run_dir(run)
    try:
        config = exp.config.with_overrides([f"env_config.shield_passes={passes}"])
        env_config = config.env_config
        if config.env != "freeway-merge" or env_config.get("backend") != "torch":
            raise ValueError(f"--runs: {run} is not a run on the torch backend's freeway-merge")
        if not env_config.get("shield", False):
            raise ValueError(f"--runs: {run} was trained without the shield (env_config.shield)")
        env = evaluation_env(config, args.eval_roads)
        actor = exp.eval_policy if policy == "trained" else make_reference(config.env, policy, env)
        result = classify(actor, env, config.seed)
        env.close()
    finally:
        exp.close()
    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_text(path, json.dumps(result))
    return result


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
    parser.add_argument("--runs", nargs="+", type=Path, required=True, help="run directories")
    parser.add_argument("--eval-roads", type=int, default=256)
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
    for run in args.runs:  # before any work
        if latest_checkpoint(run) is None:
            parser.error(f"--runs: {run} is not a run directory with a checkpoint")
    print(machine_line())
    passes = args.shield_passes
    suffix = f", {passes} shield passes" if passes > 1 else ""
    rows: dict[str, list[dict[str, Any]]] = {}
    for run in args.runs:
        name = re.sub(r"_seed\d+$", "", run.name) + suffix
        rows.setdefault(name, []).append(counts(run, "trained", passes, args))
    first = re.sub(r"_seed\d+$", "", args.runs[0].name)
    for reference in ("keep-lane", "cooperative-merge"):
        for run in (r for r in args.runs if re.sub(r"_seed\d+$", "", r.name) == first):
            rows.setdefault(reference + suffix, []).append(counts(run, reference, passes, args))
    print(table(rows))
    return rows


if __name__ == "__main__":
    main()
