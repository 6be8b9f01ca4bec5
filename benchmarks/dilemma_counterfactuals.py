"""Is the dilemma variant of freeway-merge a dilemma? Exact counterfactuals (issue 50).

The scenario settings are those of a published config (``--config``, default the dilemma
study's ``freeway-merge-dilemma/maddpg-individual``: the shield, 30 vehicles all CAVs and the
variant's ``ramp_forcing``, ``target_speed``, ``velocity_weight`` and ``lane_change_comfort``),
changed by ``--set KEY=VALUE`` (scenario keys).
Every CAV keeps its lane on ``--roads`` evaluation roads (the co-players of every question
below). At every step, each CAV's alternatives are replayed on a copy of its road where it
alone plays them for that step, then keeps its lane again, everything else the same
(:func:`mapets_rl.envs.torch_freeway.counterfactuals.branches`); per decision, discounted by
``--gamma`` (the learners' 0.95), ``own`` is the mover's return with the move minus without it,
``system`` the CAVs' summed returns with minus without. The decisions:

- ``rule's yields``: the Change Left that the cooperative merge rule (``cooperative-merge``)
  would play at that moment (a CAV in the rightmost lane before the merge point, a ramp vehicle
  beside it, room on the left);
- ``other Change Left`` / ``Change Right``: every other move of a CAV on a mainline lane near
  the merge (from 100 m before the acceleration lane to its end), where the lane exists;
- ``forcing``: a Change Left of a ramp CAV on the acceleration lane.

A move that the shield refuses runs as Keep Lane and changes nothing; the effects are averaged
over the moves that ran (``moved``: some vehicle's lateral position differs after the step). A
decision is a dilemma when ``own < 0 < system``. Then the scores of keep lane, the cooperative
rule and every ramp CAV forcing its merge (Change Left on the acceleration lane, Keep Lane
elsewhere) by the evaluation protocol (``score_roads``) on ``--score-roads`` roads per seed.

``--runs RUN_DIR ...`` (MADDPG-style runs with a Q critic): beside each decision's exact effect
on what the run's critic is fitted to (the mover's own return, or the CAVs' mean under
``team_reward``), the advantage its critic gives the move against Keep Lane
(:func:`mapets_rl.modules.critic_probe.critic_advantages`); ``--gamma`` should be the run's.

    OMP_NUM_THREADS=1 python benchmarks/dilemma_counterfactuals.py --roads 64 \\
        --score-roads 256 --seeds 0 1 2
"""

from __future__ import annotations

import argparse
import time
from functools import partial

import numpy as np
import torch
from _common import add_published_config_args, published_config
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase

from mapets_rl.app.plugins import load_recipe
from mapets_rl.envs.freeway import CL, KL
from mapets_rl.envs.references import ACTION, OBSERVATION, make_reference
from mapets_rl.envs.torch_freeway.counterfactuals import MERGE_DECISIONS, merge_decisions
from mapets_rl.experiment.protocol import (
    ROAD_EVAL_SEED_OFFSET,
    evaluation_env,
    gain_percent,
    score_roads,
)
from mapets_rl.experiment.runner import run_recipe_name
from mapets_rl.machine import machine_line
from mapets_rl.modules.critic_probe import critic_advantages
from mapets_rl.statistics import bootstrap_interval


class ForceMerge(TensorDictModuleBase):
    """Every ramp CAV on the acceleration lane plays Change Left, every other CAV Keep Lane:
    observation ``[*, n, 24]`` (entry 1: the lane number, ``lanes`` on the acceleration lane)
    -> one-hot action ``[*, n, 4]``."""

    in_keys = [OBSERVATION]
    out_keys = [ACTION]

    def __init__(self, lanes: int) -> None:
        super().__init__()
        self.lanes = lanes

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        lane = tensordict.get(OBSERVATION)[..., 1]
        index = torch.where(lane == self.lanes, CL, KL)
        tensordict.set(ACTION, torch.nn.functional.one_hot(index, 4).to(torch.int64))
        return tensordict


def effect_row(label: str, found: dict[str, np.ndarray], roads: int) -> str:
    """One markdown row: decisions per episode, the share that ran, then over those that ran
    the share costing the mover, the mean effect on the mover and on the system (bootstrap 95%
    over the decisions) and the share of dilemmas (``own < 0 < system``)."""
    ran = found["moved"].astype(bool)
    head = f"| {label} | {len(ran) / roads:.2f} | {ran.mean() if len(ran) else 0:.2f} "
    if not ran.any():
        return head + "| | | | | |"
    own, system = found["own"][ran], found["system"][ran]

    def interval(values: np.ndarray) -> str:
        mean, low, high = bootstrap_interval(values)
        return f"{mean:+.2f} [{low:+.2f}, {high:+.2f}]"

    return head + (
        f"| {(own < 0).mean():.2f} | {interval(own)} | {(system > 0).mean():.2f} "
        f"| {interval(system)} | {((own < 0) & (system > 0)).mean():.2f} |"
    )


