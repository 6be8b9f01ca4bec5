"""Can the coalition critic represent one CAV's state-dependent action effect? A synthetic
game with a known answer (issue 32).

On ``freeway-merge`` the Shapley arm's critic answers a CAV's lane change with nearly the same
value change in every coalition, uncorrelated with what the move really earns
(``benchmarks/shapley_credit_at_merge.py``). Its first layer sums the members' linear
embeddings of (observation, action) before any nonlinearity, so in a large coalition the head
may not tell which member's state goes with which member's action. This script tests that
capacity apart from the freeway, the TD targets and the exploration: an additive game where
every agent earns ``u_j = scale * o_j[1] + m_j * o_j[0]`` (``m_j`` = 1 if agent ``j`` changes lanes,
i.e. its one-hot action is Change Left or Change Right, else 0; observations standard normal),
so that ``v(C) = sum_{j in C} u_j`` and the true value of agent ``i``'s move over keeping its
lane is ``o_i[0]`` in every coalition that holds it (and its Shapley value's change).
``--scale`` sets how large the state's own part of the payoff is against the move's: on the
freeway a move changes its CAV's return by tens against returns of hundreds per CAV and
coalition values of thousands.

A :class:`~mapets_rl.shapley.CoalitionCritic` is fitted by Adam on fresh batches (states,
uniformly random actions, coalitions drawn as ``RandomCoalition`` draws them) to ``v(C)``, the
regression the TD loss does with exact targets. On held-out states, for one random agent per
state: the correlation of the critic's ``Delta v({i})``, ``Delta phi_i`` (``--permutations``
random orderings) and ``Delta v(N)`` (move minus keep lane) with the true ``o_i[0]``, and the
fit of ``v(C)`` (R^2 over held-out coalitions). ``--heads member`` fits a critic with one head
output per agent (``CoalitionCritic(member_heads=True)``, ``v(C) = sum_{j in C} q_j``) to each
member's own payoff ``u_j``, as its TD loss does with the members' rewards. ``--noise`` adds
independent zero-mean Gaussian noise of that standard deviation to every agent's payoff in the
training targets (the part of a return that the state and action do not predict, which a TD
target carries); the held-out scores are against the noiseless game.

    OMP_NUM_THREADS=1 PYTHONPATH=. python benchmarks/coalition_critic_capacity.py \\
        --agents 4 30 --cells 64 256 [--scale 1 10] [--embed 0 64] [--heads sum member] \\
        [--noise 0 10] [--sizes binomial uniform] \\
        [--steps 3000] [--lr 0.01]
"""

from __future__ import annotations

import argparse
import itertools
import time

import torch

from mapets_rl.machine import machine_line
from mapets_rl.shapley import (
    CoalitionCritic,
    prefixes_with_agents,
    sample_permutations,
    uniform_size_coalition,
)

ACTIONS = 4  # KL, CL, CR, ES
MOVES = (1, 2)  # CL, CR


def sample(n: int, obs_dim: int, batch: int, generator: torch.Generator, scale: float = 1.0):
    """States ``[batch, n, obs_dim]``, one-hot uniformly random actions ``[batch, n, 4]`` and
    every agent's payoff ``u [batch, n]`` of the synthetic game (``scale``: the weight of the
    state's own part, ``o[1]``)."""
    obs = torch.randn(batch, n, obs_dim, generator=generator)
    choice = torch.randint(ACTIONS, (batch, n), generator=generator)
    action = torch.nn.functional.one_hot(choice, ACTIONS).float()
    moving = action[..., list(MOVES)].sum(-1)
    return obs, action, scale * obs[..., 1] + moving * obs[..., 0]


def draw_coalitions(sizes: str, n: int, batch: int) -> torch.Tensor:
    """``[batch, n]`` bool coalitions drawn as ``RandomCoalition`` draws them while collecting:
    ``binomial`` (every agent joins with probability 1/2) or ``uniform`` (size uniform over
    ``1..n``, then the members)."""
    if sizes == "uniform":
        return uniform_size_coalition(torch.ones(batch, n, dtype=torch.bool))
    return torch.rand(batch, n) < 0.5


def pearson(a: torch.Tensor, b: torch.Tensor) -> float:
    """Pearson's correlation of two 1-D tensors."""
    return float(torch.corrcoef(torch.stack([a, b]))[0, 1])


