"""The safety-agility frontier of MA-PETS' planner on the figure-eight (issue 33).

Each point is one setting of the planner reward's margins (``headway`` x ``lane_change_gap``;
``FigureEightPlannerReward``) and one planner, driven over the same seeds by the episode loop
of ``multilane_diagnosis.py`` (``benchmarks/_common.py``; 400 steps, the recipe's scenario
defaults, cpu-preset CEM with iCEM's anchors and keep-best as in the recipe): its mean safety
and agility (paper eqs. 27-28) with 95% percentile-bootstrap intervals over the seeds. Planners:

- ``oracle``: the exact own-motion model, every other vehicle at constant speed;
- ``oracle-shared``: the same with plan sharing within ``--comm-range`` (``comm.share_plans``):
  the neighbouring CAVs' broadcast plans replace their constant-speed guess;
- ``learned`` / ``learned-shared``: a trained MA-PETS run's planner (``--run RUN_DIR``).

(The oracle told its neighbours' actual futures, ``oracle-exact``, was a planner of this script
at commit 00fe880, retired with ``benchmarks/exact_futures.py``: ``docs/results/history.md``.)

Each row also gives the human drivers' mean distance per step over the same episodes: an upper
bound the CAVs cannot beat for long on one lane.

Episodes are appended to ``OUT/rows.jsonl`` as they finish and the ones found there are not run
again (a stopped sweep resumes). The table and ``OUT/frontier.png`` are written at the end.

    python benchmarks/safety_agility_frontier.py --out OUT \\
        [--scenario figure-eight-multilane] [--policies oracle oracle-shared] \\
        [--headway 0 0.25 0.5] [--lane-change-gap 4 8] [--seeds 0 1 2 3 4 5] [--env n_hvs=0]

``--env key=value`` changes the scenario for every point (e.g. ``n_hvs=0``: no human drivers,
to see what they cost); rows remember it, and a sweep resumes only rows of the same scenario.
"""

from __future__ import annotations

import argparse
import itertools
import json
import re
from pathlib import Path

import numpy as np
import torch
from _common import POLICIES, SCENARIO, run_episode

from mapets_rl.config import ConfigError, parse_override
from mapets_rl.envs import make_env
from mapets_rl.envs.figure_eight import FigureEightPlannerReward
from mapets_rl.experiment import read_results
from mapets_rl.machine import machine_line
from mapets_rl.planning import CPU_PRESET
from mapets_rl.statistics import bootstrap_interval

PLANNERS = tuple(p for p in POLICIES if p.startswith(("oracle", "learned")) and "keep" not in p)
TARGETS = {"figure-eight-multilane": (0.97, 0.65), "figure-eight": (0.99, 0.8)}
"""Issue 33's targets (safety, agility [m/step]) per scenario."""


def key(row: dict) -> tuple:
    return (row["policy"], row["headway"], row["lane_change_gap"], row["seed"])


def scenario_tag(scenario: str, env_config: dict) -> str:
    """The scenario and its changes, as rows record them."""
    return " ".join([scenario, *(f"{k}={v}" for k, v in sorted(env_config.items()))])


def load_rows(path: Path) -> list[dict]:
    """The episodes already run (a torn last line from a stopped run is dropped)."""
    if not path.is_file():
        return []
    rows = []
    for line in path.read_text().splitlines():
        try:
            rows.append(json.loads(line))
        except json.JSONDecodeError:
            continue
    return rows


def summarise(rows: list[dict]) -> list[dict]:
    """Per (policy, headway, lane_change_gap): means and 95% bootstrap intervals."""
    groups: dict[tuple, list[dict]] = {}
    for row in rows:
        groups.setdefault(key(row)[:3], []).append(row)
    out = []
    for (policy, headway, gap), group in sorted(groups.items()):
        point = {"policy": policy, "headway": headway, "lane_change_gap": gap, "seeds": len(group)}
        for metric, bounds in (("safety", (0.0, 1.0)), ("agility", (0.0, np.inf))):
            point[metric] = bootstrap_interval([r[metric] for r in group], bounds=bounds)
        point["crashes"] = float(np.mean([r["crashes"] for r in group]))
        point["human_agility"] = float(np.mean([r["human_agility"] for r in group]))
        point["plan_messages"] = float(np.mean([r["plan_messages"] for r in group]))
        out.append(point)
    return out


TRAINING_EPISODES = 3
"""A run without evaluations of safety and agility (MA-PETS, whose planner drives the same way in
training and evaluation) is scored by the mean of its last this many training episodes: the
issue's episodes 13-15 of 15."""


