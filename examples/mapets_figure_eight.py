"""MA-PETS on the figure-eight (paper sec. VI-B: Figs. 3 and 5 on one lane, Fig. 4 on two).

Trains MA-PETS on ``--scenario`` (``figure-eight``: 8 CAVs, 200-step episodes;
``figure-eight-multilane``: the paper's second experiment, 2 lanes, 22 CAVs, 400-step episodes)
for ``--episodes`` episodes, for every communication range of
``--ranges`` (default d = 100 m, the paper's setting, and d = 0, independent learners), every
observation option of ``--observations`` (default ``crossing``, the library's default, and
``paper``, the paper's 7 features) and every seed of ``--seeds``; then prints a per-episode table
of agility and safety (mean +- std over seeds), the paper's two claims checked on the runs
(safety over episodes 13-15; d = 100 ahead of d = 0 over episodes 2-8, with the seeds' spread;
crashes over episodes 2-15) and writes ``table.md`` (those two tables) to ``--out``.

The runs are a sweep (:func:`mapets_rl.app.sweep.run_sweep`, what ``mapets-rl sweep``
runs): the grid ``env_config.observation`` x ``comm.comm_range`` x seeds, each run a directory
``OUT/trials/env_config.observation=<o>__comm.comm_range=<d>__seed=<s>/`` (config.yaml,
results.json, checkpoints, CSV logs), ``OUT/sweep.json`` their states, run two at a time on this
machine (``--backend ray`` for a Ray instance or cluster). An interrupted sweep resumes every
unfinished run from its latest checkpoint when the same command is run again; ``--report-only``
aggregates what has finished. The per-episode statistics and the plot come from
:func:`mapets_rl.app.comparison.compare` on the runs' training episodes, grouped by observation
option and d (``OUT/summary``: ``learning_curves.png``, ``curves.json``, ``summary.json``,
``final_metrics.md``).

    python examples/mapets_figure_eight.py               # 3 seeds x d in {100, 0} x 2 options
    python examples/mapets_figure_eight.py --scenario figure-eight-multilane  # paper Fig. 4
    python examples/mapets_figure_eight.py --ranges 100 --seeds 0 --observations crossing
    python examples/mapets_figure_eight.py --report-only             # table + plot only
    python examples/mapets_figure_eight.py --set model.epochs=5 --out DIR  # one change

Default sizes are the ``cpu`` preset of :class:`mapets_rl.recipes.mapets.MAPETSConfig` (the paper's
planner needs a GPU); ``--preset paper`` uses Table II.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from mapets_rl.app.sweep import (
    SweepSpec,
    plan_trials,
    read_trial_record,
    run_sweep,
    summarise,
)
from mapets_rl.experiment import atomic_write_text, read_results

METRICS = ("agility", "safety")
SCENARIO_DEFAULTS = {
    "figure-eight": {"cavs": 8, "horizon": 200, "observations": ["crossing", "paper"]},
    "figure-eight-multilane": {"cavs": 22, "horizon": 400, "observations": ["crossing"]},
}
"""Per scenario: the paper's CAVs and episode length, and the observation options compared."""


def group_name(observation: str, comm_range: float) -> str:
    return f"{observation} d={comm_range:g}"


def collect(paths: list[Path]) -> dict[str, dict[int, dict[int, dict[str, float]]]]:
    """The episodes' metrics of finished runs, ``{"<observation> d=<range>": {seed: {episode:
    metrics}}}``."""
    runs: dict[str, dict[int, dict[int, dict[str, float]]]] = {}
    for path in paths:
        results = read_results(path)
        config = results["config"]
        group = group_name(config["env_config"]["observation"], float(config["comm"]["comm_range"]))
        runs.setdefault(group, {})[int(results["seed"])] = {
            int(e["metrics"]["episode"]): e["metrics"] for e in results["train"]
        }
    return runs


def _per_seed_means(seeds: dict, metric: str, first: int, last: int) -> list[float]:
    """Mean of ``metric`` over episodes ``first..last`` of every seed that has them all."""
    out = []
    for eps in seeds.values():
        values = [eps[k][metric] for k in range(first, last + 1) if k in eps]
        if len(values) == last - first + 1:
            out.append(sum(values) / len(values))
    return out


def _mean(values: list[float]) -> str:
    return f"{sum(values) / len(values):.3f}" if values else "-"


def claims(runs: dict) -> str:
    """The paper's claims on these runs: late safety, sharing ahead early, crash counts.

    Per group: mean safety over episodes 13-15 (mean over seeds of the per-seed mean), mean
    safety over episodes 2-8 with the spread (min..max) of the per-seed means, and collisions
    summed over episodes 2-15 and seeds.
    """
    lines = [
        "| group | seeds | safety ep. 13-15 | safety ep. 2-8 (per-seed min..max) | "
        "agility ep. 13-15 [m/step] | collisions ep. 2-15 |",
        "|---|---|---|---|---|---|",
    ]
    for group, seeds in runs.items():
        late = _per_seed_means(seeds, "safety", 13, 15)
        early = _per_seed_means(seeds, "safety", 2, 8)
        agility = _per_seed_means(seeds, "agility", 13, 15)
        crashes = sum(
            eps[k]["collisions"] for eps in seeds.values() for k in range(2, 16) if k in eps
        )

        spread = f" ({min(early):.3f}..{max(early):.3f})" if early else ""
        lines.append(
            f"| {group} | {len(seeds)} | {_mean(late)} | {_mean(early)}{spread} | "
            f"{_mean(agility)} | {int(crashes)} |"
        )
    return "\n".join(lines) + "\n"


