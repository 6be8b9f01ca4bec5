"""Are the learned lane changes near the merge selfish? Exact counterfactuals (issue 32).

Each trained ``freeway-merge`` run (``--runs``: e.g. ``benchmarks/cooperation_control.py``'s
``<out>/runs/*``) plays its greedy policy on ``--roads`` roads of its evaluation stream (those
of ``mapets-rl evaluate RUN --roads``), with its own scenario settings. Every lane change of a
CAV on a mainline lane is replayed on a copy of the road where that CAV keeps its lane instead
(``--deviation rest``: for the rest of the episode; ``step``: this step only), everything else
the same (``mapets_rl.envs.torch_freeway.counterfactuals.lane_change_effects``). Per decision,
discounted by ``--gamma``: ``own``, what the change earns the CAV that makes it (and in metres
driven), and ``system``, what it earns the CAVs together.

A decision is a *dilemma* when ``own < 0 < system`` (cooperative and costly: what individual
credit would unlearn), *selfish-harmful* when ``system < 0 < own``, *aligned* when both have one
sign; split by where it is made (near the merge: 100 m before the acceleration lane to its end,
and elsewhere). ``--rule`` adds the cooperative merge rule on the roads of the first arm's runs.

    OMP_NUM_THREADS=1 python benchmarks/yield_counterfactuals.py --runs OUT/runs/* --rule \\
        --roads 64 --out OUT

Per run the decisions are cached in ``<out>/evals/yields_*.json``; prints a markdown table and
writes it to ``<out>/yields_gamma<G>_<deviation>.md``.
"""

from __future__ import annotations

import argparse
import json
import re
from pathlib import Path

import numpy as np

from mapets_rl.app.plugins import load_recipe
from mapets_rl.envs.references import make_reference
from mapets_rl.envs.torch_freeway.counterfactuals import deciding, lane_change_effects
from mapets_rl.experiment import atomic_write_text, latest_checkpoint, run_recipe_name
from mapets_rl.experiment.protocol import ROAD_EVAL_SEED_OFFSET, evaluation_env
from mapets_rl.machine import machine_line
from mapets_rl.statistics import bootstrap_interval

RULE = "cooperative-merge"


def decisions(run: Path, policy: str, args: argparse.Namespace) -> dict[str, np.ndarray]:
    """The counterfactuals of ``run``'s greedy policy (``policy="trained"``) or of a reference
    policy on its evaluation roads, cached in ``<out>/evals/``."""
    tag = f"{run.name}_{policy}_{args.roads}roads_gamma{args.gamma}_{args.deviation}"
    path = Path(args.out) / "evals" / f"yields_{tag}.json"
    if not path.is_file():
        exp = load_recipe(run_recipe_name(run)).from_run_dir(run)
        env = evaluation_env(exp.config, args.roads)
        try:
            env.set_seed(exp.config.seed + ROAD_EVAL_SEED_OFFSET)
            env.reset()
            actor = (
                exp.eval_policy
                if policy == "trained"
                else make_reference(exp.config.env, policy, env)
            )
            result = lane_change_effects(
                env.sim, deciding(actor), gamma=args.gamma, rest=args.deviation == "rest"
            )
        finally:
            env.close()
            exp.close()
        path.parent.mkdir(parents=True, exist_ok=True)
        atomic_write_text(path, json.dumps(result))
    return {k: np.asarray(v) for k, v in json.loads(path.read_text()).items()}


def summary_row(label: str, per_seed: list[dict[str, np.ndarray]], roads: int) -> str:
    """One markdown row: lane-change decisions per episode, the share that moves the car (the
    others, e.g. Change Left in the leftmost lane, cost comfort only), then over the moving
    decisions the mean own and system effects (bootstrap 95% over the runs' means) and the
    shares of own gains, aligned, dilemma and selfish-harmful decisions."""
    moved = [d["moved"].astype(bool) for d in per_seed]
    count = sum(len(m) for m in moved)
    share = sum(int(m.sum()) for m in moved) / max(count, 1)
    head = f"| {label} | {count / (roads * len(per_seed)):.1f} | {share:.2f} "
    if share == 0:
        return head + "| | | | | | | |"
    own = np.concatenate([d["own"][m] for d, m in zip(per_seed, moved, strict=True)])
    system = np.concatenate([d["system"][m] for d, m in zip(per_seed, moved, strict=True)])

    def seed_means(key: str) -> str:
        means = [float(d[key][m].mean()) for d, m in zip(per_seed, moved, strict=True) if m.any()]
        mean, low, high = bootstrap_interval(np.array(means))
        return f"{mean:+.1f} [{low:+.1f}, {high:+.1f}]"

    aligned = ((own > 0) & (system > 0)) | ((own < 0) & (system < 0))
    return head + (
        f"| {seed_means('own')} | {seed_means('own_metres')} | {seed_means('system')} "
        f"| {(own > 0).mean():.2f} | {aligned.mean():.2f} "
        f"| {((own < 0) & (system > 0)).mean():.2f} | {((system < 0) & (own > 0)).mean():.2f} |"
    )


HEADER = (
    "| policy, where | lane-change decisions per episode | share that moves the car "
    "| own effect, mean [95%] | own effect in metres driven | system effect, mean [95%] "
    "| own > 0 | aligned (same sign) | dilemma (own < 0 < system) "
    "| selfish-harmful (system < 0 < own) |\n|---|---|---|---|---|---|---|---|---|---|"
)


def main(argv: list[str] | None = None) -> str:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--runs", nargs="+", type=Path, required=True, help="run directories")
    parser.add_argument("--rule", action="store_true", help="also the cooperative merge rule")
    parser.add_argument("--roads", type=int, default=64, help="evaluation roads per run")
    parser.add_argument("--gamma", type=float, default=0.95, help="discount of the effects")
    parser.add_argument("--deviation", choices=["step", "rest"], default="rest")
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args(argv)
    if args.roads < 1 or not 0.0 <= args.gamma <= 1.0:
        parser.error(f"need --roads >= 1 and --gamma in [0, 1], got {args.roads}, {args.gamma}")
    for run in args.runs:  # a missing run fails before any work
        if latest_checkpoint(run) is None:
            parser.error(f"--runs: {run} holds no trained run")
    print(f"# {machine_line()}")
    arms: dict[str, list[tuple[Path, str]]] = {}
    for run in args.runs:
        arms.setdefault(re.sub(r"_seed\d+$", "", run.name), []).append((run, "trained"))
    if args.rule:
        arms[RULE] = [(run, RULE) for run, _ in next(iter(arms.values()))]
    rows = [HEADER]
    for arm, runs in arms.items():
        per_seed = [decisions(run, policy, args) for run, policy in runs]
        for where, near in (("near the merge", True), ("elsewhere", False)):
            part = [{k: v[d["near"] == near] for k, v in d.items()} for d in per_seed]
            rows.append(summary_row(f"{arm}, {where}", part, args.roads))
    table = "\n".join(rows)
    print(table)
    atomic_write_text(args.out / f"yields_gamma{args.gamma}_{args.deviation}.md", table + "\n")
    return table


if __name__ == "__main__":
    main()
