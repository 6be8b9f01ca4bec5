"""MA-PETS on the single-lane figure-eight (paper sec. VI-B, Fig. 3 and Fig. 5 analogue).

Trains MA-PETS with 8 CAVs for ``--episodes`` episodes, for every communication range of
``--ranges`` (default d = 100 m, the paper's setting, and d = 0, independent learners), every
observation option of ``--observations`` (default ``crossing``, the library's default, and
``paper``, the paper's 7 features) and every seed of ``--seeds``; then prints a per-episode table
of agility and safety (mean +- std over seeds), the paper's two claims checked on the runs
(safety over episodes 13-15; d = 100 ahead of d = 0 over episodes 2-8, with the seeds' spread;
crashes over episodes 2-15) and writes ``table.md`` (those two tables) to ``--out``. The
per-episode statistics and the plot come from :func:`mapets_rl.experiment.compare` on the
runs' training episodes, grouped by observation option and d (``learning_curves.png``,
``curves.json``, ``summary.json``, ``final_metrics.md`` in ``--out``); it refuses runs of
different scenarios (e.g. another ``--cavs``) in one ``--out``.

Each run lives in ``OUT/<observation>/d<range>_seed<seed>/`` (config.yaml, results.json,
checkpoints, CSV logs); an interrupted sweep resumes every unfinished run from its latest
checkpoint when the same command is run again. Several processes can share one ``--out`` (e.g.
one per range); ``--report-only`` then aggregates what has finished.

    python examples/mapets_figure_eight.py               # 3 seeds x d in {100, 0} x 2 options
    python examples/mapets_figure_eight.py --ranges 100 --seeds 0 --observations crossing
    python examples/mapets_figure_eight.py --report-only             # table + plot only
    python examples/mapets_figure_eight.py --set model.epochs=5 --out DIR  # one change

Default sizes are the ``cpu`` preset of :class:`recipes.mapets.MAPETSConfig` (the paper's
planner needs a GPU); ``--preset paper`` uses Table II.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from mapets_rl.experiment import (
    atomic_write_text,
    compare,
    latest_checkpoint,
    read_results,
)
from recipes.mapets import MAPETS, MAPETSConfig

METRICS = ("agility", "safety")
GROUP_BY = ["env_config.observation", "comm.comm_range"]
"""Config fields of the groups: observation option and communication range d."""


def run_dir(out: Path, observation: str, comm_range: float, seed: int) -> Path:
    return out / observation / f"d{comm_range:g}_seed{seed}"


def train_one(args: argparse.Namespace, observation: str, comm_range: float, seed: int) -> None:
    """Train (or resume) one run up to ``args.episodes`` episodes."""
    path = run_dir(args.out, observation, comm_range, seed)
    overrides = [f"episodes={args.episodes}"]
    if latest_checkpoint(path) is not None:
        exp = MAPETS.from_run_dir(path, overrides=overrides)
        if exp.episode >= args.episodes:
            print(f"{path}: done ({exp.episode} episodes)")
            return
        print(f"{path}: resuming at episode {exp.episode + 1}")
    else:
        config = MAPETSConfig(
            env_config={"n_cavs": args.cavs, "horizon": args.horizon, "observation": observation},
            seed=seed,
            episodes=args.episodes,
            comm={"comm_range": comm_range},
            preset=args.preset,
            num_threads=args.threads,
            progress=False,
        ).with_overrides(args.set)
        exp = MAPETS(config, path)

    def report(m: dict[str, float]) -> None:
        print(
            f"{observation} d={comm_range:g} seed={seed} episode {int(m['episode']):2d}: "
            f"agility {m['agility']:.3f} m/step, safety {m['safety']:.3f}, "
            f"collisions {int(m['collisions'])}, shared {int(m['transitions_shared'])}, "
            f"{m['step_time']:.2f} s/step",
            flush=True,
        )

    exp.train(on_episode_end=report)


def group_name(observation: str, comm_range: float) -> str:
    return f"{observation} d={comm_range:g}"


def collect(out: Path) -> tuple[list[Path], dict[str, dict[int, dict[int, dict[str, float]]]]]:
    """The run directories under ``out`` with finished episodes, and their episodes'
    metrics, ``{"<observation> d=<range>": {seed: {episode: metrics}}}``.

    Results files written before training and evaluation entries were kept apart hold the
    episodes under ``evaluations``; they are read as the training entries they are.
    """
    paths: list[Path] = []
    runs: dict[str, dict[int, dict[int, dict[str, float]]]] = {}
    for path in sorted(out.glob("*/d*_seed*"), key=lambda p: (p.parent.name, p.name)):
        if not (path / "results.json").is_file():
            continue
        results = read_results(path, legacy_as="train")
        if not results["train"]:
            continue
        paths.append(path)
        config = results["config"]
        comm_range = config["comm"]["comm_range"] if "comm" in config else config["comm_range"]
        group = group_name(config["env_config"]["observation"], float(comm_range))
        runs.setdefault(group, {})[int(results["seed"])] = {
            int(e["metrics"]["episode"]): e["metrics"] for e in results["train"]
        }
    return paths, runs


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
        "--observations",
        nargs="+",
        default=["crossing", "paper"],
        choices=["crossing", "paper"],
        help="figure-eight observation options",
    )
    parser.add_argument("--cavs", type=int, default=8, help="CAVs I (paper: 8)")
    parser.add_argument("--horizon", type=int, default=200, help="steps per episode H")
    parser.add_argument("--preset", default="cpu", choices=["cpu", "paper"])
    parser.add_argument("--threads", type=int, default=1, help="torch threads per run")
    parser.add_argument(
        "--set",
        nargs="*",
        default=[],
        metavar="key=value",
        help="further MAPETSConfig overrides of new runs, dotted for the planner / model / comm "
        "sections, e.g. model.epochs=5 planner.horizon=10",
    )
    parser.add_argument("--out", type=Path, default=Path("outputs/mapets_figure_eight"))
    parser.add_argument(
        "--report-only", action="store_true", help="only aggregate the runs already in --out"
    )
    args = parser.parse_args()
    for name in ("episodes", "cavs", "horizon", "threads"):
        if getattr(args, name) < 1:
            parser.error(f"--{name} must be >= 1, got {getattr(args, name)}")
    if any(d < 0 for d in args.ranges):
        parser.error(f"--ranges must be >= 0 metres, got {args.ranges}")
    args.out.mkdir(parents=True, exist_ok=True)
    if not args.report_only:
        for observation in args.observations:
            for seed in args.seeds:
                for comm_range in args.ranges:
                    train_one(args, observation, comm_range, seed)
    paths, runs = collect(args.out)
    if not paths:
        raise SystemExit(f"no finished episodes under {args.out}")
    try:
        out = compare(
            paths,
            args.out,
            list(METRICS),
            source="train",
            group_by=GROUP_BY,
            x="episode",
            legacy_as="train",
            title="MA-PETS, figure-eight",
        )
    except ValueError as err:  # e.g. runs of another --cavs or --horizon in the same --out
        raise SystemExit(f"cannot aggregate the runs under {args.out}: {err}") from None
    text = table(json.loads(out["curves"].read_text())) + "\n" + claims(runs)
    print(text, end="")
    atomic_write_text(args.out / "table.md", text)
    print(
        f"wrote {args.out / 'table.md'}, {out['plot']}, {out['curves']}, {out['summary']} "
        f"and {out['table']}"
    )


if __name__ == "__main__":
    main()
