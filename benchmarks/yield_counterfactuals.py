"""Are the learned lane changes near the merge selfish? Exact counterfactuals (issue 32).

Self-interested MADDPG (``team_reward=false``) finds the cooperative merge of ``freeway-merge``
at w = 1 as well as the team reward does (``benchmarks/cooperation_control.py``). This script
asks why: is the lane change that lets the ramp traffic in also the move that pays the CAV
that makes it?

Each trained run of ``cooperation_control.py`` (``--variants``, ``--seeds``, ``--out``: the
runs it trained) plays its greedy policy on ``--roads`` roads of its evaluation seed, with the
variant's shield and velocity weight. At every step, every lane-change decision (CL or CR, not
overruled by the shield) of a CAV on a mainline lane is replayed on a copy of the road where
that CAV keeps its lane instead, everything else the same: with ``--deviation rest`` (default)
it keeps its lane for the rest of the episode (it opts out of the policy from here: was its way
of driving from here worth it, to itself and to the system?), with ``--deviation step`` for
this step only (then it follows the policy again, which often makes the same move one step
later: the value of the move's timing). The co-players follow the policy. The policy's own
continuation is replayed on another copy
(:meth:`BatchedFreeway.take`: all of a step's copies are one batch). Per decision, over the
rest of the episode, discounted by ``--gamma`` (default 0.95, the learners' discount; 1: the
undiscounted returns of the evaluation):

- ``own``: what the lane change earns the CAV that makes it (its return with the change minus
  its return with Keep Lane), the quantity a self-interested learner is paid for, and the part
  of it in metres driven (at w = 1 the velocity term; the rest is comfort and crashes);
- ``system``: what it earns the system (the CAVs' returns summed), the team reward's quantity.

A decision is a *dilemma* when ``own < 0 < system`` (cooperative and costly: what individual
credit would unlearn), *selfish-harmful* when ``system < 0 < own``, *aligned* when both have one
sign. Decisions are split by where they are made: near the merge (100 m before the
acceleration lane to its end, ``cooperation_control.near_merge``) and elsewhere. ``--variants``
may also name ``rule``: the cooperative merge rule of ``benchmarks/freeway_headroom.py`` with
the shield and w = 1 (its yields, the reference).

    OMP_NUM_THREADS=1 PYTHONPATH=.:benchmarks python benchmarks/yield_counterfactuals.py \\
        --variants maddpg_epsilon_shield_w1_individual maddpg_epsilon_shield_w1 rule \\
        --seeds 0 1 2 3 4 --roads 64 --out /path/to/cooperation_control_out

Per (variant, seed) the decisions are cached in ``<out>/evals/yields_*.json``; prints a markdown
table and writes it to ``<out>/yields_gamma<G>_<deviation>.md``.
"""

from __future__ import annotations

import argparse
import json
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch
from cooperation_control import (
    EVAL_SEED_OFFSET,
    cav_lanes,
    cooperative_rule,
    env_settings,
    evaluation_env,
    near_merge,
    on_mainline,
    variant_overrides,
)
from tensordict import TensorDict
from tensordict.nn import TensorDictModuleBase

from mapets_rl.app.plugins import load_recipe
from mapets_rl.envs.freeway import CL, CR, KL
from mapets_rl.envs.torch_freeway.simulator import BatchedFreeway
from mapets_rl.experiment import atomic_write_text, latest_checkpoint
from mapets_rl.machine import machine_line
from mapets_rl.modules import ACTION, OBS
from mapets_rl.statistics import bootstrap_interval

RULE = "rule"
RULE_SETTINGS = {"shield": True, "velocity_weight": 1.0}
"""The scripted reference's scenario settings (those of the ``*_shield_w1`` variants)."""

Decide = Callable[[torch.Tensor], torch.Tensor]


def deciding(policy: TensorDictModuleBase) -> Decide:
    """``observation [K, I, obs] -> decisions [K, I]`` (0..3) of a TensorDict policy writing
    one-hot actions."""

    def decide(observation: torch.Tensor) -> torch.Tensor:
        td = TensorDict({OBS: observation.float()}, batch_size=observation.shape[:1])
        return policy(td).get(ACTION).argmax(-1)

    return decide