def table(curves: dict) -> str:
    """Markdown table: one row per episode, agility and safety per group (mean +- std over
    seeds, n seeds), from ``compare``'s ``curves.json``."""
    groups = {
        group_name(g["group"]["env_config.observation"], g["group"]["comm.comm_range"]): g
        for g in curves["groups"].values()
    }
    header = "| episode | " + " | ".join(f"agility {d} | safety {d}" for d in groups) + " |"
    lines = [header, "|" + "---|" * (1 + 2 * len(groups))]
    last = max(int(max(g["x"])) for g in groups.values())
    for episode in range(1, last + 1):
        cells = [str(episode)]
        for g in groups.values():
            if float(episode) not in g["x"]:
                cells += ["", ""]
                continue
            i = g["x"].index(float(episode))
            for metric in METRICS:
                stats = g["metrics"][metric]
                cells.append(f"{stats['mean'][i]:.3f} +- {stats['std'][i]:.3f} (n={g['n'][i]})")
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--episodes", type=int, default=15, help="K (paper: 15)")
    parser.add_argument(
        "--ranges",
        type=float,
        nargs="+",
        default=[100.0, 0.0],
        help="communication ranges d in metres",
    )
    parser.add_argument(
        "--scenario",
        default="figure-eight",
        choices=list(SCENARIO_DEFAULTS),
        help="one lane (paper Figs. 3, 5) or two lanes (paper Fig. 4)",
    )
    parser.add_argument(
        "--observations",
        nargs="+",
        default=None,
        choices=["crossing", "paper"],
        help="figure-eight observation options (default: both on one lane, crossing on two)",
    )
    parser.add_argument("--cavs", type=int, default=None, help="CAVs I (paper: 8 / 22)")
    parser.add_argument(
        "--horizon", type=int, default=None, help="steps per episode H (paper: 200 / 400)"
    )
    parser.add_argument("--preset", default="cpu", choices=["cpu", "paper"])
    parser.add_argument("--threads", type=int, default=1, help="torch threads (CPUs) per run")
    parser.add_argument(
        "--backend",
        choices=["local", "ray"],
        default="local",
        help="local: cpu_count // threads runs at a time on this machine; ray: Ray tasks",
    )
    parser.add_argument(
        "--set",
        nargs="*",
        default=[],
        metavar="key=value",
        help="further MAPETSConfig overrides of the runs, dotted for the planner / model / comm "
        "sections, e.g. model.epochs=5 planner.horizon=10",
    )
    parser.add_argument("--out", type=Path, default=Path("outputs/mapets_figure_eight"))
    parser.add_argument(
        "--report-only", action="store_true", help="only aggregate the runs already in --out"
    )
    args = parser.parse_args()
    defaults = SCENARIO_DEFAULTS[args.scenario]
    for name, value in defaults.items():
        if getattr(args, name) is None:
            setattr(args, name, value)
    for name in ("episodes", "cavs", "horizon", "threads"):
        if getattr(args, name) < 1:
            parser.error(f"--{name} must be >= 1, got {getattr(args, name)}")
    if any(d < 0 for d in args.ranges):
        parser.error(f"--ranges must be >= 0 metres, got {args.ranges}")
    spec = SweepSpec(
        recipe="mapets",
        env=args.scenario,
        seeds=args.seeds,
        out=args.out,
        grid={"env_config.observation": args.observations, "comm.comm_range": args.ranges},
        overrides=[
            f"episodes={args.episodes}",
            f"env_config.n_cavs={args.cavs}",
            f"env_config.horizon={args.horizon}",
            f"preset={args.preset}",
            f"num_threads={args.threads}",
            *args.set,
        ],
        backend=args.backend,
        cpus_per_trial=args.threads,
        metrics=list(METRICS),
        source="train",
        x="episode",
    )
    try:
        if args.report_only:
            _, trials = plan_trials(spec)
            paths = [
                t.run_dir
                for t in trials
                if (read_trial_record(t.run_dir) or {}).get("state") == "done"
            ]
            if not paths:
                raise SystemExit(f"no finished runs under {args.out}")
            out = summarise(spec, paths)
            failed = []
        else:
            result = run_sweep(spec)
            paths = [t.run_dir for t in result.trials if result.records[t.id]["state"] == "done"]
            if not result.summary:
                raise SystemExit(f"no summary of the runs under {args.out}: {result.summary_error}")
            out, failed = result.summary, result.failed
    except ValueError as err:  # a bad --set, or --out holding another sweep
        raise SystemExit(f"mapets_figure_eight: {err}") from None
    text = table(json.loads(out["curves"].read_text())) + "\n" + claims(collect(paths))
    print(text, end="")
    atomic_write_text(args.out / "table.md", text)
    print(
        f"wrote {args.out / 'table.md'}, {out['plot']}, {out['curves']}, {out['summary']} "
        f"and {out['table']}"
    )
    if failed:
        print(f"failed runs: {failed} (see OUT/trials/<id>/error.txt)", file=sys.stderr)
        raise SystemExit(1)


if __name__ == "__main__":
    from mapets_rl import quiet_dependencies

    quiet_dependencies()
    main()
