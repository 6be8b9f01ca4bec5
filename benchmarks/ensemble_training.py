"""Training all agents' ensembles: one batched program vs a loop over agents and members.

Workload (MA-PETS, Table II / SPEC 4): I agents x B members, 2048 transitions per agent,
5 epochs of minibatches of 128, Adam lr 1e-3, Gaussian NLL (eq. 9) with learned log-variance
bounds and a per-member bootstrap resample of each minibatch.

* vectorized: ``train_ensemble(EnsembleNLLLoss(ProbabilisticEnsemble(...)), ...)`` —
  stacked weights, one ``baddbmm`` per layer for all ``I * B`` MLPs;
* loop: the same math with one ``nn.Sequential`` per (agent, member), forward passes in a
  Python loop over agents and members, one summed backward and one (foreach) Adam step;
* with ``--reference mbrl-lib``: mbrl-lib's ``ModelTrainer`` on a ``GaussianMLP`` ensemble of
  the same sizes, one trainer per agent (mbrl-lib has no multi-agent batching), same data,
  epochs, batch size, bootstrap, NLL with learned log-variance bounds and Adam lr (see
  ``train_ensembles`` of ``benchmarks/_common.py``). Headline: mbrl-lib's time per agent over
  ours (medians of the interleaved repeats, with min..max). Optional: it needs mbrl-lib,
  which this script never installs (without it the flag prints how to install it beside the
  pinned torch and exits with status 2).

Example::

    python benchmarks/ensemble_training.py --repeats 3                      # cpu preset, 3x64
    python benchmarks/ensemble_training.py --hidden 300 300 300 --repeats 2 # paper model
    PYTHONPATH=. /work/mbrl-venv/bin/python benchmarks/ensemble_training.py \
        --reference mbrl-lib --agents 1 --hidden 300 300 300 --threads 1 --repeats 3 --no-loop
"""

from __future__ import annotations

import argparse
import statistics
import time

import torch
from _common import REFERENCES, require_mbrl, train_ensembles
from tensordict import TensorDict
from torch import nn
from torch.nn import functional as F

from mapets_rl.machine import machine_line
from mapets_rl.models import ProbabilisticEnsemble
from mapets_rl.objectives import EnsembleNLLLoss, ensemble_optimizer, train_ensemble

OBS_DIM, ACT_DIM = 7, 1


def make_data(rows: int, n_agents: int) -> TensorDict:
    gen = torch.Generator().manual_seed(0)
    obs = torch.randn(rows, n_agents, OBS_DIM, generator=gen)
    act = torch.rand(rows, n_agents, ACT_DIM, generator=gen)
    nxt = obs + 0.1 * torch.tanh(obs.roll(1, -1)) + 0.05 * act
    return TensorDict(
        {
            ("agents", "observation"): obs,
            ("agents", "action"): act,
            ("next", "agents", "observation"): nxt,
        },
        [rows],
    )


def vectorized(data: TensorDict, args: argparse.Namespace) -> float:
    model = ProbabilisticEnsemble(OBS_DIM, ACT_DIM, args.agents, args.members, tuple(args.hidden))
    loss = EnsembleNLLLoss(model)
    optim = ensemble_optimizer(loss, lr=1e-3)
    start = time.perf_counter()
    train_ensemble(loss, optim, data, epochs=args.epochs, batch_size=args.batch_size)
    return time.perf_counter() - start


