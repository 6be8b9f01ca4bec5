"""Seconds per planning decision of TrajectorySamplingCEM, with in-run references.

For each preset (``paper``: Table II, ``cpu``: the scaled-down preset) and each number of agents
``I`` the script times one decision of the batched planner on the figure-eight reward and
reports, all measured in the same run:

* achieved GFLOP/s (2 x MACs of the MLP layers actually evaluated) and its ratio to a plain
  batched GEMM chain of the same layer shapes (``bmm`` only, no bias, activations or sampling);
* its ratio to the fastest whole-MLP kernel (bias and SiLU included) available here:
  ``baddbmm`` + in-place SiLU, per-member oneDNN linear with fused SiLU, and with
  ``--compile`` ``torch.compile`` (see :func:`mlp_kernels`);
* a naive reference planner (same algorithm, Python loops over agents and members, fp32);
* bf16 vs fp32: speed-up and the difference of the chosen actions (relative to the action
  range), next to the fp32 seed-to-seed spread as the noise floor;
* one call for ``I`` agents vs ``I`` separate single-agent calls;
* peak resident memory of the whole process during the decisions (VmHWM, reset before each one);
* with ``--reference mbrl-lib``: mbrl-lib's PETS agent (``TrajectoryOptimizerAgent`` + CEM +
  ``GaussianMLP`` ensemble, TS-inf; see ``benchmarks/_common.py``) at the same sizes,
  models (our weights copied), observations and reward: ``I`` separate ``agent.act(obs)``
  calls (mbrl-lib has no multi-agent batching), interleaved with our one call for the ``I``
  agents; the headline is our time per agent over mbrl-lib's (medians, with min..max).
  Optional: it needs mbrl-lib, which this script never installs (without it the flag prints
  how to install it beside the pinned torch and exits with status 2).

Examples::

    python benchmarks/planner.py --quick
    python benchmarks/planner.py --configs paper --agents 1 8 22 --dtypes fp32 --repeats 1
    python benchmarks/planner.py --configs cpu --agents 1 8 22 --dtypes fp32 bf16 --repeats 5
    python benchmarks/planner.py --quick --agents 8 --set noise_beta=2 keep_elites=0.3
    python benchmarks/planner.py --configs cpu --agents 1 8 22 --dtypes fp32 bf16 --compiled
    python benchmarks/planner.py --configs cpu --compiled --baseline population=32 compile=false
    python benchmarks/planner.py --device cuda --configs paper --agents 1 8 22 --dtypes fp32 bf16
    PYTHONPATH=. /work/mbrl-venv/bin/python benchmarks/planner.py --reference mbrl-lib \
        --configs paper --agents 1 --dtypes fp32 --threads 1 --repeats 2 --naive-max-agents 0
"""

from __future__ import annotations

import argparse
import statistics
import time
from collections.abc import Callable
from dataclasses import replace

import torch
from _common import REFERENCES, pets_agents, require_mbrl
from torch.nn import functional as F

from mapets_rl.config import parse_override
from mapets_rl.envs import registered_scenario
from mapets_rl.machine import machine_line
from mapets_rl.models import ProbabilisticEnsemble
from mapets_rl.planning import PRESETS, Preset, TrajectorySamplingCEM

OBS_DIM, ACT_DIM = 7, 1
LOW, HIGH = 0.0, 13.89
DTYPES = {"fp32": torch.float32, "bf16": torch.bfloat16}
#: The figure-eight's planner reward with the settings MA-PETS plans with (the registry's
#: section at its defaults).
figure_eight_reward = registered_scenario("figure-eight").planner_reward().reward
#: Where models, planners and reference kernels run (``--device``).
DEVICE = torch.device("cpu")


