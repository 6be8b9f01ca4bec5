"""Communication overhead and clique cover number against the communication range d.

The MA-PETS paper's Table III (transitions exchanged per episode) and Fig. 7 (minimum clique
cover number chi_bar(G_{d,k}) over 15 episodes) on the single-lane figure-eight with 8 CAVs.

Protocol: scripted CAVs (``mapets_rl.envs.ScriptedCAVPolicy``) drive ``--episodes`` episodes;
every range d is evaluated on the same trajectories (a paired comparison). As in the paper
(sec. III-B), the exchange happens at the end of each episode over the graph of the **final
state**: ``CommunicationRange(d).episode_graph(rollout)`` links every CAV that drove in the
episode by its last driving position (a crashed CAV from its crash site). (With ``make_env`` the
per-step ``("next", "agents", "neighbors")`` of the final state is empty, because PettingZoo
removes all agents at truncation.) Each range has its own
:class:`~mapets_rl.comm.NeighbourDatasets` (capacity 2048 per agent) that stores the episode's
transitions of active CAVs and exchanges them over that graph. Overhead = transitions sent over
all links (one copy per receiver) and the bytes they take.

Run:  python examples/comm_overhead.py [--episodes 15] [--out outputs/comm_overhead]
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import torch  # noqa: E402
from tensordict import TensorDict  # noqa: E402

from mapets_rl.comm import CommunicationRange, NeighbourDatasets, clique_cover  # noqa: E402
from mapets_rl.envs import ScriptedCAVPolicy, make_env  # noqa: E402
from mapets_rl.experiment import atomic_savefig, atomic_write_text  # noqa: E402
from mapets_rl.plotting import draw_curve  # noqa: E402

RANGES = (0.0, 50.0, 100.0, 150.0, 200.0)
PAPER_TABLE_III = {0.0: 0.0, 50.0: 330.13, 100.0: 1866.0, 150.0: 6139.7, 200.0: 10961.06}


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--episodes", type=int, default=15, help="episodes (paper: 15)")
    parser.add_argument("--out", type=Path, default=Path("outputs/comm_overhead"))
    parser.add_argument("--ranges", type=float, nargs="+", default=list(RANGES))
    parser.add_argument("--p-fail", type=float, default=0.0, help="link failure probability")
    parser.add_argument("--n-cavs", type=int, default=8)
    parser.add_argument("--horizon", type=int, default=200, help="steps per episode (H)")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    if args.episodes < 1:
        parser.error(f"--episodes must be >= 1, got {args.episodes}")
    if any(d < 0 for d in args.ranges):
        parser.error(f"--ranges must be >= 0, got {args.ranges}")
    if not 0.0 <= args.p_fail <= 1.0:
        parser.error(f"--p-fail must be in [0, 1], got {args.p_fail}")
    return args


def run(args: argparse.Namespace) -> dict:
    ranges = sorted(set(args.ranges))
    env = make_env("figure-eight", seed=args.seed, n_cavs=args.n_cavs, horizon=args.horizon)
    comm = {
        d: CommunicationRange(d, p_fail=args.p_fail, seed=args.seed + k)
        for k, d in enumerate(ranges)
    }
    policy = ScriptedCAVPolicy(env)
    datasets = {d: NeighbourDatasets(args.n_cavs, 2048, seed=args.seed) for d in ranges}
    overhead = {d: [] for d in ranges}
    overhead_bytes = {d: [] for d in ranges}
    chi = {d: [] for d in ranges}
    all_exact = True
    steps, spans = [], []
    start = time.perf_counter()
    for episode in range(args.episodes):
        rollout = env.rollout(args.horizon, policy, break_when_any_done=True)
        steps.append(rollout.shape[0])
        final = rollout["next", "agents", "position"][-1]  # [I, 2]
        spans.append(float(torch.cdist(final, final).max()))
        transitions = TensorDict(
            {
                "observation": rollout["agents", "observation"],
                "action": rollout["agents", "action"],
                "next_observation": rollout["next", "agents", "observation"],
            },
            rollout["agents"].batch_size,
        )
        for d in ranges:
            datasets[d].add(transitions, mask=rollout["agents", "mask"])
            graph = comm[d].episode_graph(rollout)  # [I, I] at the exchange time t_k + H
            stats = datasets[d].exchange(graph)
            cover = clique_cover(graph)
            all_exact &= cover.exact
            overhead[d].append(stats.transitions)
            overhead_bytes[d].append(stats.bytes)
            chi[d].append(len(cover))
        print(
            f"episode {episode + 1:2d}/{args.episodes}: {steps[-1]} steps, "
            f"chi_bar = {[chi[d][-1] for d in ranges]}",
            flush=True,
        )
    elapsed = time.perf_counter() - start
    return {
        "config": {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(args).items()},
        "ranges": ranges,
        "steps_per_episode": steps,
        "max_cav_distance_m": spans,
        "transitions_per_episode": {f"{d:g}": overhead[d] for d in ranges},
        "bytes_per_episode": {f"{d:g}": overhead_bytes[d] for d in ranges},
        "clique_cover_number": {f"{d:g}": chi[d] for d in ranges},
        "clique_cover_exact": all_exact,
        "seconds": elapsed,
    }


def _mean_std(values: list[float]) -> tuple[float, float]:
    t = torch.tensor(values, dtype=torch.float64)
    return float(t.mean()), float(t.std(unbiased=False))


def report(results: dict) -> None:
    ranges = results["ranges"]
    print()
    print(
        f"{'d (m)':>6} | {'transitions/episode':>19} | {'paper (Tab. III)':>16} | "
        f"{'kB/episode':>10} | {'clique cover (mean +- std)':>26}"
    )
    print("-" * 90)
    means_t, means_chi = [], []
    for d in ranges:
        t_mean, _ = _mean_std(results["transitions_per_episode"][f"{d:g}"])
        b_mean, _ = _mean_std(results["bytes_per_episode"][f"{d:g}"])
        c_mean, c_std = _mean_std(results["clique_cover_number"][f"{d:g}"])
        paper = PAPER_TABLE_III.get(d)
        paper_s = f"{paper:16.2f}" if paper is not None else f"{'-':>16}"
        print(
            f"{d:6g} | {t_mean:19.1f} | {paper_s} | {b_mean / 1e3:10.1f} | "
            f"{c_mean:17.2f} +- {c_std:4.2f}"
        )
        means_t.append(t_mean)
        means_chi.append(c_mean)
    grows = all(b > a for a, b in zip(means_t, means_t[1:], strict=False))
    falls = all(b <= a for a, b in zip(means_chi, means_chi[1:], strict=False))
    exact = "exact (minimum)" if results["clique_cover_exact"] else "greedy upper bound"
    print("-" * 90)
    print(f"overhead strictly increasing in d: {grows}")
    print(f"mean clique cover number non-increasing in d: {falls} ({exact})")
    span_mean, _ = _mean_std(results["max_cav_distance_m"])
    print(
        f"largest CAV-to-CAV distance at episode end: {span_mean:.0f} m on average "
        "(the overhead curve's shape follows the map's geometry; the paper used SMARTS maps)"
    )
    n_ep = len(results["steps_per_episode"])
    print(f"{n_ep} episodes, {sum(results['steps_per_episode'])} steps, {results['seconds']:.1f} s")


def plot(results: dict, path: Path) -> None:
    """Transitions exchanged per episode (ours and the paper's Table III) and the clique cover
    number (every episode's, and their mean) against d; the means with their bootstrap 95%
    bands over episodes (:func:`mapets_rl.plotting.draw_curve`)."""
    ranges = results["ranges"]
    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(10, 4))
    # [episodes, ranges] (the ranges in order): every range is scored on the same episodes
    transitions = torch.tensor(list(results["transitions_per_episode"].values())).T
    draw_curve(
        ax1,
        ranges,
        transitions,
        metric="transitions_shared",
        marker="o",
        label="ours (scripted CAVs)",
    )
    paper_d = [d for d in ranges if d in PAPER_TABLE_III]
    ax1.plot(paper_d, [PAPER_TABLE_III[d] for d in paper_d], "s--", label="paper, Table III")
    ax1.set_xlabel("communication range d (m)")
    ax1.set_ylabel("transitions exchanged per episode")
    ax1.set_title("Communication overhead")
    ax1.legend()
    for d in ranges:
        values = results["clique_cover_number"][f"{d:g}"]
        ax2.scatter([d] * len(values), values, alpha=0.25, color="tab:blue", s=12)
    chi = torch.tensor(list(results["clique_cover_number"].values())).T
    draw_curve(
        ax2,
        ranges,
        chi,
        metric="clique_cover_number",
        marker="o",
        color="tab:red",
        label="mean, bootstrap 95% CI",
    )
    ax2.set_xlabel("communication range d (m)")
    ax2.set_ylabel("minimum clique cover number")
    ax2.set_title(f"Clique cover, {len(results['steps_per_episode'])} episodes (cf. Fig. 7)")
    ax2.legend()
    fig.tight_layout()
    atomic_savefig(fig, path, format="png", dpi=120)
    plt.close(fig)


def main(argv: list[str] | None = None) -> dict:
    args = parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    results = run(args)
    report(results)
    plot(results, args.out / "comm_overhead.png")
    payload = json.dumps(results, indent=2)
    json_path = args.out / "comm_overhead.json"
    atomic_write_text(json_path, payload)
    print(f"wrote {args.out / 'comm_overhead.png'} and {json_path}")
    return results


if __name__ == "__main__":
    from mapets_rl import quiet_dependencies

    quiet_dependencies()
    main()
