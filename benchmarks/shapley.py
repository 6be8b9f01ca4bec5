"""Shapley-value benchmark: the exact path through the coalition critic (batched, chunked over
states, bf16 autocast) vs a per-coalition loop, and one actor update at n = 30 on the sampled
path vs the direct formulation.

Run: ``OMP_NUM_THREADS=1 .venv/bin/python benchmarks/shapley.py`` (options: ``--help``). Prints
the CPU capability and thread count, then medians (min..max) of ``--repeats`` round-robin
timings, so that load from other processes hits all variants alike; ratios are within one run.
"""

from __future__ import annotations

import argparse
import statistics
import time
from collections.abc import Callable

import torch
from tensordict import TensorDict

from mapets_rl.machine import machine_line
from mapets_rl.objectives import ShapleyActorCriticLoss
from mapets_rl.shapley import (
    coalition_masks,
    exact_shapley,
    make_coalition_actor,
    permutation_prefix_masks,
    sample_permutations,
    sampled_shapley,
    shapley_matrix,
)
from mapets_rl.shapley.critic import CoalitionCritic


def _interleaved(fns: dict[str, Callable], repeats: int) -> tuple[dict, dict]:
    """Round-robin timings: ``{name: [seconds] * repeats}`` and each function's last output."""
    outs = {name: fn() for name, fn in fns.items()}  # warm-up
    times: dict[str, list[float]] = {name: [] for name in fns}
    for _ in range(repeats):
        for name, fn in fns.items():
            t0 = time.perf_counter()
            outs[name] = fn()
            times[name].append(time.perf_counter() - t0)
    return times, outs


def _fmt(ts: list[float]) -> str:
    return f"{statistics.median(ts) * 1e3:8.1f} ms ({min(ts) * 1e3:.1f}..{max(ts) * 1e3:.1f})"


def _report(times: dict[str, list[float]], reference: str) -> None:
    ref = statistics.median(times[reference])
    for name, ts in times.items():
        print(f"  {name:<34} {_fmt(ts)}   {ref / statistics.median(ts):5.2f}x of {reference}")


def exact_benchmark(
    n: int, states: int, obs_dim: int, act_dim: int, repeats: int, chunk: int
) -> None:
    torch.manual_seed(0)
    critic = CoalitionCritic(n, obs_dim, act_dim)
    obs = torch.randn(states, n, obs_dim)
    act = torch.nn.functional.one_hot(torch.randint(act_dim, (states, n)), act_dim).float()
    masks = coalition_masks(n)
    m = shapley_matrix(n, dtype=obs.dtype)

    def loop_over_coalitions() -> torch.Tensor:
        # One TensorDictModule call per coalition (the critic's public forward), then eq. 3.
        td = TensorDict({("agents", "observation"): obs, ("agents", "action"): act}, [states])
        values = []
        for k in range(2**n):
            td.set(("agents", "coalition"), masks[k].expand(states, n))
            values.append(critic(td).get("coalition_value"))
        return torch.cat(values, dim=-1) @ m

    fns = {
        f"loop ({2**n} critic calls)": loop_over_coalitions,
        "batched (1 call)": lambda: exact_shapley(critic.all_coalition_values(obs, act), n),
        f"batched, chunks of {chunk} states": lambda: exact_shapley(
            critic.all_coalition_values(obs, act, chunk_states=chunk), n
        ),
        f"chunks of {chunk} + bf16 autocast": lambda: exact_shapley(
            critic.all_coalition_values(
                obs, act, chunk_states=chunk, autocast_dtype=torch.bfloat16
            ),
            n,
        ),
    }
    print(
        f"exact Shapley, n={n}, {states} states, critic {obs_dim}+{act_dim} in, 128x128 hidden, "
        f"{repeats} repeats"
    )
    with torch.inference_mode():
        times, outs = _interleaved(fns, repeats)
    _report(times, f"loop ({2**n} critic calls)")
    names = list(fns)
    ref = outs[names[1]]
    scale = ref.abs().mean().item()
    for name in names[2:]:
        err = (outs[name] - ref).abs().max().item()
        print(f"  max |phi - phi_batched| {name}: {err:.2e} (mean |phi| {scale:.2e})")
    err = (outs[names[0]] - ref).abs().max().item()
    print(f"  max |phi_loop - phi_batched|: {err:.2e}")


