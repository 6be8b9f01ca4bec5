"""Ablation: link-failure probability p in {0, 0.25, 0.5} at d = 100 m (MA-PETS paper Fig. 8).

    python benchmarks/ablations/link_failure.py [--scale cpu|paper] [--seeds 0 1 2]
        [--backend local|ray] [--out outputs/ablations/link_failure] [--set key=value ...]

Scale ``cpu`` (default): the cpu preset (w=25, Q=8, X=4, Y=2, P=5, B=5, 3x64), 8 CAVs,
200-step episodes, 10 episodes per run (as the other ablations; the paper runs 15):
3 probabilities x 3 seeds = 9 runs, about 25-40 min on two cores. Scale ``paper``: Table II
sizes, 15 episodes. Smoke run:
``--seeds 0 --set episodes=2 env_config.horizon=20``.

Writes ``OUT/table.md`` (per p: agility and safety over the last three episodes, early safety,
transitions shared and clique cover number per episode) and
``OUT/summary/learning_curves.png`` (per-episode curves, bootstrap 95% bands over seeds).
"""

from __future__ import annotations

from _common import field_table, parser, run, write_table


def main() -> None:
    args = parser(__doc__, "link_failure").parse_args()
    result = run(args, {"comm.p_fail": [0.0, 0.25, 0.5]}, ["episodes=10", "comm.comm_range=100"])
    table = field_table(result, "comm.p_fail", "p_fail")
    write_table(args, "Link failures at d = 100 m (paper Fig. 8)", table, result)
    raise SystemExit(1 if result.failed else 0)


if __name__ == "__main__":
    main()
