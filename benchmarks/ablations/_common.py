"""What the MA-PETS ablation scripts share: the command line, the two scales, running the
sweep (:func:`mapets_rl.app.sweep.run_sweep`), and the table of one swept field.

Every script sweeps one MA-PETS config field on the single-lane figure-eight (8 CAVs) over
seeds; each trial is a normal run directory under ``OUT/trials`` (an interrupted script resumes
when run again), ``OUT/summary`` holds compare's learning curves (bootstrap 95% bands over seeds,
grouped by the swept field) and ``OUT/table.md`` the script's table.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import torch

from mapets_rl.app.sweep import SweepResult, SweepSpec, run_sweep
from mapets_rl.experiment import atomic_write_text, read_results
from mapets_rl.machine import machine_line
from mapets_rl.statistics import mean_ci95

SCALES: dict[str, list[str]] = {
    # the cpu preset (w=25, Q=32, X=4, Y=2, P=5, B=5, 3x64, 30 epochs), the paper's scenario
    "cpu": ["preset=cpu"],
    # Table II unchanged: w=25, Q=400, X=40, Y=5, P=20, B=5, 3x300, 5 epochs; 15 episodes
    "paper": ["preset=paper", "episodes=15"],
}
"""Overrides of every trial at each scale (scripts add their episode budget for ``cpu``)."""
METRICS = ["agility", "safety", "transitions_shared", "clique_cover_number"]


def parser(doc: str, name: str) -> argparse.ArgumentParser:
    """The options every ablation script takes."""
    p = argparse.ArgumentParser(
        description=doc.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter
    )
    p.add_argument("--scale", choices=sorted(SCALES), default="cpu", help="cpu (default) or paper")
    p.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2], help="seeds (default 0 1 2)")
    p.add_argument("--out", type=Path, default=Path(f"outputs/ablations/{name}"))
    p.add_argument("--backend", choices=["local", "ray"], default="local")
    p.add_argument("--address", default=None, metavar="HOST:PORT", help="Ray cluster to join")
    p.add_argument("--cpus-per-trial", type=float, default=1.0)
    p.add_argument("--gpus-per-trial", type=float, default=0.0)
    p.add_argument(
        "--set",
        nargs="*",
        default=[],
        metavar="key=value",
        help="further overrides of every trial, e.g. episodes=2 env_config.horizon=20 "
        "for a smoke run",
    )
    return p


def run(
    args: argparse.Namespace, grid: Mapping[str, list[Any]], cpu_overrides: Sequence[str]
) -> SweepResult:
    """Sweep ``grid`` x ``args.seeds`` for MA-PETS on the figure-eight at ``args.scale``;
    exits with 1 (after the others finished) when a trial failed."""
    print(f"# {machine_line()}", flush=True)
    overrides = [*SCALES[args.scale], *(cpu_overrides if args.scale == "cpu" else []), *args.set]
    spec = SweepSpec(
        recipe="mapets",
        env="figure-eight",
        seeds=args.seeds,
        out=args.out,
        grid=dict(grid),
        overrides=overrides,
        backend=args.backend,
        address=args.address,
        cpus_per_trial=args.cpus_per_trial,
        gpus_per_trial=args.gpus_per_trial,
        source="train",
        x="episode",
        metrics=METRICS,
    )
    result = run_sweep(spec, echo=lambda line: print(line, flush=True))
    if result.failed:
        print(f"failed trials: {result.failed} (see OUT/trials/<id>/error.txt)", file=sys.stderr)
    return result


def episodes(run_dir: Path) -> dict[int, dict[str, float]]:
    """``{episode: metrics}`` of a MA-PETS run directory's training entries."""
    return {int(e["metrics"]["episode"]): e["metrics"] for e in read_results(run_dir)["train"]}


def _order(value: Any) -> tuple[int, float, str]:
    """Sort key of grid values: numbers by value, then anything else by its JSON text."""
    if isinstance(value, (int, float)) and not isinstance(value, bool):
        return (0, float(value), "")
    return (1, 0.0, json.dumps(value, sort_keys=True))


def _per_seed(runs: list[dict], metric: str, eps: range) -> list[float]:
    """Per run, the mean of ``metric`` over episodes ``eps`` (none when ``eps`` is empty)."""
    return [sum(r[k][metric] for k in eps) / len(eps) for r in runs] if eps else []


def _cell(values: list[float]) -> str:
    """``mean ± 95% CI half-width`` of ``values``, ``-`` when there are none."""
    if not values:
        return "-"
    mean, half = mean_ci95(values)
    return f"{mean:.3f} ± {half:.3f}"


def field_table(
    result: SweepResult,
    key: str,
    label: str,
    extra: Callable[[Any], list[str]] | None = None,
    extra_header: Sequence[str] = (),
) -> str:
    """Markdown table, one row per value of grid ``key``: seeds, episodes, agility and safety
    over the last three episodes (mean ± 95% CI over seeds of the per-seed means), safety over
    episodes 2..4 (early learning), and per-episode means over all planned episodes of the
    transitions shared and the clique cover number; ``extra(value)`` adds cells."""
    rows: dict[str, dict[str, Any]] = {}
    for trial in result.trials:
        if result.records[trial.id]["state"] != "done":
            continue
        value = trial.values[key]
        row = rows.setdefault(json.dumps(value), {"value": value, "runs": []})
        row["runs"].append(episodes(trial.run_dir))
    header = [
        label,
        "seeds",
        "episodes",
        "agility, last 3 [m/step]",
        "safety, last 3",
        "safety, ep. 2-4",
        "transitions shared / episode",
        "clique cover number / episode",
        *extra_header,
    ]
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    for row in sorted(rows.values(), key=lambda r: _order(r["value"])):
        runs = row["runs"]
        last = min(max(r) for r in runs)
        tail = range(max(1, last - 2), last + 1)
        early = range(2, min(4, last) + 1)

        planned = [k for k in range(1, last + 1) if all(not r[k]["random"] for r in runs)]
        shared = [r[k]["transitions_shared"] for r in runs for k in range(1, last + 1)]
        chi = [r[k]["clique_cover_number"] for r in runs for k in planned]
        lines.append(
            "| "
            + " | ".join(
                [
                    f"{row['value']}",
                    str(len(runs)),
                    str(last),
                    _cell(_per_seed(runs, "agility", tail)),
                    _cell(_per_seed(runs, "safety", tail)),
                    _cell(_per_seed(runs, "safety", early)),
                    f"{torch.tensor(shared).mean():.1f}",
                    f"{torch.tensor(chi).float().mean():.2f}" if chi else "-",
                    *(extra(row["value"]) if extra else []),
                ]
            )
            + " |"
        )
    return "\n".join(lines) + "\n"


def write_table(args: argparse.Namespace, title: str, table: str, result: SweepResult) -> None:
    """Print and write ``OUT/table.md`` (title, scale, the table, the plot's path)."""
    plot = result.summary.get("plot")
    text = (
        f"# {title}\n\nscale `{args.scale}`, seeds {args.seeds}, overrides "
        f"{' '.join(args.set) or '(none)'}\n\n{table}\n"
        + (f"Learning curves: `{plot}`\n" if plot else "")
    )
    atomic_write_text(args.out / "table.md", text)
    print(text, end="")
