"""Why CAVs crash on the two-lane figure-eight: policies scored and every crash classified.

Drives ``figure-eight-multilane`` (22 CAVs, 400 steps, the recipe's scenario defaults) with
policies that separate the causes, one change at a time, on the same seeds:

- ``scripted``: :class:`~mapets_rl.envs.ScriptedCAVPolicy` (IDM, first come first served at
  the crossing, never changes lanes): the scenario is drivable;
- ``random`` / ``random-keep-lane``: uniform target speeds with uniform lane-change flags /
  with the flag held at 0 (what the first MA-PETS episode drives, and its share of lane changes);
- ``oracle`` / ``oracle-keep-lane``: the MA-PETS planner (cpu-preset CEM, the recipe's reward
  and termination with the lane-aware test) planning through
  :class:`~mapets_rl.envs.figure_eight_kinematics.FigureEightKinematicModel` (exact own speed,
  constant-speed neighbours) instead of a learned ensemble: a crash here is the planner's or
  the unforeseeable traffic's, not the model's. Its margins are the scenario's planner-reward
  section (:class:`~mapets_rl.envs.FigureEightPlannerReward`, the ones MA-PETS plans with)
  with ``--reward key=value`` changes: ``--reward lane_change_gap=0 lane_change_time=0``
  switches the lane-aware termination off, ``--reward headway=0 lane_change_time=0`` gives the
  fixed margins of earlier versions;
- ``oracle-shared`` / ``learned-shared``: the same planners with plan sharing
  (:class:`~mapets_rl.planning.shared_plans.PlanSharingPlanner`, MA-PETS ``comm.share_plans``):
  each CAV plans with the broadcast plans of the CAVs it observes within ``--comm-range``
  metres as their future speeds;
- ``learned``: the planner of a trained MA-PETS run (``--run RUN_DIR``, its last checkpoint:
  the learned ensembles, the recipe's reward, termination and CEM) on the same seeds: what the
  learned model adds to the oracle's crashes, class by class.

Every CAV crash is classified from the simulator state of the step before it: ``crossing``
(the two vehicles on different branches, both near the crossing point), ``lane change (CAV)``
/ ``lane change (other)`` (one of the two was between lanes), ``into leader`` (the partner was
ahead in the CAV's lane), ``rear-ended`` (it was behind). The partner is the nearest vehicle
that crashed in the same step.

Usage::

    python benchmarks/multilane_diagnosis.py --seeds 0 1 2 --policies scripted random oracle
    python benchmarks/multilane_diagnosis.py --policies learned --run RUN_DIR

The oracle told its neighbours' actual futures (``oracle-exact``, ``oracle-exact-windowed``)
was measured by this script and ``benchmarks/exact_futures.py`` at commit 00fe880 (retired;
``docs/results/history.md``).
"""

from __future__ import annotations

import argparse
import json
from collections import Counter
from pathlib import Path

import numpy as np
import torch
from _common import CLASSES, POLICIES, SCENARIO, run_episode

from mapets_rl.config import ConfigError, parse_override
from mapets_rl.envs.figure_eight import FigureEightPlannerReward
from mapets_rl.machine import machine_line
from mapets_rl.planning import CPU_PRESET


def main(argv: list[str] | None = None) -> list[dict]:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--policies", nargs="+", choices=POLICIES, default=list(POLICIES))
    parser.add_argument(
        "--scenario",
        default=SCENARIO,
        choices=("figure-eight", SCENARIO),
        help="figure-eight: the one-lane reference (no keep-lane variants)",
    )
    parser.add_argument("--horizon", type=int, default=400, help="steps per episode")
    parser.add_argument(
        "--reward",
        nargs="*",
        default=[],
        metavar="key=value",
        help="oracle: FigureEightPlannerReward fields over its defaults (the "
        "margins MA-PETS plans with), e.g. headway=0 lane_change_gap=8",
    )
    parser.add_argument(
        "--anchor-candidates", action="store_true", help="oracle: iCEM's fallback candidates"
    )
    parser.add_argument("--keep-best", action="store_true", help="oracle: best sequence")
    parser.add_argument("--run", default=None, help="learned: a MA-PETS run directory")
    parser.add_argument(
        "--set",
        nargs="*",
        default=[],
        metavar="key=value",
        help="learned: overrides of the run's config, e.g. planner_reward.lane_change_time=1",
    )
    parser.add_argument(
        "--planner",
        nargs="*",
        default=[],
        metavar="key=value",
        help="oracle: PlannerConfig fields over the cpu preset's, e.g. population=16 noise_beta=2",
    )
    parser.add_argument(
        "--comm-range",
        type=float,
        default=100.0,
        help="*-shared: the range d [m] within which CAVs hear the plans",
    )
    parser.add_argument("--out", type=Path, default=None, help="write the rows as JSON here")
    args = parser.parse_args(argv)
    if not args.comm_range >= 0:
        parser.error(f"--comm-range must be >= 0 metres, got {args.comm_range}")
    try:
        planner_settings = dict(map(parse_override, args.planner))
        CPU_PRESET.planner.replace(**planner_settings)
    except (ConfigError, TypeError) as err:
        parser.error(f"--planner: {err}")
    try:
        reward = FigureEightPlannerReward(**dict(map(parse_override, args.reward)))
    except ConfigError as err:
        parser.error(f"--reward: {err}")
    if any(p.startswith("learned") for p in args.policies) and (
        args.run is None or not (Path(args.run) / "config.yaml").is_file()
    ):
        parser.error(f"--policies learned needs --run RUN_DIR of a MA-PETS run, got {args.run}")
    torch.set_num_threads(1)
    print(f"# {machine_line()}")
    rows = []
    for name in args.policies:
        for seed in args.seeds:
            row = run_episode(
                name, seed, args.horizon, reward, args.scenario, args.run, tuple(args.set),
                args.comm_range, anchor_candidates=args.anchor_candidates,
                keep_best=args.keep_best, **planner_settings,
            )  # fmt: skip
            rows.append(row)
            print(json.dumps(row), flush=True)
    header = " | ".join(CLASSES)
    print(
        f"\n| policy | seeds | safety | agility [m/step] | crashes / 22 | {header} | "
        "plans sent / step |"
    )
    print("|---|---|---|---|---|" + "---|" * (len(CLASSES) + 1))
    for name in args.policies:
        group = [r for r in rows if r["policy"] == name]
        total: Counter = Counter()
        for r in group:
            total.update(r["classes"])
        n = len(group)
        cells = " | ".join(f"{total[c] / n:.1f}" for c in CLASSES)
        print(
            f"| {name} | {n} | {np.mean([r['safety'] for r in group]):.3f} | "
            f"{np.mean([r['agility'] for r in group]):.3f} | "
            f"{np.mean([r['crashes'] for r in group]):.1f} | {cells} | "
            f"{np.mean([r['plan_messages'] for r in group]):.1f} |"
        )
    if args.out is not None:
        tmp = args.out.with_suffix(".tmp")
        tmp.write_text(json.dumps(rows, indent=1))
        tmp.replace(args.out)
    return rows


if __name__ == "__main__":
    from mapets_rl import quiet_dependencies

    quiet_dependencies()
    main()