def make_model(cfg: Preset, n_agents: int, seed: int = 0) -> ProbabilisticEnsemble:
    """Random-weight ensemble with figure-eight-like normalisation statistics."""
    torch.manual_seed(seed)
    model = ProbabilisticEnsemble(OBS_DIM, ACT_DIM, n_agents, **cfg.model.model_kwargs())
    with torch.no_grad():
        mean = torch.tensor([7.0, 0.0, 0.0, 7.0, 7.0, 30.0, 30.0, 7.0])
        std = torch.tensor([4.0, 60.0, 60.0, 4.0, 4.0, 20.0, 20.0, 4.0])
        model.input_mean.copy_(mean.expand_as(model.input_mean))
        model.input_std.copy_(std.expand_as(model.input_std))
        model.output_std.fill_(0.2)
    return model.requires_grad_(False)


def make_obs(n_agents: int, seed: int = 1) -> torch.Tensor:
    gen = torch.Generator().manual_seed(seed)
    obs = torch.rand(n_agents, OBS_DIM, generator=gen)
    scale = torch.tensor([13.89, 200.0, 200.0, 13.89, 13.89, 75.0, 75.0])
    return obs * scale - torch.tensor([0.0, 100.0, 100.0, 0.0, 0.0, 0.0, 0.0])


def macs_per_row(cfg: Preset) -> int:
    sizes = (OBS_DIM + ACT_DIM, *cfg.model.hidden, 2 * OBS_DIM)
    return sum(a * b for a, b in zip(sizes[:-1], sizes[1:], strict=True))


def flops(cfg: Preset, n_agents: int, iterations: int) -> float:
    rows = n_agents * cfg.planner.population * cfg.planner.particles
    return 2.0 * macs_per_row(cfg) * rows * cfg.planner.horizon * iterations


class PeakMemory:
    """Peak resident set size (MiB) of this process inside a ``with`` block."""

    def __enter__(self) -> PeakMemory:
        if DEVICE.type == "cuda":
            torch.cuda.reset_peak_memory_stats(DEVICE)
            return self
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")
        return self

    def __exit__(self, *exc) -> None:
        if DEVICE.type == "cuda":
            self.peak = torch.cuda.max_memory_allocated(DEVICE) / 2**20
            return
        self.peak = self._read("VmHWM")

    @staticmethod
    def _read(field: str) -> float:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith(field):
                    return int(line.split()[1]) / 1024
        raise RuntimeError(f"{field} not in /proc/self/status")


def gemm_chain(cfg: Preset, n_agents: int) -> Callable[[int], None]:
    """Plain ``bmm`` chain with the planner's layer shapes; call it with a number of model steps.

    No bias, activation, sampling or reward: the ceiling the planner's matmuls could reach.
    """
    groups = n_agents * cfg.model.ensemble_size
    rows = cfg.planner.population * cfg.planner.particles // cfg.model.ensemble_size
    sizes = (OBS_DIM + ACT_DIM, *cfg.model.hidden, 2 * OBS_DIM)
    weights = [
        torch.randn(groups, a, b, device=DEVICE) * 0.05
        for a, b in zip(sizes[:-1], sizes[1:], strict=True)
    ]
    x = torch.randn(groups, rows, sizes[0], device=DEVICE)

    def chain(steps: int) -> None:
        for _ in range(steps):
            h = x
            for w in weights:
                h = torch.bmm(h, w)

    return chain