def baseline_points(run_dirs: list[Path], scenario: str) -> list[dict]:
    """One point per family of trained runs ``run_dirs`` (a family: the directory names without
    their ``_seedN`` / ``_sN`` suffix, e.g. ``mappo_seed0``, ``mappo_seed1`` of
    ``examples/baselines_figure_eight.py``): each run's safety and agility from its last
    evaluation, or, for a run with none (MA-PETS), the mean of its last
    :data:`TRAINING_EPISODES` training episodes; means and 95% bootstrap intervals over the
    family's runs (seeds), and the frames they trained for. ValueError naming the run when it
    is not a run of ``scenario`` or has no entry with both metrics."""
    groups: dict[str, list[dict]] = {}
    for run in run_dirs:
        results = read_results(run)
        if results["env"] != scenario:
            raise ValueError(f"--baselines: {str(run)!r} is a run of {results['env']!r}, "
                             f"not of {scenario!r}")  # fmt: skip
        wanted = {"safety", "agility"}
        evaluations = [e for e in results["evaluations"] if wanted <= set(e["metrics"])]
        episodes = [e for e in results["train"] if wanted <= set(e["metrics"])]
        if evaluations:
            entry = {"frames": evaluations[-1]["frames"], **evaluations[-1]["metrics"]}
        elif episodes:
            last = episodes[-TRAINING_EPISODES:]
            entry = {"frames": last[-1]["frames"]}
            entry.update({m: float(np.mean([e["metrics"][m] for e in last])) for m in wanted})
        else:
            raise ValueError(f"--baselines: {str(run)!r} has no entry of safety and agility")
        groups.setdefault(re.sub(r"_s(eed)?\d+$", "", Path(run).name), []).append(entry)
    points = []
    for family, entries in sorted(groups.items()):
        point = {"policy": family, "seeds": len(entries), "frames": [e["frames"] for e in entries]}
        for metric, bounds in (("safety", (0.0, 1.0)), ("agility", (0.0, np.inf))):
            point[metric] = bootstrap_interval([e[metric] for e in entries], bounds=bounds)
        points.append(point)
    return points