def critic_rows(label: str, found: dict[str, np.ndarray], j: int, team_of: int | None) -> str:
    """One markdown row for run ``j``: over the decisions that ran, the exact effect on the
    critic's target (``system / team_of`` under a team reward of ``team_of`` CAVs, else
    ``own`` for ``team_of=None``) and the critic's advantage, each a mean with a bootstrap 95%
    interval, the share of each above zero and their correlation."""
    ran = found["moved"].astype(bool)
    if not ran.any():
        return f"| {label} | | | | | |"
    exact = found["own"][ran] if team_of is None else found["system"][ran] / team_of
    critic = found[f"probe{j}"][ran]
    cells = []
    for values in (exact, critic):
        mean, low, high = bootstrap_interval(values)
        cells.append(f"{mean:+.3f} [{low:+.3f}, {high:+.3f}] | {(values > 0).mean():.2f}")
    correlation = np.corrcoef(exact, critic)[0, 1] if len(exact) > 1 else float("nan")
    return f"| {label} | {cells[0]} | {cells[1]} | {correlation:+.2f} |"


CRITIC_HEADER = (
    "| decision | exact effect on the critic's target, mean [95%] | share > 0 "
    "| critic's advantage over Keep Lane, mean [95%] | share > 0 | correlation |\n"
    "|---|---|---|---|---|---|"
)


HEADER = (
    "| decision (every co-player keeps its lane) | per episode | share that ran "
    "| share costing the mover | mover's effect, mean [95%] | share paying the system "
    "| system effect, mean [95%] | dilemma (own < 0 < system) |\n"
    "|---|---|---|---|---|---|---|---|"
)


def main(argv: list[str] | None = None) -> str:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    add_published_config_args(parser, "freeway-merge-dilemma/maddpg-individual")
    parser.add_argument("--roads", type=int, default=64, help="roads of the counterfactuals")
    parser.add_argument("--score-roads", type=int, default=256, help="roads per seed, scores")
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--gamma", type=float, default=0.95, help="discount of the effects")
    parser.add_argument("--runs", nargs="*", default=[], metavar="RUN_DIR",
                        help="runs whose critics are set beside the exact effects")  # fmt: skip
    args = parser.parse_args(argv)
    if args.roads < 1 or args.score_roads < 1 or not 0.0 <= args.gamma <= 1.0:
        parser.error("need --roads >= 1, --score-roads >= 1 and --gamma in [0, 1]")
    config = published_config(args)
    print(f"# {machine_line()}")
    print(f"# {args.config} {' '.join(args.set)}: {config.unbatched_env_config()}")
    started = time.perf_counter()
    runs = [load_recipe(run_recipe_name(run)).from_run_dir(run) for run in args.runs]
    env = evaluation_env(config, args.roads)
    try:
        env.set_seed(config.seed + ROAD_EVAL_SEED_OFFSET)
        env.reset()
        probes = [partial(critic_advantages, run.critic, n_actions=4) for run in runs]
        found = {key: value.numpy() for key, value in
                 merge_decisions(env.sim, args.gamma, probes).items()}  # fmt: skip
        cavs = env.sim.n_cavs
    finally:
        env.close()
        for run in runs:
            run.close()
    rows = [HEADER]
    parts = [{key: value[found["kind"] == kind] for key, value in found.items()} for kind in
             range(len(MERGE_DECISIONS))]  # fmt: skip
    for label, part in zip(MERGE_DECISIONS, parts, strict=True):
        rows.append(effect_row(label, part, args.roads))
    mainline = found["kind"] < MERGE_DECISIONS.index("forcing")
    near = {key: value[mainline] for key, value in found.items()}
    rows.append(effect_row("every mainline move near the merge", near, args.roads))
    for j, run in enumerate(runs):
        team = bool(run.config.env_config.get("team_reward", False))
        rows += ["", f"{args.runs[j]} (team reward: {team}, gamma {run.config.gamma}):",
                 CRITIC_HEADER]  # fmt: skip
        for label, part in zip(MERGE_DECISIONS, parts, strict=True):
            rows.append(critic_rows(label, part, j, cavs if team else None))
    lanes = int(config.env_config.get("lanes", 3))
    policies = {
        "cooperative rule": lambda env: make_reference(config.env, "cooperative-merge", env),
        "every ramp CAV forcing": lambda env: ForceMerge(lanes),
    }
    gains: dict[str, list[float]] = {name: [] for name in policies}
    for seed in args.seeds:
        seeded = config.with_overrides([f"seed={seed}"])
        reference = score_roads(
            seeded, lambda env: make_reference(config.env, "keep-lane", env), args.score_roads
        )
        for name, policy in policies.items():
            gains[name].append(gain_percent(score_roads(seeded, policy, args.score_roads),
                                            reference))  # fmt: skip
    rows += [
        "",
        f"| policy | over keep lane, per seed ({args.score_roads} roads each) | mean |",
        "|---|---|---|",
    ]
    for name, per_seed in gains.items():
        each = ", ".join(f"{g:+.1f}%" for g in per_seed)
        rows.append(f"| {name} | {each} | {np.mean(per_seed):+.1f}% |")
    table = "\n".join(rows)
    print(table)
    print(f"# {time.perf_counter() - started:.0f} s")
    return table


if __name__ == "__main__":
    main()
