"""Ablation: MPC horizon w in {10, 25, 40} steps around the cpu preset (MA-PETS paper's
horizon figure: safety grows with w up to ~25; too short or too long a horizon costs agility).

    python benchmarks/ablations/horizon.py [--scale cpu|paper] [--seeds 0 1 2]
        [--backend local|ray] [--out outputs/ablations/horizon] [--set key=value ...]

Scale ``cpu`` (default): the cpu preset with w varied (Q=32, X=4, Y=2, P=5, B=5, 3x64), d = 100,
8 CAVs, 200-step episodes, 10 episodes per run: 3 horizons x 3 seeds = 9 runs, about 30-50 min
on two cores (w=40 plans 1.6x longer than w=25). Scale ``paper``: Table II sizes with w varied,
15 episodes. Smoke run: ``--seeds 0 --set episodes=2 env_config.horizon=20``.

Writes ``OUT/table.md`` and ``OUT/summary/learning_curves.png`` (bootstrap 95% bands over seeds).
"""

from __future__ import annotations

from _common import field_table, parser, run, write_table


def main() -> None:
    args = parser(__doc__, "horizon").parse_args()
    result = run(args, {"planner.horizon": [10, 25, 40]}, ["episodes=10"])
    table = field_table(result, "planner.horizon", "w [steps of 0.1 s]")
    write_table(args, "MPC horizon w", table, result)
    raise SystemExit(1 if result.failed else 0)


if __name__ == "__main__":
    main()