def update_benchmark(
    n: int, batch: int, obs_dim: int, act_dim: int, perms: int, repeats: int, chunk: int
) -> None:
    """One actor update (Shapley value + backward) at ``n`` agents on the sampled path."""
    torch.manual_seed(0)
    actor = make_coalition_actor(n, obs_dim, act_dim, discrete=True)
    critic = CoalitionCritic(n, obs_dim, act_dim)
    td = TensorDict(
        {
            ("agents", "observation"): torch.randn(batch, n, obs_dim),
            ("agents", "action"): torch.nn.functional.one_hot(
                torch.randint(act_dim, (batch, n)), act_dim
            ).float(),
            ("agents", "coalition"): torch.rand(batch, n) < 0.5,
        },
        [batch],
    )
    losses = {
        c: ShapleyActorCriticLoss(
            actor,
            critic,
            num_permutations=perms,
            exact_max_agents=1,
            chunk_states=c,
            delay_actor=False,
        )
        for c in (None, chunk)
    }
    direct_loss = losses[None]
    eye = torch.eye(n, dtype=torch.bool)

    def direct() -> float:
        # The formulation before the first-layer sharing: n substituted joint actions per state,
        # every prefix coalition through the critic with autograd over all of it.
        obs, a_batch = td["agents", "observation"], td["agents", "action"]
        a_pol, _ = direct_loss.policy_action(
            direct_loss.actor_network_params, obs, td["agents", "coalition"], greedy=False
        )
        joint = torch.where(eye.unsqueeze(-1), a_pol.unsqueeze(-3), a_batch.unsqueeze(-3))
        before = permutation_prefix_masks(sample_permutations(perms, n)).transpose(0, 1)
        params = direct_loss.critic_network_params.detach()
        with params.to_module(direct_loss.critic_network, preserve_module_state=False):
            v_with = critic.coalition_values(obs.unsqueeze(-3), joint, before | eye.unsqueeze(-2))
            with torch.no_grad():
                v_before = critic.coalition_values(obs.unsqueeze(-3), a_batch.unsqueeze(-3), before)
        loss = -(v_with - v_before).mean()
        loss.backward()
        return loss.item()

    def ours(c: int | None) -> Callable[[], float]:
        def run() -> float:
            loss, _ = losses[c].loss_actor(td)
            loss.backward()
            return loss.item()

        return run

    fns = {
        "direct (before this change)": direct,
        "factorised, 1 pass": ours(None),
        f"factorised, chunks of {chunk} states": ours(chunk),
    }
    print(
        f"actor update, sampled Shapley, n={n}, batch {batch}, {perms} antithetic permutations, "
        f"{repeats} repeats"
    )
    times, _ = _interleaved(fns, repeats)
    _report(times, "direct (before this change)")
    with torch.no_grad():
        phi, stderr = losses[chunk].shapley_values(td, return_stderr=True)
    print(
        f"  reported stderr (random critic): mean {stderr.mean():.2e}, mean |phi| "
        f"{phi.abs().mean():.2e}, relative {(stderr.mean() / phi.abs().mean()).item():.3f}"
    )


def sampled_benchmark(n: int, states: int, obs_dim: int, act_dim: int, perms: int) -> None:
    torch.manual_seed(0)
    critic = CoalitionCritic(n, obs_dim, act_dim)
    obs = torch.randn(states, n, obs_dim)
    act = torch.nn.functional.one_hot(torch.randint(act_dim, (states, n)), act_dim).float()

    def value_fn(masks: torch.Tensor) -> torch.Tensor:
        return critic.coalition_values(obs, act, masks)

    print(
        f"sampled Shapley (game.sampled_shapley), n={n}, {states} states, {perms} permutations "
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
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--chunk", type=int, default=8, help="states per chunk")
    parser.add_argument("--update-n", type=int, default=30)
    parser.add_argument("--update-batch", type=int, default=128)
    parser.add_argument("--update-obs-dim", type=int, default=22, help="freeway observation")
    parser.add_argument("--update-permutations", type=int, nargs="+", default=[8, 32])
    parser.add_argument("--sampled-n", type=int, default=30)
    parser.add_argument("--sampled-states", type=int, default=32)
    parser.add_argument("--permutations", type=int, default=1000)
    parser.add_argument("--skip", nargs="*", default=[], choices=["exact", "update", "sampled"])
    args = parser.parse_args()
    print(f"# {machine_line()}")
    if "exact" not in args.skip:
        exact_benchmark(args.n, args.states, args.obs_dim, args.act_dim, args.repeats, args.chunk)
    if "update" not in args.skip:
        for perms in args.update_permutations:
            update_benchmark(
                args.update_n,
                args.update_batch,
                args.update_obs_dim,
                args.act_dim,
                perms,
                args.repeats,
                args.chunk,
            )
    if "sampled" not in args.skip:
        sampled_benchmark(
            args.sampled_n, args.sampled_states, args.obs_dim, args.act_dim, args.permutations
        )


if __name__ == "__main__":
    from mapets_rl import quiet_dependencies

    quiet_dependencies()
    main()