def returns_per_cav(
    copies: BatchedFreeway,
    first: torch.Tensor,
    decide: Decide,
    gamma: float,
    keeping: torch.Tensor | None = None,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Every road of ``copies`` plays ``first [K, I]`` now and ``decide`` after (the CAVs of
    ``keeping [K, I]`` (bool) Keep Lane instead), to the end of its episode: each CAV's return
    from now on ``[K, I]`` and the metres it drives (float64, the step ``k`` steps from now
    weighted by ``gamma ** k``), and the bodies' lateral positions after the first step
    ``[K, N]``."""
    if keeping is not None:
        plain = decide

        def decide(observation: torch.Tensor) -> torch.Tensor:
            return torch.where(keeping, KL, plain(observation))

    result = copies.step(first)
    y = copies.state["bodies"].get("y").clone()
    total = result.reward.double().clone()
    metres = result.distance.double().clone()
    running = ~(result.truncated | result.terminated)
    discount = 1.0
    while bool(running.any()):
        result = copies.step(decide(result.observation))
        discount *= gamma
        on = running.unsqueeze(-1)
        total += torch.where(on, discount * result.reward.double(), 0.0)
        metres += torch.where(on, discount * result.distance.double(), 0.0)
        running &= ~(result.truncated | result.terminated)
    return total, metres, y


def branches(
    sim: BatchedFreeway,
    action: torch.Tensor,
    road: torch.Tensor,
    cav: torch.Tensor,
    replacement: torch.Tensor,
    decide: Decide,
    gamma: float,
    *,
    keep_lane_after: bool = False,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Decision ``k`` (CAV ``cav[k]`` of road ``road[k]``, ``[K]`` each) replayed on its own
    copy of the road with that CAV's action this step replaced by ``replacement[k]``, beside one
    copy per road that plays ``action [B, I]`` unchanged; all copies then follow ``decide``
    (with ``keep_lane_after``, the replaced CAVs keep their lane instead, to the end), in one
    batch (:func:`returns_per_cav`). Returns its ``returns``, ``metres`` and ``y`` rows and,
    ``[K]`` each, the index of every decision's unchanged copy and of its own copy."""
    bases = road.unique()  # sorted: the policy's own continuation of each road
    copies = sim.take(torch.cat([bases, road]))
    first = action[torch.cat([bases, road])].clone()
    branch = torch.arange(bases.numel(), bases.numel() + road.numel())
    first[branch, cav] = replacement
    keeping = None
    if keep_lane_after:
        keeping = torch.zeros_like(first, dtype=torch.bool)
        keeping[branch, cav] = True
    returns, metres, y = returns_per_cav(copies, first, decide, gamma, keeping)
    return returns, metres, y, torch.searchsorted(bases, road), branch


@torch.no_grad()
def counterfactuals(
    decide: Decide, settings: dict, seed: int, args: argparse.Namespace
) -> dict[str, list]:
    """The greedy episodes of ``decide`` on ``--roads`` evaluation roads of ``seed``: per
    lane-change decision of a CAV on a mainline lane, its step, whether it was near the merge,
    and its own and system effects (lists, one entry per decision)."""
    # every CAV's own reward; the system's is their sum
    env = evaluation_env(args.roads, args.n_vehicles, {**settings, "team_reward": False})
    env.set_seed(EVAL_SEED_OFFSET + seed)
    env.reset()
    sim = env.sim
    out: dict[str, list] = {
        "step": [],
        "near": [],
        "moved": [],
        "own": [],
        "own_metres": [],
        "system": [],
    }
    observation = sim.observe()
    for step in range(int(env.config["horizon"])):
        action = decide(observation)
        safe = sim.shield(action)[0] if sim.config["shield"] else action
        lane, x = cav_lanes(sim)
        alive = sim.state["agents"].get("alive")
        chosen = alive & ((safe == CL) | (safe == CR)) & on_mainline(sim, lane)
        if bool(chosen.any()):
            road, cav = chosen.nonzero(as_tuple=True)  # [K]
            returns, metres, y, own_base, kept = branches(
                sim, action, road, cav, torch.full_like(cav, KL), decide, args.gamma,
                keep_lane_after=args.deviation == "rest",
            )  # fmt: skip
            out["moved"] += (y[own_base] != y[kept]).any(-1).tolist()
            out["step"] += [step] * road.numel()
            out["near"] += near_merge(sim, x)[road, cav].tolist()
            out["own"] += (returns[own_base, cav] - returns[kept, cav]).tolist()
            out["own_metres"] += (metres[own_base, cav] - metres[kept, cav]).tolist()
            out["system"] += (returns[own_base].sum(-1) - returns[kept].sum(-1)).tolist()
        observation = sim.step(action).observation
    env.close()
    return out


def recipe_of(variant: str, args: argparse.Namespace) -> str:
    """The recipe that trained ``variant`` (ValueError naming a variant that is not one)."""
    sizes = argparse.Namespace(train_roads=1, n_vehicles=args.n_vehicles, frames=1, anneal_frames=1)
    return variant_overrides(variant, sizes)[0]


def run_dir_of(variant: str, seed: int, args: argparse.Namespace) -> Path:
    """The run directory of ``variant`` at ``seed`` under ``--out``; ValueError if it has no
    checkpoint."""
    run_dir = Path(args.out) / "runs" / f"{variant}_seed{seed}"
    if latest_checkpoint(run_dir) is None:
        raise ValueError(f"--out: no trained run {run_dir} (train it with cooperation_control.py)")
    return run_dir


def run_policy(variant: str, seed: int, args: argparse.Namespace) -> tuple[Decide, dict, Callable]:
    """The greedy decisions of ``variant`` at ``seed``, its scenario settings and a closer."""
    if variant == RULE:
        return deciding(cooperative_rule(args.n_vehicles)), RULE_SETTINGS, lambda: None
    recipe = recipe_of(variant, args)
    exp = load_recipe(recipe).from_run_dir(run_dir_of(variant, seed, args))
    return deciding(exp.eval_policy), env_settings(variant), exp.close


def decisions(variant: str, seed: int, args: argparse.Namespace) -> dict[str, list]:
    """The counterfactuals of ``variant`` at ``seed``, cached in ``<out>/evals/``."""
    path = (
        Path(args.out)
        / "evals"
        / f"yields_{variant}_seed{seed}_{args.roads}roads_gamma{args.gamma}_{args.deviation}.json"
    )
    if path.is_file():
        cached = json.loads(path.read_text())
        if "own_metres" in cached:  # older caches lack it: measured again
            return cached
    decide, settings, close = run_policy(variant, seed, args)
    try:
        result = counterfactuals(decide, settings, seed, args)
    finally:
        close()
    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_text(path, json.dumps(result))
    return result


def summary_row(label: str, per_seed: list[dict[str, np.ndarray]], roads: int) -> str:
    """One markdown row: lane-change decisions per episode, the share that moves the car (the
    others are commands with nothing to do, e.g. Change Left in the leftmost lane, which cost
    comfort only), then over the moving decisions the mean own and system effects (bootstrap
    95% over the seeds' means) and the shares of own gains, aligned, dilemma and
    selfish-harmful decisions."""
    moved = [d["moved"].astype(bool) for d in per_seed]
    count = sum(len(m) for m in moved)
    share = sum(int(m.sum()) for m in moved) / max(count, 1)
    head = f"| {label} | {count / (roads * len(per_seed)):.1f} | {share:.2f} "
    if share == 0:
        return head + "| | | | | | | |"
    own = np.concatenate([d["own"][m] for d, m in zip(per_seed, moved, strict=True)])
    system = np.concatenate([d["system"][m] for d, m in zip(per_seed, moved, strict=True)])

    def seed_means(key: str) -> str:
        means = [float(d[key][m].mean()) for d, m in zip(per_seed, moved, strict=True) if m.any()]
        mean, low, high = bootstrap_interval(np.array(means))
        return f"{mean:+.1f} [{low:+.1f}, {high:+.1f}]"

    aligned = ((own > 0) & (system > 0)) | ((own < 0) & (system < 0))
    return head + (
        f"| {seed_means('own')} | {seed_means('own_metres')} | {seed_means('system')} "
        f"| {(own > 0).mean():.2f} "
        f"| {aligned.mean():.2f} | {((own < 0) & (system > 0)).mean():.2f} "
        f"| {((system < 0) & (own > 0)).mean():.2f} |"
    )


HEADER = (
    "| policy, where | lane-change decisions per episode | share that moves the car "
    "| own effect, mean [95%] | own effect in metres driven | system effect, mean [95%] "
    "| own > 0 | aligned (same sign) | dilemma (own < 0 < system) "
    "| selfish-harmful (system < 0 < own) |\n"
    "|---|---|---|---|---|---|---|---|---|---|"
)


def main(argv: list[str] | None = None) -> str:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--variants", nargs="+", required=True)
    parser.add_argument("--seeds", nargs="+", type=int, default=[0])
    parser.add_argument("--roads", type=int, default=64, help="evaluation roads per seed")
    parser.add_argument("--n-vehicles", type=int, default=30)
    parser.add_argument(
        "--gamma", type=float, default=0.95, help="discount of the effects (the learners': 0.95)"
    )
    parser.add_argument(
        "--deviation",
        choices=["step", "rest"],
        default="rest",
        help="step: Keep Lane for the decision's step only; rest: for the rest of the episode",
    )
    parser.add_argument("--out", required=True, help="cooperation_control.py's --out")
    args = parser.parse_args(argv)
    if args.roads < 1:
        parser.error(f"--roads must be >= 1, got {args.roads}")
    if not 0.0 <= args.gamma <= 1.0:
        parser.error(f"--gamma must be in [0, 1], got {args.gamma}")
    for variant in args.variants:  # a bad name or a missing run fails before any work
        if variant != RULE:
            recipe_of(variant, args)
            for seed in args.seeds:
                run_dir_of(variant, seed, args)
    print(f"# {machine_line()}")
    rows = [HEADER]
    for variant in args.variants:
        per_seed = []
        for seed in args.seeds:
            data = decisions(variant, seed, args)
            per_seed.append({k: np.asarray(v) for k, v in data.items()})
        for where, near in (("near the merge", True), ("elsewhere", False)):
            part = [{k: v[d["near"] == near] for k, v in d.items()} for d in per_seed]
            rows.append(summary_row(f"{variant}, {where}", part, args.roads))
    table = "\n".join(rows)
    print(table)
    name = f"yields_gamma{args.gamma}_{args.deviation}.md"
    atomic_write_text(Path(args.out) / name, table + "\n")
    return table


if __name__ == "__main__":
    main()