def loop(data: TensorDict, args: argparse.Namespace) -> float:
    sizes = (OBS_DIM + ACT_DIM, *args.hidden)
    nets, bounds = [], []
    for _ in range(args.agents * args.members):
        layers: list[nn.Module] = []
        for a, b in zip(sizes[:-1], sizes[1:], strict=True):
            layers += [nn.Linear(a, b), nn.SiLU()]
        nets.append(nn.Sequential(*layers, nn.Linear(sizes[-1], 2 * OBS_DIM)))
    for _ in range(args.agents):
        bounds.append(nn.Parameter(torch.full((2, OBS_DIM), 0.5)))
        with torch.no_grad():
            bounds[-1][1] = -10.0
    params = [p for net in nets for p in net.parameters()] + bounds
    optim = torch.optim.Adam(params, lr=1e-3)
    obs = data["agents", "observation"]
    act = data["agents", "action"]
    nxt = data["next", "agents", "observation"]
    rows = obs.shape[0]
    start = time.perf_counter()
    inputs = torch.cat([obs, act], -1)
    delta = nxt - obs
    in_mean, in_std = inputs.mean(0), inputs.std(0).clamp_min(1e-6)
    out_mean, out_std = delta.mean(0), delta.std(0).clamp_min(1e-6)
    for _ in range(args.epochs):
        order = torch.randperm(rows)
        for s in range(0, rows, args.batch_size):
            idx = order[s : s + args.batch_size]
            total = 0.0
            for i in range(args.agents):
                x = (inputs[idx, i] - in_mean[i]) / in_std[i]
                y = (delta[idx, i] - out_mean[i]) / out_std[i]
                max_lv, min_lv = bounds[i][0], bounds[i][1]
                for b in range(args.members):
                    boot = torch.randint(len(idx), (len(idx),))
                    mean, raw = nets[i * args.members + b](x[boot]).split(OBS_DIM, -1)
                    logvar = max_lv - F.softplus(max_lv - raw)
                    logvar = min_lv + F.softplus(logvar - min_lv)
                    nll = ((mean - y[boot]).pow(2) * torch.exp(-logvar) + logvar).sum(-1).mean()
                    total = total + nll
                total = total + 0.01 * (max_lv.sum() - min_lv.sum())
            optim.zero_grad(set_to_none=True)
            total.backward()
            optim.step()
    return time.perf_counter() - start


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--agents", type=int, default=8)
    parser.add_argument("--members", type=int, default=5)
    parser.add_argument("--hidden", type=int, nargs="+", default=[64, 64, 64])
    parser.add_argument("--transitions", type=int, default=2048, help="per agent")
    parser.add_argument("--epochs", type=int, default=5)
    parser.add_argument("--batch-size", type=int, default=128)
    parser.add_argument("--repeats", type=int, default=3, help="best of this many runs")
    parser.add_argument("--threads", type=int, default=None)
    parser.add_argument(
        "--no-loop", dest="loop", action="store_false", help="skip the per-member loop"
    )
    parser.add_argument(
        "--reference",
        choices=REFERENCES,
        default=None,
        help="also time mbrl-lib's ModelTrainer on the same workload (needs mbrl-lib, installed "
        "separately: without it this prints how and exits with status 2)",
    )
    args = parser.parse_args()
    if args.reference is not None:
        require_mbrl(args.reference)
    for name in ("agents", "members", "transitions", "epochs", "batch_size", "repeats"):
        if getattr(args, name) <= 0:
            parser.error(f"--{name.replace('_', '-')} must be positive")
    if args.threads is not None:
        torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    data = make_data(args.transitions, args.agents)
    steps = args.epochs * -(-args.transitions // args.batch_size)
    print(
        f"# {machine_line()}; I={args.agents}, "
        f"B={args.members}, hidden={args.hidden}, {args.transitions} transitions/agent, "
        f"{args.epochs} epochs x batch {args.batch_size} = {steps} steps"
    )
    # Alternate the variants (best of --repeats each) so load changes on a shared machine hit
    # all of them.
    times: dict[str, list[float]] = {"vectorized": []}
    if args.loop:
        times["loop"] = []
    if args.reference is not None:
        times["mbrl-lib"] = []
        obs = data["agents", "observation"]
        act = data["agents", "action"]
        nxt = data["next", "agents", "observation"]
    for _ in range(args.repeats):
        times["vectorized"].append(vectorized(data, args))
        if args.loop:
            times["loop"].append(loop(data, args))
        if args.reference is not None:
            seconds, losses = train_ensembles(
                obs, act, nxt, args.members, tuple(args.hidden), args.epochs, args.batch_size
            )
            times["mbrl-lib"].append(seconds)
    vec = min(times["vectorized"])
    print(f"vectorized (one batched program): {vec:8.2f} s  ({vec / steps * 1e3:.1f} ms/step)")
    if args.loop:
        ref = min(times["loop"])
        print(f"loop over agents x members:       {ref:8.2f} s  ({ref / steps * 1e3:.1f} ms/step)")
        print(f"speed-up: {ref / vec:.2f}x")
    if args.reference is not None:
        mbrl = [t / args.agents for t in times["mbrl-lib"]]
        ours = [t / args.agents for t in times["vectorized"]]
        paired = [m / o for m, o in zip(mbrl, ours, strict=True)]
        print(
            f"mbrl-lib ModelTrainer, {args.agents} separate trainers: per agent "
            f"{spread(mbrl)}; last-epoch training loss per agent "
            f"{[round(v, 3) for v in losses]} (mbrl-lib's NLL on unnormalised targets)"
        )
        print(
            f"HEADLINE I={args.agents}, hidden={args.hidden}: ours per agent {spread(ours)}; "
            f"mbrl-lib / ours per agent = {statistics.median(mbrl) / statistics.median(ours):.2f}x"
            f" (medians; per-repeat pairs {min(paired):.2f}..{max(paired):.2f}, "
            f"n={len(paired)})"
        )


def spread(values: list[float]) -> str:
    """``median (min..max)`` of timings in seconds."""
    return f"{statistics.median(values):.3f} s ({min(values):.3f}..{max(values):.3f})"


if __name__ == "__main__":
    from mapets_rl import quiet_dependencies

    quiet_dependencies()
    main()
