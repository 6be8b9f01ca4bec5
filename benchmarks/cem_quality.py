"""Solution quality of the CEM planner vs its population, with iCEM's sampling options.

A known-optimum toy (no learning, no noise): a 1-D point mass ``pos' = pos + dt vel,
vel' = vel + dt a`` (dt 0.1) with the quadratic reward ``-(|s'|^2 + 0.1 a^2)``, exact model
(a :class:`~mapets_rl.planning.DynamicsModel`, one particle), action bounds [-20, 20], horizon
25 (the presets'). The optimum of a decision is the finite-horizon LQ solution (least squares).
For ``M`` random start states, batched as envs of one planner, and several seeds it reports:

* ``regret``: ``J* - J(plan)`` of the first decision's returned sequence (the CEM mean, or the
  best sequence with ``keep_best``), in the planner's own objective, median and mean;
* ``closed loop``: the true cost summed over ``--steps`` MPC steps from the same states (the
  warm start and shifted elites at work), relative to MPC with the exact LQ solution (1 =
  optimal).

Variants (``--base`` planner settings: the ``cpu`` preset's ``Y``, momentum, anchors and
keep-best, ``X = max(1, Q // 8)``): ``cem`` (white noise), ``+colored`` (``noise_beta``),
``+elites`` (``keep_elites``, shifted across decisions), ``+both``; ``--decay`` adds
``population_decay`` to the last.

Example::

    python benchmarks/cem_quality.py --populations 32 16 8 --seeds 10
"""

from __future__ import annotations

import argparse
import statistics
import time

import torch

from mapets_rl.planning import CPU_PRESET, TrajectorySamplingCEM

DT, RHO, LOW, HIGH = 0.1, 0.1, -20.0, 20.0


class PointMass:
    """Exact 1-D point mass (a DynamicsModel without an ensemble: ``B = 1``)."""

    n_agents, obs_dim, action_dim, ensemble_size = 1, 2, 1, 1

    def predict(self, obs, action, dtype=torch.float32):
        mean = torch.cat([DT * obs[..., 1:2], DT * action], dim=-1)
        return mean, torch.full_like(mean, -60.0)


def reward(obs, action, next_obs):
    return -(next_obs.pow(2).sum(-1) + RHO * action.pow(2).sum(-1))


def rollout_return(s0: torch.Tensor, actions: torch.Tensor) -> torch.Tensor:
    """``sum_t r`` of sequences ``actions [N, H]`` from states ``s0 [N, 2]``."""
    pos, vel = s0[:, 0].double(), s0[:, 1].double()
    total = torch.zeros_like(pos)
    for a in actions.double().unbind(-1):
        pos, vel = pos + DT * vel, vel + DT * a
        total -= pos**2 + vel**2 + RHO * a**2
    return total


def lq_optimum(s0: torch.Tensor, horizon: int) -> torch.Tensor:
    """The unconstrained optimal sequences ``[N, H]`` (within the bounds here) by least squares."""
    a_mat = torch.tensor([[1.0, DT], [0.0, 1.0]], dtype=torch.float64)
    b_vec = torch.tensor([[0.0], [DT]], dtype=torch.float64)
    powers = [torch.linalg.matrix_power(a_mat, t) for t in range(horizon + 1)]
    design = torch.zeros(2 * horizon + horizon, horizon, dtype=torch.float64)
    for t in range(horizon):
        for k in range(t + 1):
            design[2 * t : 2 * t + 2, k : k + 1] = powers[t - k] @ b_vec
    design[2 * horizon :] = RHO**0.5 * torch.eye(horizon, dtype=torch.float64)
    free = torch.stack([powers[t + 1] for t in range(horizon)])  # [H, 2, 2]
    rhs = -(free @ s0.double().T).permute(2, 0, 1).reshape(len(s0), 2 * horizon)
    rhs = torch.cat([rhs, torch.zeros(len(s0), horizon, dtype=torch.float64)], dim=1)
    return torch.linalg.lstsq(design.expand(len(s0), -1, -1), rhs.unsqueeze(-1)).solution[..., 0]