def mlp_kernels(
    cfg: Preset, n_agents: int, compile_reference: bool = False
) -> dict[str, Callable[[int], None]]:
    """Candidate kernels for the whole MLP (bias and SiLU included) at the planner's shapes.

    Each is called with a number of model steps. The planner is reported as a fraction of
    the fastest of them (the "fastest same-shape kernel available" on this machine):

    * ``baddbmm+silu``: one ``baddbmm`` per layer over all ``I * B`` members, SiLU in place;
    * ``onednn``: per member ``torch.ops.mkldnn._linear_pointwise`` (oneDNN GEMM with the
      bias and the SiLU ("swish") fused), a Python loop over the ``I * B`` members;
    * ``compile``: ``torch.compile`` (inductor, CPU) of the baddbmm chain (``--compile``).
    """
    groups = n_agents * cfg.model.ensemble_size
    rows = cfg.planner.population * cfg.planner.particles // cfg.model.ensemble_size
    sizes = (OBS_DIM + ACT_DIM, *cfg.model.hidden, 2 * OBS_DIM)
    gen = torch.Generator().manual_seed(0)
    weights = [
        torch.randn(groups, a, b, generator=gen) * 0.1
        for a, b in zip(sizes[:-1], sizes[1:], strict=True)
    ]
    biases = [torch.randn(groups, 1, b, generator=gen) * 0.1 for b in sizes[1:]]
    x = torch.randn(groups, rows, sizes[0], generator=gen)
    weights, biases, x = (
        [w.to(DEVICE) for w in weights],
        [b.to(DEVICE) for b in biases],
        x.to(DEVICE),
    )
    last = len(weights) - 1

    def baddbmm_mlp() -> torch.Tensor:
        h = x
        for layer, (w, b) in enumerate(zip(weights, biases, strict=True)):
            h = torch.baddbmm(b, h, w)
            if layer < last:
                F.silu(h, inplace=True)
        return h

    kernels: dict[str, Callable[[], torch.Tensor]] = {"baddbmm+silu": baddbmm_mlp}
    onednn = torch.backends.mkldnn.is_available() and DEVICE.type == "cpu"
    if onednn and hasattr(torch.ops.mkldnn, "_linear_pointwise"):
        linear = torch.ops.mkldnn._linear_pointwise
        members_w = [[w[g].t().contiguous() for w in weights] for g in range(groups)]
        members_b = [[b[g, 0].contiguous() for b in biases] for g in range(groups)]

        def onednn_mlp() -> torch.Tensor:
            outs = []
            for g in range(groups):
                h = x[g]
                for layer in range(last + 1):
                    act = "swish" if layer < last else "none"
                    h = linear(h, members_w[g][layer], members_b[g][layer], act, [], "")
                outs.append(h)
            return torch.stack(outs)

        torch.testing.assert_close(onednn_mlp(), baddbmm_mlp(), rtol=1e-4, atol=1e-4)
        kernels["onednn"] = onednn_mlp
    if compile_reference:
        compiled = torch.compile(baddbmm_mlp, dynamic=False)
        start = time.perf_counter()
        compiled()
        print(f"      torch.compile of the MLP: {time.perf_counter() - start:.1f} s")
        kernels["compile"] = compiled

    def repeat(fn: Callable[[], torch.Tensor]) -> Callable[[int], None]:
        def run(steps: int) -> None:
            for _ in range(steps):
                fn()

        return run

    return {name: repeat(fn) for name, fn in kernels.items()}


def timed(fn: Callable[[], object]) -> float:
    if DEVICE.type == "cuda":
        torch.cuda.synchronize(DEVICE)
    start = time.perf_counter()
    fn()
    if DEVICE.type == "cuda":
        torch.cuda.synchronize(DEVICE)
    return time.perf_counter() - start


