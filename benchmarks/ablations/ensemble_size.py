"""Ablation: ensemble size B in {1, 5, 10} around the cpu preset (MA-PETS paper Fig. 9: a
larger B regularises learning and improves agility, with diminishing returns).

    python benchmarks/ablations/ensemble_size.py [--scale cpu|paper] [--seeds 0 1 2]
        [--backend local|ray] [--out outputs/ablations/ensemble_size] [--set key=value ...]

Scale ``cpu`` (default): the cpu preset with B varied and P = 10 particles (``ts_inf`` needs P
to be a multiple of B; the preset's P = 5 is not one of 10), d = 100, 8 CAVs, 200-step
episodes, 10 episodes per run: 3 sizes x 3 seeds = 9 runs, about 40-60 min on two cores.
Scale ``paper``: Table II sizes (P = 20) with B varied, 15 episodes. Smoke run:
``--seeds 0 --set episodes=2 env_config.horizon=20``.

Writes ``OUT/table.md`` and ``OUT/summary/learning_curves.png`` (bootstrap 95% bands over seeds).
"""

from __future__ import annotations

from _common import field_table, parser, run, write_table


def main() -> None:
    args = parser(__doc__, "ensemble_size").parse_args()
    cpu = ["episodes=10", "planner.particles=10"]
    result = run(args, {"model.ensemble_size": [1, 5, 10]}, cpu)
    table = field_table(result, "model.ensemble_size", "B")
    write_table(args, "Ensemble size B (paper Fig. 9)", table, result)
    raise SystemExit(1 if result.failed else 0)


if __name__ == "__main__":
    main()
