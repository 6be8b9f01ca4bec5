"""MA-PETS on the single-lane figure-eight (paper sec. VI-B, Fig. 3 and Fig. 5 analogue).

Trains MA-PETS with 8 CAVs for ``--episodes`` episodes, for every communication range of
``--ranges`` (default d = 100 m, the paper's setting, and d = 0, independent learners), every
observation option of ``--observations`` (default ``crossing``, the library's default, and
``paper``, the paper's 7 features) and every seed of ``--seeds``; then prints a per-episode table
of agility and safety (mean +- std over seeds), the paper's two claims checked on the runs
(safety over episodes 13-15; d = 100 ahead of d = 0 over episodes 2-8, with the seeds' spread;
crashes over episodes 2-15) and writes ``table.md``, ``summary.json`` and
``learning_curves.png`` to ``--out``.

Each run lives in ``OUT/d<range>_seed<seed>/`` (config.yaml, results.json, checkpoints, CSV
logs); an interrupted sweep resumes every unfinished run from its latest checkpoint when the
same command is run again. Several processes can share one ``--out`` (e.g. one per range);
``--report-only`` then aggregates what has finished.

    python examples/mapets_figure_eight.py               # 3 seeds x d in {100, 0} x 2 options
    python examples/mapets_figure_eight.py --ranges 100 --seeds 0 --observations crossing
    python examples/mapets_figure_eight.py --report-only             # table + plot only
    python examples/mapets_figure_eight.py --set epochs=5 --out DIR  # one change at a time

Default sizes are the ``cpu`` preset of :class:`recipes.mapets.MAPETSConfig` (the paper's
planner needs a GPU); ``--preset paper`` uses Table II.
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

from mapets_rl.experiment import (  # noqa: E402
    atomic_savefig,
    atomic_write_text,
    latest_checkpoint,
    mean_ci95,
    read_results,
)
from recipes.mapets import MAPETS, MAPETSConfig  # noqa: E402

METRICS = ("agility", "safety")


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
            comm_range=comm_range,
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


def collect(out: Path) -> dict[str, dict[int, dict[int, dict[str, float]]]]:
    """``{"<observation> d=<range>": {seed: {episode: metrics}}}`` of every run under ``out``."""
    runs: dict[str, dict[int, dict[int, dict[str, float]]]] = {}
    for path in sorted(out.glob("*/d*_seed*"), key=lambda p: (p.parent.name, p.name)):
        if not (path / "results.json").is_file():
            continue
        results = read_results(path)
        comm_range = float(results["config"]["comm_range"])
        episodes = {
            int(e["metrics"]["episode"]): e["metrics"] for e in results["evaluations"]
        }
        runs.setdefault(f"{path.parent.name} d={comm_range:g}", {})[int(results["seed"])] = (
            episodes
        )
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


def summarise(runs: dict) -> dict[str, dict[str, list]]:
    """Per group and metric: per-episode mean, std, CI95 half-width and seed count."""
    summary: dict[str, dict[str, list]] = {}
    for group, seeds in runs.items():
        last = max(max(eps) for eps in seeds.values())
        entry: dict[str, list] = {"episode": list(range(1, last + 1)), "n": []}
        for metric in METRICS:
            means, stds, halves = [], [], []
            for episode in entry["episode"]:
                values = [eps[episode][metric] for eps in seeds.values() if episode in eps]
                mean, half = mean_ci95(values) if values else (math.nan, math.nan)
                var = (
                    sum((v - mean) ** 2 for v in values) / (len(values) - 1)
                    if len(values) > 1
                    else 0.0
                )
                means.append(mean)
                stds.append(math.sqrt(var))
                halves.append(half)
            entry[f"{metric}_mean"], entry[f"{metric}_std"] = means, stds
            entry[f"{metric}_ci95"] = halves
        entry["n"] = [
            sum(episode in eps for eps in seeds.values()) for episode in entry["episode"]
        ]
        summary[group] = entry
    return summary


def table(summary: dict[str, dict[str, list]]) -> str:
    """Markdown table: one row per episode, agility and safety per group (mean +- std, n)."""
    ranges = list(summary)
    header = "| episode | " + " | ".join(
        f"agility {d} | safety {d}" for d in ranges
    ) + " |"
    lines = [header, "|" + "---|" * (1 + 2 * len(ranges))]
    last = max(len(s["episode"]) for s in summary.values())
    for k in range(last):
        cells = [str(k + 1)]
        for d in ranges:
            s = summary[d]
            if k < len(s["episode"]):
                for metric in METRICS:
                    cells.append(
                        f"{s[f'{metric}_mean'][k]:.3f} +- {s[f'{metric}_std'][k]:.3f} "
                        f"(n={s['n'][k]})"
                    )
            else:
                cells += ["", ""]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def plot(summary: dict[str, dict[str, list]], path: Path) -> None:
    fig, axes = plt.subplots(1, 2, figsize=(10, 3.6))
    for d, s in summary.items():
        for ax, metric in zip(axes, METRICS, strict=True):
            mean, half = s[f"{metric}_mean"], s[f"{metric}_ci95"]
            line = ax.plot(s["episode"], mean, marker="o", label=d)[0]
            lo = [m - (h if math.isfinite(h) else 0.0) for m, h in zip(mean, half, strict=True)]
            hi = [m + (h if math.isfinite(h) else 0.0) for m, h in zip(mean, half, strict=True)]
            ax.fill_between(s["episode"], lo, hi, color=line.get_color(), alpha=0.2)
    axes[0].set_ylabel("agility [m/step]")
    axes[1].set_ylabel("safety")
    for ax in axes:
        ax.set_xlabel("episode")
        ax.grid(alpha=0.3)
        ax.legend()
    fig.suptitle("MA-PETS, figure-eight, 8 CAVs (mean and 95% CI over seeds)")
    fig.tight_layout()
    atomic_savefig(fig, path)
    plt.close(fig)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--episodes", type=int, default=15, help="K (paper: 15)")
    parser.add_argument("--ranges", type=float, nargs="+", default=[100.0, 0.0],
                        help="communication ranges d in metres")
    parser.add_argument("--observations", nargs="+", default=["crossing", "paper"],
                        choices=["crossing", "paper"], help="figure-eight observation options")
    parser.add_argument("--cavs", type=int, default=8, help="CAVs I (paper: 8)")
    parser.add_argument("--horizon", type=int, default=200, help="steps per episode H")
    parser.add_argument("--preset", default="cpu", choices=["cpu", "paper"])
    parser.add_argument("--threads", type=int, default=1, help="torch threads per run")
    parser.add_argument("--set", nargs="*", default=[], metavar="key=value",
                        help="further MAPETSConfig overrides of new runs, e.g. "
                        "epochs=5 horizon=10")
    parser.add_argument("--out", type=Path, default=Path("outputs/mapets_figure_eight"))
    parser.add_argument("--report-only", action="store_true",
                        help="only aggregate the runs already in --out")
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
    runs = collect(args.out)
    if not runs:
        raise SystemExit(f"no finished episodes under {args.out}")
    summary = summarise(runs)
    text = table(summary) + "\n" + claims(runs)
    print(text, end="")
    atomic_write_text(args.out / "table.md", text)
    atomic_write_text(args.out / "summary.json", json.dumps(summary, indent=1))
    plot(summary, args.out / "learning_curves.png")
    print(f"wrote {args.out / 'table.md'}, {args.out / 'summary.json'} and "
          f"{args.out / 'learning_curves.png'}")


if __name__ == "__main__":
    main()