@torch.no_grad()
def naive_plan(
    model: ProbabilisticEnsemble, cfg: Preset, obs: torch.Tensor, gen: torch.Generator
) -> torch.Tensor:
    """Reference: the same TS-inf CEM with Python loops over agents and members (fp32)."""
    members, per = cfg.model.ensemble_size, cfg.planner.particles // cfg.model.ensemble_size
    shape = (cfg.planner.population, cfg.planner.horizon, ACT_DIM)
    actions = []
    for i in range(model.n_agents):
        mu = torch.full((cfg.planner.horizon, ACT_DIM), (LOW + HIGH) / 2)
        std = torch.full_like(mu, (HIGH - LOW) / 4)
        for _ in range(cfg.planner.iterations):
            cand = (mu + std * torch.randn(shape, generator=gen)).clamp(LOW, HIGH)
            returns = torch.zeros(members, per, cfg.planner.population)
            state = obs[i].expand(members, per, cfg.planner.population, OBS_DIM).clone()
            for t in range(cfg.planner.horizon):
                act = cand[:, t].expand(per, -1, -1)
                nxt = torch.empty_like(state)
                for b in range(members):
                    x = torch.cat([state[b], act], -1).reshape(-1, OBS_DIM + ACT_DIM)
                    h = (x - model.input_mean[i, 0, 0]) / model.input_std[i, 0, 0]
                    for layer in range(len(model.weights)):
                        h = torch.addmm(model.biases[layer][i, b, 0], h, model.weights[layer][i, b])
                        if layer < len(model.weights) - 1:
                            h = F.silu(h)
                    mean, raw = h.split(OBS_DIM, -1)
                    logvar = model.max_logvar[i, 0, 0] - F.softplus(model.max_logvar[i, 0, 0] - raw)
                    logvar = model.min_logvar[i, 0, 0] + F.softplus(
                        logvar - model.min_logvar[i, 0, 0]
                    )
                    mean = mean * model.output_std[i, 0, 0] + model.output_mean[i, 0, 0]
                    std_out = torch.exp(0.5 * logvar) * model.output_std[i, 0, 0]
                    delta = mean + std_out * torch.randn(mean.shape, generator=gen)
                    nxt[b] = state[b] + delta.reshape(per, cfg.planner.population, OBS_DIM)
                returns += figure_eight_reward(state, act.expand(members, -1, -1, -1), nxt)
                state = nxt
            scores = returns.mean((0, 1)).nan_to_num(float("-inf"))
            elites = cand[scores.topk(cfg.planner.elites).indices]
            mu = cfg.planner.alpha * mu + (1 - cfg.planner.alpha) * elites.mean(0)
            std = cfg.planner.alpha * std + (1 - cfg.planner.alpha) * elites.std(0, unbiased=False)
            if std.max() < cfg.planner.epsilon:
                break
        actions.append(mu[0].clamp(LOW, HIGH))
    return torch.stack(actions)


