"""Ablation: trajectory-sampling particles P in {5, 10, 20} around the cpu preset (MA-PETS paper
Fig. 10: more particles estimate the return better and improve agility).

    python benchmarks/ablations/particles.py [--scale cpu|paper] [--seeds 0 1 2]
        [--backend local|ray] [--out outputs/ablations/particles] [--set key=value ...]

Scale ``cpu`` (default): the cpu preset with P varied (w=25, Q=32, X=4, Y=2, B=5, 3x64),
d = 100, 8 CAVs, 200-step episodes, 10 episodes per run: 3 values x 3 seeds = 9 runs, about
40-70 min on two cores (P=20 plans ~4x longer than P=5). Scale ``paper``: Table II sizes
with P varied, 15 episodes. Smoke run: ``--seeds 0 --set episodes=2 env_config.horizon=20``.

Writes ``OUT/table.md`` and ``OUT/summary/learning_curves.png`` (bootstrap 95% bands over seeds).
"""

from __future__ import annotations

from _common import field_table, parser, run, write_table


def main() -> None:
    args = parser(__doc__, "particles").parse_args()
    result = run(args, {"planner.particles": [5, 10, 20]}, ["episodes=10"])
    table = field_table(result, "planner.particles", "P")
    write_table(args, "Particles P (paper Fig. 10)", table, result)
    raise SystemExit(1 if result.failed else 0)


if __name__ == "__main__":
    main()