def step(s: torch.Tensor, a: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """True next states and costs of ``s [N, 2]`` under ``a [N]``."""
    nxt = torch.stack([s[:, 0] + DT * s[:, 1], s[:, 1] + DT * a], dim=1)
    return nxt, nxt.pow(2).sum(-1) + RHO * a**2


def evaluate(settings: dict, starts: torch.Tensor, seed: int, steps: int) -> tuple:
    """(regrets [M] of the first decision, closed-loop cost [M], seconds per decision)."""
    planner = TrajectorySamplingCEM(
        PointMass(),
        reward,
        LOW,
        HIGH,
        seed=seed,
        particles=1,
        propagation="expectation",
        **settings,
    )
    horizon = planner.config.horizon
    obs = starts[:, None, :]  # [M, I=1, obs]
    planner.plan(obs)
    plan = planner.last_solution[:, 0, :, 0]  # [M, H]: the mean, or the best with keep_best
    regret = rollout_return(starts, lq_optimum(starts, horizon)) - rollout_return(starts, plan)
    s, cost, seconds = starts.clone(), torch.zeros(len(starts), dtype=torch.float64), 0.0
    planner.reset()
    for _ in range(steps):
        t0 = time.perf_counter()
        action = planner.plan(s[:, None, :])[:, 0, 0]
        seconds += time.perf_counter() - t0
        s, c = step(s, action)
        cost += c.double()
    return regret, cost, seconds / steps


def optimal_closed_loop(starts: torch.Tensor, horizon: int, steps: int) -> torch.Tensor:
    s, cost = starts.clone(), torch.zeros(len(starts), dtype=torch.float64)
    for _ in range(steps):
        action = lq_optimum(s, horizon)[:, 0].float().clamp(LOW, HIGH)
        s, c = step(s, action)
        cost += c.double()
    return cost


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--populations", nargs="+", type=int, default=[32, 16, 8])
    parser.add_argument("--seeds", type=int, default=10)
    parser.add_argument("--starts", type=int, default=16, help="start states (envs) M")
    parser.add_argument("--steps", type=int, default=25, help="closed-loop MPC steps")
    parser.add_argument("--beta", type=float, default=2.0, help="noise_beta of +colored")
    parser.add_argument("--keep", type=float, default=0.3, help="keep_elites of +elites")
    parser.add_argument("--decay", type=float, default=None, help="population_decay of +both")
    parser.add_argument("--plain", action="store_true", help="base without anchors/keep-best")
    args = parser.parse_args()
    torch.set_num_threads(1)
    base = CPU_PRESET.planner.to_dict()
    base = {k: base[k] for k in ("horizon", "iterations", "alpha", "epsilon")}
    base.update(optimizer="icem", dtype="fp32")  # every option off in "cem" (--plain)
    base.update(anchor_candidates=not args.plain, keep_best=not args.plain)
    variants = {
        "cem": {},
        "+colored": {"noise_beta": args.beta},
        "+elites": {"keep_elites": args.keep},
        "+both": {"noise_beta": args.beta, "keep_elites": args.keep},
    }
    if args.decay is not None:
        variants["+both"]["population_decay"] = args.decay
    gen = torch.Generator().manual_seed(1234)
    starts = torch.rand(args.starts, 2, generator=gen) * torch.tensor([4.0, 2.0]) - torch.tensor(
        [2.0, 1.0]
    )
    best = optimal_closed_loop(starts, base["horizon"], args.steps)
    print(f"base {base}, M={args.starts} start states x {args.seeds} seeds, {args.steps} steps")
    print("| Q | X | variant | regret median | regret mean | closed loop / optimal | ms/decision |")
    print("|---|---|---|---|---|---|---|")
    for q in args.populations:
        x = max(1, q // 8)
        for name, extra in variants.items():
            regrets, ratios, times = [], [], []
            for seed in range(args.seeds):
                settings = {**base, "population": q, "elites": x, **extra}
                regret, cost, seconds = evaluate(settings, starts, seed, args.steps)
                regrets += regret.tolist()
                ratios.append((cost / best).mean().item())
                times.append(seconds)
            print(
                f"| {q} | {x} | {name} | {statistics.median(regrets):.3g} | "
                f"{statistics.mean(regrets):.3g} | {statistics.mean(ratios):.4f} | "
                f"{1e3 * statistics.median(times):.2f} |",
                flush=True,
            )


if __name__ == "__main__":
    main()