def bench(name: str, cfg: Preset, n_agents: int, args: argparse.Namespace) -> None:
    """Time every variant once per repeat, interleaved, and keep each variant's fastest run."""
    obs = make_obs(n_agents).to(DEVICE)
    model = make_model(cfg, n_agents).to(DEVICE)
    modes: dict[str, dict] = {"": {"compile": False} if args.compiled else {}}
    if args.graph:
        modes["+graph"] = {"cuda_graph": True}
    if args.compiled:
        modes["+compiled"] = {"compile": True}
    planners = {
        key + suffix: TrajectorySamplingCEM(
            model,
            figure_eight_reward,
            LOW,
            HIGH,
            seed=0,
            config=cfg.planner,
            dtype=DTYPES[key],
            **settings,
        )
        for suffix, settings in modes.items()
        for key in args.dtypes
    }
    baseline_settings = dict(map(parse_override, args.baseline))
    if baseline_settings:
        for key in args.dtypes:
            planners[f"{key}@baseline"] = TrajectorySamplingCEM(
                model,
                figure_eight_reward,
                LOW,
                HIGH,
                seed=0,
                config=cfg.planner.replace(**baseline_settings),
                dtype=DTYPES[key],
            )
    first: dict[str, torch.Tensor] = {}  # cold-start decisions, to compare dtypes

    def decide(key: str) -> None:
        action = planners[key].plan(obs)
        first.setdefault(key, action)

    variants: dict[str, Callable[[], object]] = {
        key: (lambda key=key: decide(key)) for key in planners
    }
    if n_agents > 1 and args.separate and DEVICE.type == "cpu":
        single = [
            TrajectorySamplingCEM(
                make_model(cfg, 1, seed=i),
                figure_eight_reward,
                LOW,
                HIGH,
                seed=0,
                config=cfg.planner,
                dtype="fp32",
            )
            for i in range(n_agents)
        ]
        variants["separate"] = lambda: [p.plan(o[None]) for p, o in zip(single, obs, strict=True)]
    if n_agents <= args.naive_max_agents and DEVICE.type == "cpu":
        gen = torch.Generator().manual_seed(0)
        variants["naive"] = lambda: naive_plan(model, cfg, obs, gen)
    if args.reference == "mbrl-lib":
        reward = registered_scenario("figure-eight").planner_reward(headway=0.0).reward
        agents = pets_agents(model, cfg, LOW, HIGH, reward, seed=0, device=str(DEVICE))
        obs_np = obs.cpu().numpy()
        variants["mbrl-lib"] = lambda: [
            agent.act(o) for agent, o in zip(agents, obs_np, strict=True)
        ]
    for _ in range(args.warmup):
        for fn in variants.values():
            fn()
    compile_seconds = {
        key: planner.compiled_step.compile_seconds
        for key, planner in planners.items()
        if planner.compiled_step is not None
    }
    chain = gemm_chain(cfg, n_agents)
    chain(1)
    kernels = mlp_kernels(cfg, n_agents, args.compile)
    for kernel in kernels.values():
        kernel(1)
    times: dict[str, list[float]] = {key: [] for key in [*variants, "gemm", *kernels]}
    peak = dict.fromkeys(planners, 0.0)
    iters = cfg.planner.iterations
    for _ in range(args.repeats):
        for key, fn in variants.items():
            if key in planners:
                with PeakMemory() as mem:
                    times[key].append(timed(fn))
                peak[key] = max(peak[key], mem.peak)
                iters = planners[key].last_iterations
            else:
                times[key].append(timed(fn))
        steps = cfg.planner.horizon * iters
        times["gemm"].append(timed(lambda steps=steps: chain(steps)))
        for kernel_name, kernel in kernels.items():
            times[kernel_name].append(timed(lambda steps=steps, kernel=kernel: kernel(steps)))
    best = {key: min(v) for key, v in times.items()}
    total = flops(cfg, n_agents, iters)
    line = f"{name:>5} I={n_agents:<3d}"
    for key in planners:
        planner_cfg = cfg.planner.replace(**baseline_settings) if "@" in key else cfg.planner
        work = flops(replace(cfg, planner=planner_cfg), n_agents, iters)
        line += (
            f" | {key}: {best[key]:8.3f} s/decision {work / best[key] / 1e9:6.1f} GFLOP/s "
            f"peak RSS {peak[key]:6.0f} MiB"
        )
    print(line)
    for key in args.dtypes:
        if f"{key}+graph" in planners:
            eager, graphed = times[key], times[f"{key}+graph"]
            diff = (first[f"{key}+graph"] - first[key]).abs().max().item() / (HIGH - LOW)
            print(
                f"      CUDA graph {key}: eager {spread(eager)}, graphed {spread(graphed)} -> "
                f"{statistics.median(eager) / statistics.median(graphed):.2f}x (medians); "
                f"max |a_graph - a_eager| = {diff:.2e} of range; "
                f"{planners[f'{key}+graph'].graph_captures} capture(s)"
            )
    for key in args.dtypes:
        if f"{key}+compiled" in planners:
            eager, fast = times[key], times[f"{key}+compiled"]
            diff = (first[f"{key}+compiled"] - first[key]).abs().max().item() / (HIGH - LOW)
            step = planners[f"{key}+compiled"].compiled_step
            print(
                f"      compiled {key}: eager {spread(eager)}, compiled {spread(fast)} -> "
                f"{statistics.median(eager) / statistics.median(fast):.2f}x (medians); "
                f"max |a_compiled - a_eager| = {diff:.2e} of range; compile "
                f"{compile_seconds[f'{key}+compiled']:.1f} s (first decision, untimed; "
                f"{step.compiles} graph(s))"
                + (f"; EAGER FALLBACK: {step.fallback_reason}" if step.fallback_reason else "")
            )
    for key in args.dtypes:
        if f"{key}@baseline" in planners:
            base = times[f"{key}@baseline"]
            for other in [k for k in planners if k.split("+")[0] == key]:
                print(
                    f"      vs baseline ({' '.join(args.baseline)}), {key}: baseline "
                    f"{spread(base)}, {other} {spread(times[other])} -> "
                    f"{statistics.median(base) / statistics.median(times[other]):.2f}x (medians)"
                )
    gemm = best["gemm"]
    if "fp32" not in planners:
        return
    sec = best["fp32"]
    print(
        f"      GEMM chain {gemm:8.3f} s ({total / gemm / 1e9:.1f} GFLOP/s):"
        f" fp32 planner reaches {gemm / sec:.2f} of GEMM ({iters} CEM iterations)"
    )
    fastest = min(kernels, key=lambda k: best[k])
    listing = ", ".join(f"{k} {best[k]:.3f} s" for k in kernels)
    print(
        f"      whole-MLP kernels (bias + SiLU): {listing}; fastest {fastest}: fp32 planner "
        f"reaches {best[fastest] / sec:.2f} of it"
    )
    if "bf16" in planners:
        action32, action16 = first["fp32"], first["bf16"]
        other = TrajectorySamplingCEM(
            model,
            figure_eight_reward,
            LOW,
            HIGH,
            seed=123,
            config=cfg.planner,
            dtype="fp32",
        )
        seed_spread = (other.plan(obs) - action32).abs().max().item() / (HIGH - LOW)
        diff = (action16 - action32).abs().max().item() / (HIGH - LOW)
        print(
            f"      bf16 speed-up over fp32: {sec / best['bf16']:.2f}x; max |a_bf16 - a_fp32| = "
            f"{diff:.2e} of range (fp32 seed-to-seed spread: {seed_spread:.2e})"
        )
    if "separate" in best:
        print(
            f"      {n_agents} separate I=1 calls: {best['separate']:8.3f} s -> one batched call "
            f"is {best['separate'] / sec:.2f}x faster"
        )
    if "naive" in best:
        print(
            f"      naive loops (agents x members, fp32): {best['naive']:8.3f} s -> batched "
            f"planner is {best['naive'] / sec:.2f}x faster"
        )
    if name == "cpu":
        print(f"      200-step episode at this I: ~{200 * sec:.1f} s of planning (fp32)")
    if "mbrl-lib" in times:
        reference_headline(times, planners, n_agents)


