"""Shapley-value benchmark: batched exact path through the coalition critic vs loops, and the
permutation estimator at n = 30.

Run: ``.venv/bin/python benchmarks/shapley.py`` (options: ``--help``). Prints ratios measured in
one run on this machine; absolute times depend on the (possibly shared) CPU. The batched path
and the per-coalition loop are timed round-robin (best of ``--repeats``); the literal eq. 3 loop
(``n * 2**(n-1)`` pairs of critic calls) is timed on ``--textbook-agents`` agents and scaled.
"""

from __future__ import annotations

import argparse
import time

import torch
from tensordict import TensorDict

from mapets_rl.shapley import coalition_masks, exact_shapley, sampled_shapley, shapley_matrix
from mapets_rl.shapley.critic import CoalitionCritic


def _timeit_interleaved(fns: dict, repeats: int) -> tuple[dict, dict]:
    """Best-of-``repeats`` wall time of each function, measured round-robin so that a burst of
    load from other processes hits all of them alike; returns (times, last outputs)."""
    outs = {name: fn() for name, fn in fns.items()}  # warm-up
    best = dict.fromkeys(fns, float("inf"))
    for _ in range(repeats):
        for name, fn in fns.items():
            t0 = time.perf_counter()
            outs[name] = fn()
            best[name] = min(best[name], time.perf_counter() - t0)
    return best, outs


def exact_benchmark(
    n: int, states: int, obs_dim: int, act_dim: int, repeats: int, textbook_agents: int
) -> None:
    torch.manual_seed(0)
    critic = CoalitionCritic(n, obs_dim, act_dim)
    obs = torch.randn(states, n, obs_dim)
    act = torch.nn.functional.one_hot(torch.randint(act_dim, (states, n)), act_dim).float()
    masks = coalition_masks(n)

    def batched() -> torch.Tensor:
        return exact_shapley(critic.all_coalition_values(obs, act), n)

    def loop_over_coalitions() -> torch.Tensor:
        # One TensorDictModule call per coalition (the critic's public forward), then eq. 3.
        td = TensorDict({("agents", "observation"): obs, ("agents", "action"): act}, [states])
        values = []
        for k in range(2**n):
            td.set(("agents", "coalition"), masks[k].expand(states, n))
            values.append(critic(td).get("coalition_value"))
        return torch.cat(values, dim=-1) @ shapley_matrix(n, dtype=obs.dtype)

    def textbook_eq3(agents: int) -> torch.Tensor:
        # Literal eq. 3: for every agent i and coalition C not containing i, two critic calls.
        m = shapley_matrix(n, dtype=obs.dtype)
        phi = torch.zeros(states, n)
        for i in range(agents):
            for k in range(2**n):
                if masks[k, i]:
                    continue
                with_i = masks[k | (1 << i)].expand(states, 1, n)
                without = masks[k].expand(states, 1, n)
                diff = critic.coalition_values(obs, act, with_i) - critic.coalition_values(
                    obs, act, without
                )
                phi[:, i] += -m[k, i] * diff.squeeze(-1)
        return phi

    with torch.inference_mode():
        times, outs = _timeit_interleaved(
            {"batched": batched, "loop": loop_over_coalitions}, repeats
        )
        t_batched, t_loop = times["batched"], times["loop"]
        phi, phi_loop = outs["batched"], outs["loop"]
        t0 = time.perf_counter()
        phi_textbook = textbook_eq3(textbook_agents)
        t_textbook = (time.perf_counter() - t0) * n / textbook_agents
    err = max(
        (phi - phi_loop).abs().max().item(),
        (phi - phi_textbook)[:, :textbook_agents].abs().max().item(),
    )
    print(f"exact Shapley, n={n}, {states} states, critic {obs_dim}+{act_dim} in, 128x128 hidden")
    print(f"  batched (1 critic call, {2**n} coalitions): {t_batched * 1e3:9.1f} ms")
    print(
        f"  loop over coalitions ({2**n} calls):       {t_loop * 1e3:9.1f} ms"
        f"   speed-up {t_loop / t_batched:6.1f}x"
    )
    note = "" if textbook_agents == n else f", timed on {textbook_agents} agent(s) x {n}"
    print(
        f"  textbook eq. 3 ({n * 2**n} calls{note}): {t_textbook * 1e3:9.1f} ms"
        f"   speed-up {t_textbook / t_batched:6.1f}x"
    )
    print(f"  max |phi_batched - phi_loops| = {err:.2e}")


def sampled_benchmark(n: int, states: int, obs_dim: int, act_dim: int, perms: int) -> None:
    torch.manual_seed(0)
    critic = CoalitionCritic(n, obs_dim, act_dim)
    obs = torch.randn(states, n, obs_dim)
    act = torch.nn.functional.one_hot(torch.randint(act_dim, (states, n)), act_dim).float()

    def value_fn(masks: torch.Tensor) -> torch.Tensor:
        return critic.coalition_values(obs, act, masks)

    print(
        f"sampled Shapley, n={n}, {states} states, {perms} permutations "
        f"({perms * (n + 1)} coalitions per state)"
    )
    with torch.inference_mode():
        for antithetic in (True, False):
            gen = torch.Generator().manual_seed(1)
            t0 = time.perf_counter()
            phi, stderr = sampled_shapley(
                value_fn, n, perms, gen, antithetic=antithetic, max_coalitions_per_call=8 * 1024
            )
            dt = time.perf_counter() - t0
            rel = (stderr / phi.abs().mean()).mean().item()
            print(
                f"  antithetic={antithetic!s:5}: {dt:6.2f} s, mean stderr {stderr.mean():.2e} "
                f"(mean |phi| {phi.abs().mean():.2e}, relative {rel:.3f})"
            )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--n", type=int, default=10)
    parser.add_argument("--states", type=int, default=256)
    parser.add_argument("--obs-dim", type=int, default=10)
    parser.add_argument("--act-dim", type=int, default=4)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument(
        "--textbook-agents",
        type=int,
        default=1,
        help="agents timed on the literal eq. 3 loop (the time is scaled to all n agents)",
    )
    parser.add_argument("--sampled-n", type=int, default=30)
    parser.add_argument("--sampled-states", type=int, default=32)
    parser.add_argument("--permutations", type=int, default=1000)
    args = parser.parse_args()
    print(f"torch {torch.__version__}, {torch.get_num_threads()} threads")
    exact_benchmark(
        args.n, args.states, args.obs_dim, args.act_dim, args.repeats, args.textbook_agents
    )
    sampled_benchmark(
        args.sampled_n, args.sampled_states, args.obs_dim, args.act_dim, args.permutations
    )


if __name__ == "__main__":
    main()