def plot(points: list[dict], scenario: str, tag: str, path: Path, baselines: list[dict]) -> None:
    """Safety against agility, one marker per planner (and per baseline recipe), bars = 95%
    intervals."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 5))
    for n, policy in enumerate(sorted({p["policy"] for p in points})):
        mine = [p for p in points if p["policy"] == policy]
        x = np.array([p["agility"][0] for p in mine])
        y = np.array([p["safety"][0] for p in mine])
        xerr = np.array([[p["agility"][0] - p["agility"][1], p["agility"][2] - p["agility"][0]]
                         for p in mine]).T  # fmt: skip
        yerr = np.array([[p["safety"][0] - p["safety"][1], p["safety"][2] - p["safety"][0]]
                         for p in mine]).T  # fmt: skip
        ax.errorbar(x, y, xerr=xerr, yerr=yerr, fmt="osD^v"[n % 5], capsize=3, label=policy)
        for p, xi, yi in zip(mine, x, y, strict=True):
            ax.annotate(f"{p['headway']:g}s/{p['lane_change_gap']:g}m", (xi, yi), fontsize=7,
                        xytext=(3, 3), textcoords="offset points")  # fmt: skip
    for k, b in enumerate(baselines):  # trained runs: filled crosses, one colour per family
        ax.errorbar(
            [b["agility"][0]], [b["safety"][0]],
            xerr=[[b["agility"][0] - b["agility"][1]], [b["agility"][2] - b["agility"][0]]],
            yerr=[[b["safety"][0] - b["safety"][1]], [b["safety"][2] - b["safety"][0]]],
            fmt="X", color=plt.get_cmap("Dark2")(k % 8), capsize=3, markersize=8,
            label=f"{b['policy']} (trained, {max(b['frames'])} steps)",
        )  # fmt: skip
    safety, agility = TARGETS[scenario]
    ax.axhline(safety, color="grey", ls="--", lw=0.8)
    ax.axvline(agility, color="grey", ls="--", lw=0.8)
    ax.set_xlabel("agility [m/step] (speed limit: 1.39)")
    ax.set_ylabel("safety")
    ax.set_title(f"{tag}\nlabels: headway / lane-change gap; bars: 95% bootstrap", fontsize=9)
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def interval(value: tuple[float, float, float]) -> str:
    """``mean [low, high]`` of :func:`bootstrap_interval`, three decimals."""
    return f"{value[0]:.3f} [{value[1]:.3f}, {value[2]:.3f}]"


def main(argv: list[str] | None = None) -> list[dict]:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, required=True, help="folder of rows.jsonl and plot")
    parser.add_argument(
        "--scenario", default=SCENARIO, choices=("figure-eight", SCENARIO), help="the road"
    )
    parser.add_argument("--policies", nargs="+", choices=PLANNERS, default=["oracle"])
    parser.add_argument("--headway", nargs="+", type=float, default=[0.0, 0.25, 0.5])
    parser.add_argument("--lane-change-gap", nargs="+", type=float, default=[8.0])
    parser.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2, 3, 4, 5])
    parser.add_argument("--comm-range", type=float, default=100.0, help="*-shared: d [m]")
    parser.add_argument("--steps", type=int, default=400, help="steps per episode (>= 1)")
    parser.add_argument("--run", default=None, help="learned*: a MA-PETS run directory")
    parser.add_argument("--baselines", nargs="*", type=Path, default=[], metavar="RUN_DIR",
                        help="trained runs of the scenario, one point per family of seeds (the "
                        "last evaluation, or the last 3 training episodes of a MA-PETS run), "
                        "e.g. examples/baselines_figure_eight.py's")  # fmt: skip
    parser.add_argument("--env", nargs="*", default=[], metavar="key=value",
                        help="scenario config changes, e.g. n_hvs=0")  # fmt: skip
    parser.add_argument("--reward", nargs="*", default=[], metavar="key=value",
                        help="other FigureEightPlannerReward fields for every point, e.g. "
                        "collision_reward=-100 (rows record them)")  # fmt: skip
    parser.add_argument("--planner", nargs="*", default=[], metavar="key=value",
                        help="oracle*: PlannerConfig fields over the cpu preset's, e.g. "
                        "population=64 (rows record them)")  # fmt: skip
    args = parser.parse_args(argv)
    try:
        planner = {"anchor_candidates": True, "keep_best": True}
        planner.update(map(parse_override, args.planner))
        CPU_PRESET.planner.replace(**planner)
    except (ConfigError, TypeError) as err:
        parser.error(f"--planner: {err}")
    try:
        env_config = dict(map(parse_override, args.env))
        make_env(args.scenario, **env_config).close()  # a bad change fails before any episode
    except (ConfigError, ValueError) as err:
        parser.error(f"--env: {err}")
    tag = scenario_tag(args.scenario, {**env_config, "horizon": args.steps})
    if args.planner:
        tag += " | planner " + " ".join(sorted(args.planner))
    if args.reward:
        tag += " | reward " + " ".join(sorted(args.reward))
    if any(p.startswith("learned") for p in args.policies) and (
        args.run is None or not (Path(args.run) / "config.yaml").is_file()
    ):
        parser.error(f"learned policies need --run RUN_DIR of a MA-PETS run, got {args.run}")
    try:
        reward_fields = dict(map(parse_override, args.reward))
        if {"headway", "lane_change_gap"} & set(reward_fields):
            raise ConfigError("headway and lane_change_gap are the grid's: give them as options")
        FigureEightPlannerReward(**reward_fields)
    except (ConfigError, TypeError) as err:
        parser.error(f"--reward: {err}")
    for name in ("headway", "lane_change_gap"):
        try:  # every setting is checked before the first episode
            for value in getattr(args, name):
                FigureEightPlannerReward(**{name: value})
        except ValueError as err:
            parser.error(f"--{name.replace('_', '-')}: {err}")
    if not args.comm_range >= 0:
        parser.error(f"--comm-range must be >= 0 metres, got {args.comm_range}")
    if args.steps < 1:
        parser.error(f"--steps must be >= 1, got {args.steps}")
    try:
        baselines = baseline_points(args.baselines, args.scenario)
    except ValueError as err:
        parser.error(str(err))
    torch.set_num_threads(1)
    print(f"# {machine_line()}")
    args.out.mkdir(parents=True, exist_ok=True)
    path = args.out / "rows.jsonl"
    rows = [r for r in load_rows(path) if r.get("scenario") == tag]
    done = {key(r) for r in rows}
    grid = itertools.product(args.policies, args.headway, args.lane_change_gap, args.seeds)
    for policy, headway, gap, seed in grid:
        if (policy, headway, gap, seed) in done:
            continue
        reward = FigureEightPlannerReward(headway=headway, lane_change_gap=gap, **reward_fields)
        row = run_episode(
            policy, seed, args.steps, reward, args.scenario, args.run, (), args.comm_range,
            env_config, **planner,
        )  # fmt: skip
        row.update(headway=headway, lane_change_gap=gap, scenario=tag)
        with path.open("a") as out:
            out.write(json.dumps(row) + "\n")
        rows.append(row)
        print(json.dumps(row), flush=True)
    wanted = {(p, h, g) for p, h, g, _ in itertools.product(
        args.policies, args.headway, args.lane_change_gap, args.seeds)}  # fmt: skip
    points = [p for p in summarise(rows) if (p["policy"], p["headway"], p["lane_change_gap"])
              in wanted]  # fmt: skip
    print(
        "\n| planner | headway [s] | lane-change gap [m] | seeds | safety [95% CI] | "
        "agility [m/step] [95% CI] | crashes | humans' m/step | plans sent / step |"
    )
    print("|---|---|---|---|---|---|---|---|---|")
    for p in points:
        print(
            f"| {p['policy']} | {p['headway']:g} | {p['lane_change_gap']:g} | {p['seeds']} | "
            f"{interval(p['safety'])} | {interval(p['agility'])} | "
            f"{p['crashes']:.1f} | {p['human_agility']:.3f} | {p['plan_messages']:.1f} |"
        )
    for b in baselines:  # in the same table
        print(
            f"| {b['policy']} (trained {max(b['frames'])} steps) | - | - | {b['seeds']} | "
            f"{interval(b['safety'])} | {interval(b['agility'])} | - | - | - |"
        )
    plot(points, args.scenario, tag, args.out / "frontier.png", baselines)
    print(f"figure: {args.out / 'frontier.png'}")
    return points


if __name__ == "__main__":
    from mapets_rl import quiet_dependencies

    quiet_dependencies()
    main()