def spread(values: list[float]) -> str:
    """``median (min..max)`` of timings in seconds."""
    return f"{statistics.median(values):.4f} s ({min(values):.4f}..{max(values):.4f})"


def reference_headline(times: dict[str, list[float]], planners: dict, n_agents: int) -> None:
    """Our seconds per agent and decision over mbrl-lib's, from the interleaved repeats."""
    ref = [t / n_agents for t in times["mbrl-lib"]]
    print(f"      mbrl-lib PETS, {n_agents} separate agents: per agent {spread(ref)}")
    for key in planners:
        ours = [t / n_agents for t in times[key]]
        paired = [r / o for r, o in zip(ref, ours, strict=True)]
        ratio = statistics.median(ref) / statistics.median(ours)
        print(
            f"      HEADLINE {key}, I={n_agents} in one call: per agent {spread(ours)}; "
            f"mbrl-lib / ours per agent = {ratio:.2f}x (medians; per-repeat pairs "
            f"{min(paired):.2f}..{max(paired):.2f}, n={len(paired)})"
        )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--configs", nargs="+", default=["cpu", "paper"], choices=list(PRESETS))
    parser.add_argument("--agents", nargs="+", type=int, default=[1, 8, 22])
    parser.add_argument("--dtypes", nargs="+", default=["fp32", "bf16"], choices=list(DTYPES))
    parser.add_argument("--repeats", type=int, default=2, help="timed decisions per setting")
    parser.add_argument(
        "--naive-max-agents", type=int, default=8, help="run the naive reference up to this I"
    )
    parser.add_argument(
        "--no-separate",
        dest="separate",
        action="store_false",
        help="skip timing I separate single-agent calls",
    )
    parser.add_argument("--threads", type=int, default=None, help="torch intra-op threads")
    parser.add_argument(
        "--device",
        default="cpu",
        help="cpu or cuda[:i]: models, planners and reference kernels (naive and separate "
        "references run on the CPU only); peak memory is then the device's allocator peak",
    )
    parser.add_argument("--warmup", type=int, default=1, help="untimed decisions first")
    parser.add_argument(
        "--iterations",
        type=int,
        default=None,
        help="override the presets' CEM iterations (time per decision scales linearly)",
    )
    parser.add_argument(
        "--set",
        nargs="*",
        default=[],
        metavar="key=value",
        help="override PlannerConfig fields of the presets, e.g. noise_beta=2 keep_elites=0.3 "
        "(iCEM's options: add optimizer=icem to the paper preset's; the FLOP counts keep "
        "assuming Q candidates per iteration)",
    )
    parser.add_argument(
        "--compile",
        action="store_true",
        help="also time torch.compile (inductor) of the MLP as a reference kernel",
    )
    parser.add_argument(
        "--graph",
        action="store_true",
        help="also time each dtype with cuda_graph=True (the decision captured once and "
        "replayed; --device cuda only); the capture is the untimed warm-up call",
    )
    parser.add_argument(
        "--compiled",
        action="store_true",
        help="also time each dtype with compile=True (the rollout step through torch.compile; "
        "the compilation is the untimed warm-up call, its seconds are printed)",
    )
    parser.add_argument(
        "--baseline",
        nargs="*",
        default=[],
        metavar="key=value",
        help="also time, interleaved, a baseline planner: the preset with these PlannerConfig "
        "fields (e.g. the cpu preset before issue 24: population=32 compile=false), and print "
        "each variant's speed-up over it",
    )
    parser.add_argument("--quick", action="store_true", help="cpu preset, I in {1, 8}, 2 repeats")
    parser.add_argument(
        "--reference",
        choices=REFERENCES,
        default=None,
        help="also time mbrl-lib's PETS agent at the same config (needs mbrl-lib, installed "
        "separately: without it this prints how and exits with status 2)",
    )
    args = parser.parse_args()
    if args.reference is not None:
        require_mbrl(args.reference)
    if args.quick:
        args.configs, args.agents, args.repeats = ["cpu"], [1, 8], 2
    if args.repeats <= 0 or args.warmup < 0 or any(i <= 0 for i in args.agents):
        parser.error("--repeats and --agents must be positive, --warmup non-negative")
    if args.compiled and args.warmup < 1:
        parser.error("--compiled needs --warmup >= 1 (the compilation must not be timed)")
    if args.threads is not None:
        torch.set_num_threads(args.threads)
    global DEVICE
    DEVICE = torch.device(args.device)
    if DEVICE.type == "cuda" and not torch.cuda.is_available():
        parser.error("--device cuda: torch.cuda.is_available() is False on this machine")
    if args.graph and DEVICE.type != "cuda":
        parser.error("--graph needs --device cuda (CUDA graphs)")
    if DEVICE.type == "cuda":
        print(f"device {torch.cuda.get_device_name(DEVICE)}")
    print(f"# {machine_line()}")
    for name in args.configs:
        cfg = PRESETS[name]
        if args.iterations is not None:
            cfg = replace(cfg, planner=replace(cfg.planner, iterations=args.iterations))
        if args.set:
            cfg = replace(cfg, planner=cfg.planner.replace(**dict(map(parse_override, args.set))))
        print(f"\n[{name}] {cfg}  ({macs_per_row(cfg)} MACs per model row)")
        for n_agents in args.agents:
            bench(name, cfg, n_agents, args)


if __name__ == "__main__":
    from mapets_rl import quiet_dependencies

    quiet_dependencies()
    main()
