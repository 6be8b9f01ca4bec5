"""The coalition game of freeway-merge states, computed by simulation (issue 32 groundwork).

For ``--seeds`` episodes of ``freeway-merge`` (30 vehicles, ``--cavs`` of them CAVs), the CAVs
keep their lane up to each step of ``--steps``; at that state every coalition ``C`` of CAVs
plays the cooperative merge rule (``benchmarks/freeway_headroom.py``) while the others keep
their lane, each coalition on its own copy of the road (``shapley.simulated_game``), and
``v(C)`` is the system return over the rest of the episode. Per state: the cooperative gain
``v(N) - v(0)``, the additive prediction ``sum_i v({i}) - v(0)`` (what the game would be worth
if every CAV's yield counted alone), the exact Shapley value and how far it is from each CAV's
own marginal gain ``v({i}) - v(0)`` (Proposition 2: equal in an additive game), and whether the
game is convex (Theorem 2: the Shapley value is then in the core).

    PYTHONPATH=. python benchmarks/simulated_coalition_game.py [--seeds 10] [--cavs 8]
        [--steps 0 5 10 15]
"""

from __future__ import annotations

import argparse
import math
import statistics
import time

import torch
from freeway_headroom import CooperativeMerge
from tensordict import TensorDict

from mapets_rl.envs import make_env
from mapets_rl.envs.freeway import KL
from mapets_rl.envs.torch_freeway.simulator import BatchedFreeway
from mapets_rl.modules import ACTION, OBS
from mapets_rl.shapley.game import exact_shapley, is_convex
from mapets_rl.shapley.simulated import simulated_game


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--seeds", type=int, default=10)
    parser.add_argument("--cavs", type=int, default=8, help="CAVs of the 30 vehicles (<= 12)")
    parser.add_argument("--steps", nargs="+", type=int, default=[0, 5, 10, 15])
    args = parser.parse_args()
    if not 1 <= args.cavs <= 12:
        parser.error(f"--cavs must be in [1, 12] (2**cavs copies of a road), got {args.cavs}")
    if args.seeds < 1 or any(not 0 <= s < 40 for s in args.steps):
        parser.error("--seeds must be >= 1 and --steps in [0, 39]")
    torch.set_num_threads(1)
    config = make_env("freeway-merge", backend="torch", cav_ratio=args.cavs / 30).config
    rule = CooperativeMerge(3, math.inf, 60.0, 30.0, 15.0, 15.0, 1.5, torch.int64)

    def cooperative(observation: torch.Tensor, members: torch.Tensor) -> torch.Tensor:
        td = TensorDict({OBS: observation}, batch_size=observation.shape[:-2])
        return rule(td).get(ACTION).argmax(-1)

    n = int(config["n_cavs"])
    print(f"# freeway-merge, 30 vehicles, {n} CAVs, {2**n} coalitions per state, seeds "
          f"0..{args.seeds - 1}, states after {args.steps} keep-lane steps")  # fmt: skip
    print(
        "| step | cooperative gain v(N)-v(0) | additive prediction | gain / additive | "
        "max abs(phi_i - own gain_i) | convex games | seconds per game |"
    )
    print("|---|---|---|---|---|---|---|")
    for step in args.steps:
        gains, additive, gaps, convex, seconds = [], [], [], [], []
        for seed in range(args.seeds):
            sim = BatchedFreeway(config, True, 1, seed=seed)
            for _ in range(step):
                sim.step(torch.full((1, n), KL))
            start = time.perf_counter()
            values = simulated_game(sim, 0, cooperative).double()
            seconds.append(time.perf_counter() - start)
            singles = torch.stack([values[1 << i] for i in range(n)]) - values[0]
            phi = exact_shapley(values, n)
            gains.append(float(values[-1] - values[0]))
            additive.append(float(singles.sum()))
            gaps.append(float((phi - singles).abs().max()))
            convex.append(bool(is_convex(values, n, atol=1e-3)))
        ratio = [g / a for g, a in zip(gains, additive, strict=True) if abs(a) > 1e-9]
        print(
            f"| {step} | {statistics.mean(gains):+.1f} (sd {statistics.pstdev(gains):.1f}) | "
            f"{statistics.mean(additive):+.1f} (sd {statistics.pstdev(additive):.1f}) | "
            f"{statistics.median(ratio) if ratio else float('nan'):.2f} (median) | "
            f"{statistics.mean(gaps):.1f} (mean) | {sum(convex)}/{len(convex)} | "
            f"{statistics.median(seconds):.2f} |",
            flush=True,
        )


if __name__ == "__main__":
    from mapets_rl import quiet_dependencies

    quiet_dependencies()
    main()