def fit_and_score(
    n: int,
    cells: int,
    sizes: str,
    embed: int,
    scale: float,
    heads: str,
    noise: float,
    args: argparse.Namespace,
) -> dict[str, float]:
    """Fit a ``[cells, cells]`` critic (with a per-agent ``embed``-wide layer before the sum
    when ``embed > 0``; ``heads``: ``sum`` one output fitted to ``v(C)``, ``member`` one per
    agent fitted to its own payoff) to the game of ``n`` agents with coalitions drawn by
    ``sizes``, every payoff in the targets plus Gaussian ``noise``; its correlations with the
    true move effect and its held-out R^2."""
    torch.manual_seed(args.seed)
    generator = torch.Generator().manual_seed(args.seed)
    member = heads == "member"
    critic = CoalitionCritic(
        n,
        args.obs_dim,
        ACTIONS,
        num_cells=[cells, cells],
        embed_cells=[embed] if embed else [],
        member_heads=member,
    )
    optimizer = torch.optim.Adam(critic.parameters(), lr=args.lr)
    start = time.perf_counter()
    for _ in range(args.steps):
        obs, action, payoff = sample(n, args.obs_dim, args.batch, generator, scale)
        members = draw_coalitions(sizes, n, args.batch)
        if noise > 0:
            payoff = payoff + noise * torch.randn(payoff.shape, generator=generator)
        target = payoff * members  # [batch, n]: each member's payoff
        value = critic.coalition_values(obs, action, members.unsqueeze(-2), per_member=member)
        if member:
            loss = (value.squeeze(-2) - target).pow(2).sum(-1).mean()
        else:
            loss = (value.squeeze(-1) - target.sum(-1)).pow(2).mean()
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
    seconds = time.perf_counter() - start
    with torch.no_grad():
        obs, action, payoff = sample(n, args.obs_dim, args.eval_states, generator, scale)
        members = draw_coalitions(sizes, n, args.eval_states)
        target = (payoff * members).sum(-1)
        value = critic.coalition_values(obs, action, members.unsqueeze(-2)).squeeze(-1)
        r2 = 1 - (value - target).pow(2).mean() / target.var()
        rows = torch.arange(args.eval_states)
        agent = torch.randint(n, (args.eval_states,), generator=generator)
        keep, move = action.clone(), action.clone()
        keep[rows, agent] = torch.nn.functional.one_hot(torch.tensor(0), ACTIONS).float()
        move[rows, agent] = torch.nn.functional.one_hot(torch.tensor(MOVES[0]), ACTIONS).float()
        single = torch.nn.functional.one_hot(agent, n).bool().unsqueeze(-2)
        # the coalitions with the agent that its Shapley value reads: a random prefix plus it
        with_agent = prefixes_with_agents(sample_permutations(args.permutations, n), agent)
        masks = torch.cat([single, torch.ones_like(single), with_agent], dim=-2)  # {i}, N, ...
        delta = critic.coalition_values(obs, move, masks) - critic.coalition_values(
            obs, keep, masks
        )
        truth = obs[rows, agent, 0]
    return {
        "r2": float(r2),
        "corr_single": pearson(delta[:, 0], truth),
        "corr_grand": pearson(delta[:, 1], truth),
        "corr_phi": pearson(delta[:, 2:].mean(-1), truth),
        "seconds": seconds,
    }


def main(argv: list[str] | None = None) -> list[dict]:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--agents", nargs="+", type=int, default=[4, 30])
    parser.add_argument("--cells", nargs="+", type=int, default=[64, 256])
    parser.add_argument("--sizes", nargs="+", default=["binomial"], choices=["binomial", "uniform"])
    parser.add_argument(
        "--embed",
        nargs="+",
        type=int,
        default=[0],
        help="widths of a per-agent layer before the members are summed (0: none, the paper's)",
    )
    parser.add_argument("--scale", nargs="+", type=float, default=[1.0], help="o[1]'s weight")
    parser.add_argument(
        "--heads",
        nargs="+",
        default=["sum"],
        choices=["sum", "member"],
        help="sum: one output fitted to v(C) (the paper's); member: one per agent, own payoff",
    )
    parser.add_argument(
        "--noise", nargs="+", type=float, default=[0.0], help="sd of the payoffs' target noise"
    )
    parser.add_argument("--obs-dim", type=int, default=8)
    parser.add_argument("--steps", type=int, default=3000)
    parser.add_argument("--batch", type=int, default=1024)
    parser.add_argument("--lr", type=float, default=0.01)
    parser.add_argument("--eval-states", type=int, default=2048)
    parser.add_argument("--permutations", type=int, default=64, help="orderings for Delta phi")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    if args.permutations < 2 or args.permutations % 2:
        parser.error(f"--permutations must be even and >= 2, got {args.permutations}")
    for name in ("obs_dim", "steps", "batch", "eval_states"):
        if getattr(args, name) < 1:
            parser.error(f"--{name.replace('_', '-')} must be >= 1, got {getattr(args, name)}")
    if args.obs_dim < 2:
        parser.error(f"--obs-dim must be >= 2 (the game reads columns 0 and 1), got {args.obs_dim}")
    if min(args.agents) < 1 or min(args.cells) < 1 or min(args.embed) < 0 or not args.lr > 0:
        parser.error("--agents and --cells must be >= 1, --embed >= 0 and --lr > 0")
    for name in ("scale", "noise"):
        if not all(0 <= x < float("inf") for x in getattr(args, name)):
            parser.error(f"--{name} must be finite and >= 0, got {getattr(args, name)}")
    print(f"# {machine_line()}")
    print(
        f"synthetic additive game, obs_dim {args.obs_dim}, {args.steps} Adam steps (lr "
        f"{args.lr}) of batch {args.batch}, {args.eval_states} held-out states, seed {args.seed}"
    )
    print(
        "| agents | scale | noise | critic | per-agent layer | heads | coalition sizes "
        "| R^2 of v(C) "
        "| corr(Delta v({i}), true) "
        "| corr(Delta phi_i, true) | corr(Delta v(N), true) | fit [s] |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|---|---|")
    rows = []
    grid = itertools.product(
        args.agents, args.scale, args.noise, args.cells, args.embed, args.heads, args.sizes
    )
    for n, scale, noise, cells, embed, heads, sizes in grid:
        row = {
            "agents": n,
            "scale": scale,
            "noise": noise,
            "cells": cells,
            "embed": embed,
            "heads": heads,
            "sizes": sizes,
        }
        row.update(fit_and_score(n, cells, sizes, embed, scale, heads, noise, args))
        rows.append(row)
        print(
            f"| {n} | {scale:g} | {noise:g} | 2x{cells} | {embed or 'none'} | {heads} | {sizes} "
            f"| {row['r2']:.3f} "
            f"| {row['corr_single']:.2f} | {row['corr_phi']:.2f} | {row['corr_grand']:.2f} "
            f"| {row['seconds']:.0f} |",
            flush=True,
        )
    return rows


if __name__ == "__main__":
    main()
