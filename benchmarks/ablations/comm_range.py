"""Ablation: communication range d in {0, 50, 100, 150, 200} m (MA-PETS paper Fig. 5 learning
curves, Table III transitions shared, Fig. 7 clique cover number), with learning agents.

    python benchmarks/ablations/comm_range.py [--scale cpu|paper] [--seeds 0 1 2]
        [--backend local|ray] [--out outputs/ablations/comm_range] [--set key=value ...]

Scale ``cpu`` (default): the cpu preset (w=25, Q=8, X=4, Y=2, P=5, B=5, 3x64), 8 CAVs,
200-step episodes, 10 episodes per run: 5 ranges x 3 seeds = 15 runs of ~30 s per planned
episode, about 40-60 min on two cores (two trials at a time). Scale ``paper``: Table II sizes
and 15 episodes, unchanged (a GPU per trial: ``--backend ray --gpus-per-trial 1 --set
device=cuda``). Smoke run: ``--seeds 0 --set episodes=2 env_config.horizon=20``.

Writes ``OUT/table.md`` (per d: agility and safety over the last three episodes, early
safety, transitions shared and clique cover number per episode, the paper's Table III),
``OUT/comm_overhead.png`` (transitions shared and clique cover number against d) and
``OUT/summary/learning_curves.png`` (per-episode curves, bootstrap 95% bands over seeds).
"""

from __future__ import annotations

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
from _common import episodes, field_table, parser, run, write_table  # noqa: E402

from mapets_rl.experiment import atomic_savefig  # noqa: E402
from mapets_rl.plotting import draw_band  # noqa: E402
from mapets_rl.statistics import bootstrap_interval  # noqa: E402

RANGES = [0, 50, 100, 150, 200]
PAPER_TABLE_III = {0: 0.0, 50: 330.13, 100: 1866.0, 150: 6139.7, 200: 10961.06}
"""MA-PETS paper Table III: transitions exchanged per episode against d (m)."""


def plot(result, path) -> None:
    """Transitions shared per episode (ours and the paper's) and clique cover number (every
    planned episode's, and the mean) against d; the means over seeds (of each seed's mean over
    its episodes) with their bootstrap 95% bands (:func:`mapets_rl.plotting.draw_band`)."""
    by_d: dict[float, list[list[dict]]] = {}  # d -> per seed, its episodes' metrics
    for trial in result.trials:
        if result.records[trial.id]["state"] == "done":
            by_d.setdefault(trial.values["comm.comm_range"], []).append(
                list(episodes(trial.run_dir).values())
            )
    ds = sorted(by_d)

    def per_seed_means(metric: str, planned_only: bool) -> list[tuple[float, list[float]]]:
        """``(d, each seed's mean of metric over its (planned) episodes)`` of the ds that have
        such episodes."""
        out = []
        for d in ds:
            seeds = [
                [m[metric] for m in eps if not (planned_only and m["random"])] for eps in by_d[d]
            ]
            means = [sum(v) / len(v) for v in seeds if v]
            if means:
                out.append((d, means))
        return out

    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(10, 4), layout="constrained")
    for ax, metric, planned_only, kwargs in (
        (ax1, "transitions_shared", False, {"label": "ours (learning CAVs)"}),
        (
            ax2,
            "clique_cover_number",
            True,
            {"color": "tab:red", "label": "mean over seeds (planned episodes)"},
        ),
    ):
        points = per_seed_means(metric, planned_only)
        stats = [bootstrap_interval(seeds) for _, seeds in points]
        several = all(len(seeds) > 1 for _, seeds in points)
        draw_band(
            ax,
            [d for d, _ in points],
            [s.estimate for s in stats],
            [s.low for s in stats] if several else None,
            [s.high for s in stats] if several else None,
            metric=metric,
            marker="o",
            **kwargs,
        )
    ax1.plot(list(PAPER_TABLE_III), list(PAPER_TABLE_III.values()), "s--", label="paper Table III")
    ax1.set(xlabel="communication range d [m]", ylabel="transitions shared per episode")
    ax1.legend()
    for d in ds:
        chi = [m["clique_cover_number"] for eps in by_d[d] for m in eps if not m["random"]]
        ax2.scatter([d] * len(chi), chi, s=10, alpha=0.3, color="tab:blue")
    ax2.set(xlabel="communication range d [m]", ylabel="minimum clique cover number")
    ax2.legend()
    fig.suptitle("MA-PETS, figure-eight, 8 CAVs: communication overhead (cf. Table III, Fig. 7)")
    atomic_savefig(fig, path, dpi=110)
    plt.close(fig)


def main() -> None:
    args = parser(__doc__, "comm_range").parse_args()
    result = run(args, {"comm.comm_range": RANGES}, ["episodes=10"])
    table = field_table(
        result,
        "comm.comm_range",
        "d [m]",
        extra=lambda d: [f"{PAPER_TABLE_III.get(d, float('nan')):g}"],
        extra_header=["paper Table III"],
    )
    if any(r["state"] == "done" for r in result.records.values()):
        plot(result, args.out / "comm_overhead.png")
    write_table(args, "Communication range d (paper Fig. 5, Table III, Fig. 7)", table, result)
    raise SystemExit(1 if result.failed else 0)


if __name__ == "__main__":
    main()
