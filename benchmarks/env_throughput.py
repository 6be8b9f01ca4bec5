"""Environment throughput: env steps per second through the raw highway-env scenario, the
PettingZoo env and the TorchRL env, all measured in this run, plus the same figure-eight scenario
with highway-env's stock neighbour search as the reference.

CAVs drive the crash-free scripted policy (IDM + first come, first served at the crossing) so
every vehicle stays on the road; its cost is included in every layer alike. Every layer replays
the same seeded episode, so all of them simulate identical traffic. Layers: ``raw`` (the
highway-env scenario), ``pettingzoo``, ``torchrl``, ``raw, stock control`` (the raw scenario
with highway-env's own vehicle and lane control methods in place of our float-math overrides:
same trajectories, so the ratio is what the overrides save) and, on the figure-eight,
``stock-search`` (highway-env's stock neighbour search, lane tracking, all-pairs collision loop
and control methods: the reference).

Rates are steps per CPU-second of this process (single-threaded), measured in rounds in which
the layers take turns; the table gives the median rate and the spread (min..max) over rounds,
and the ratios are medians of the per-round ratios. Targets: ours >= 2x the stock-search
reference at 8 CAVs + 8 HVs and >= 3x at 22 + 20 on two lanes; the TorchRL env at most 20%
slower than the raw env at 8 + 8 (issue 14).

    PYTHONPATH=. python benchmarks/env_throughput.py [--steps 300] [--repeats 5]
        [--cases 8+8 22+20 freeway] [--backends freeway-merge] [--roads 1 64 256 1024]
        [--device cuda]

``--backends SCENARIO`` times the two backends of a freeway scenario side by side instead (issue
30): the highway-env TorchRL env (one road) against ``make_env(..., backend="torch",
num_envs=B)`` for each ``B`` of ``--roads``, with the fused CPU kernel and with the torch
program (``kernel="torch"``), every CAV keeping its lane, 30 vehicles, one thread; frames are
steps x roads, per CPU-second; ratios are medians of the per-round ratios to highway-env.
Targets: >= 400x highway-env at B >= 256 (at least 200x).

``--device cuda`` (with ``--backends``) steps the torch program on the GPU for each ``B`` of
``--roads`` beside highway-env and the CPU kernel at B = 256 on this host; GPU frames are per
wall-second (the GPU works while the process waits), the CPU layers per CPU-second as above.
"""

from __future__ import annotations

import argparse
import statistics
import time
from collections.abc import Callable

import torch

from mapets_rl.envs import ScriptedCAVPolicy, make_env, make_parallel_env
from mapets_rl.envs.vehicles import stock_control
from mapets_rl.machine import machine_line

CASES = {
    "8+8": ("figure-eight 8 CAVs + 8 HVs", "figure-eight", {"n_cavs": 8, "n_hvs": 8}),
    "22+20": (
        "figure-eight 22 CAVs + 20 HVs, 2 lanes",
        "figure-eight-multilane",
        {"n_cavs": 22, "n_hvs": 20},
    ),
    "freeway": ("freeway 30 vehicles", "freeway", {"n_vehicles": 30}),
}


def rate(run: Callable[[], int], device: str = "cpu") -> float:
    """Steps per CPU-second of one call of ``run`` (which returns the steps it took); on a GPU
    (``device="cuda"``) per wall-second, the GPU's queue drained before and after.

    Process CPU time, not wall time, on the CPU: everything here is single-threaded, and CPU
    time is far less disturbed by other processes sharing the machine.
    """
    if device == "cuda":
        torch.cuda.synchronize()
        start = time.perf_counter()
        steps = run()
        torch.cuda.synchronize()
        return steps / (time.perf_counter() - start)
    start = time.process_time()
    steps = run()
    return steps / (time.process_time() - start)


def raw_runner(name: str, config: dict, steps: int, stock: bool = False) -> Callable[[], int]:
    """The raw scenario; ``stock``: with highway-env's own vehicle/lane control methods in place
    of our float-math overrides (same trajectories)."""
    scenario = make_parallel_env(name, **config).env

    def episode() -> None:
        scenario.reset(seed=0)
        for _ in range(steps):
            _, _, terminated, truncated, _ = scenario.step(scenario.scripted_action())
            if terminated or truncated:
                scenario.reset()

    def run() -> int:
        if stock:
            with stock_control():
                episode()
        else:
            episode()
        return steps

    return run


def pettingzoo_runner(name: str, config: dict, steps: int) -> Callable[[], int]:
    env = make_parallel_env(name, **config)

    index = env.agent_index

    def run() -> int:
        env.reset(seed=0)
        for _ in range(steps):
            joint = env.env.scripted_action()
            actions = {a: joint[index[a]] for a in env.agents}
            env.step(actions)
            if not env.agents:
                env.reset()
        return steps

    return run


def torchrl_runner(name: str, config: dict, steps: int) -> Callable[[], int]:
    env = make_env(name, seed=0, **config)
    policy = ScriptedCAVPolicy(env)

    def run() -> int:
        with torch.no_grad():
            start = env.reset(seed=0)
            env.rollout(
                steps, policy, auto_reset=False, tensordict=start, break_when_any_done=False
            )
        return steps

    return run


def backend_runner(
    name: str, steps: int, roads: int | None, kernel: str = "auto", device: str = "cpu"
) -> Callable[[], int]:
    """Frames of ``steps`` keep-lane steps of scenario ``name`` at 30 vehicles: the highway-env
    backend (``roads=None``) or ``roads`` roads of the torch backend on ``device``."""
    if roads is None:
        env = make_env(name, seed=0, n_vehicles=30, categorical_actions=True)
    else:
        env = make_env(name, seed=0, backend="torch", num_envs=roads, n_vehicles=30,
                       categorical_actions=True, kernel=kernel, device=device)  # fmt: skip
    action = torch.zeros(
        env.full_action_spec["agents", "action"].shape, dtype=torch.long, device=env.device
    )

    def run() -> int:
        td = env.reset()
        with torch.no_grad():
            for _ in range(steps):
                td = env.step_and_maybe_reset(td.set(("agents", "action"), action))[1]
        return steps * (roads or 1)

    return run


def compare_backends(
    name: str, steps: int, repeats: int, road_counts: list[int], device: str = "cpu"
) -> None:
    """The two backends of freeway scenario ``name`` side by side (see module docstring)."""
    layers: dict[str, Callable[[], int]] = {"highway-env": backend_runner(name, steps, None)}
    devices = {"highway-env": "cpu"}
    if device == "cuda":
        layers["torch B=256, kernel (CPU)"] = backend_runner(name, steps, 256)
        for roads in road_counts:
            layers[f"torch B={roads}, cuda"] = backend_runner(name, steps, roads, device="cuda")
            devices[f"torch B={roads}, cuda"] = "cuda"
    else:
        for roads in road_counts:
            layers[f"torch B={roads}, kernel"] = backend_runner(name, steps, roads)
            layers[f"torch B={roads}, torch ops"] = backend_runner(name, steps, roads, "torch")
    for run in layers.values():  # warm-up (builds the kernel on first use)
        run()
    rates: dict[str, list[float]] = {layer: [] for layer in layers}
    for _ in range(repeats):
        for layer, run in layers.items():
            rates[layer].append(rate(run, devices.get(layer, "cpu")))
    unit = "CPU-s (GPU rows: wall-s)" if device == "cuda" else "CPU-s"
    print(f"\n{name}, 30 vehicles, keep lane: frames per {unit} (median, min..max), ratio")
    reference = rates["highway-env"]
    for layer, values in rates.items():
        ratio = statistics.median(v / r for v, r in zip(values, reference, strict=True))
        spread = f"{statistics.median(values):.0f} ({min(values):.0f}..{max(values):.0f})"
        print(f"{layer:28s} {spread:>28s} {ratio:8.1f}x")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--steps", type=int, default=300, help="env steps per timed run")
    parser.add_argument("--repeats", type=int, default=5, help="timed rounds per layer")
    parser.add_argument(
        "--cases", nargs="+", choices=sorted(CASES), default=list(CASES), help="cases to run"
    )
    parser.add_argument(
        "--backends", choices=["freeway", "freeway-merge"], default=None,
        help="compare the highway-env and torch backends of this scenario instead",
    )  # fmt: skip
    parser.add_argument("--roads", nargs="+", type=int, default=[1, 64, 256, 1024])
    parser.add_argument(
        "--device", choices=["cpu", "cuda"], default="cpu",
        help="with --backends: step the torch backend's roads on this device",
    )  # fmt: skip
    args = parser.parse_args()
    if args.device == "cuda" and (args.backends is None or not torch.cuda.is_available()):
        parser.error("--device cuda needs --backends and a CUDA device")
    torch.set_num_threads(1)
    print(f"# {machine_line()}")
    if args.backends is not None:
        if args.device == "cuda":
            print(f"GPU: {torch.cuda.get_device_name()}")
        compare_backends(args.backends, args.steps, args.repeats, args.roads, args.device)
        return

    print(f"{'case':42s} {'layer':20s} {'steps per CPU-s (median, min..max)':>36s}")
    ratios: dict[str, dict[str, float]] = {}
    for key in args.cases:
        label, name, config = CASES[key]
        layers = {
            "raw": raw_runner(name, config, args.steps),
            "pettingzoo": pettingzoo_runner(name, config, args.steps),
            "torchrl": torchrl_runner(name, config, args.steps),
        }
        layers["raw, stock control"] = raw_runner(name, config, args.steps, stock=True)
        if name.startswith("figure-eight"):
            stock = {**config, "stock_neighbour_search": True}
            layers["stock-search"] = raw_runner(name, stock, args.steps, stock=True)
        for run in layers.values():  # warm-up
            run()
        rates: dict[str, list[float]] = {layer: [] for layer in layers}
        for _ in range(args.repeats):  # layers take turns
            for layer, run in layers.items():
                rates[layer].append(rate(run))
        for layer, values in rates.items():
            spread = f"{statistics.median(values):.1f} ({min(values):.1f}..{max(values):.1f})"
            print(f"{label:42s} {layer:20s} {spread:>36s}")
        ratios[label] = {
            "overhead": statistics.median(
                r / t - 1.0 for r, t in zip(rates["raw"], rates["torchrl"], strict=True)
            ),
            "control": statistics.median(
                r / s for r, s in zip(rates["raw"], rates["raw, stock control"], strict=True)
            ),
        }
        if "stock-search" in rates:
            ratios[label]["speedup"] = statistics.median(
                r / s for r, s in zip(rates["raw"], rates["stock-search"], strict=True)
            )

    print("\nratios (medians of per-round ratios, same run)")
    for label, values in ratios.items():
        target = 20 if "8 CAVs + 8" in label else 30
        line = (
            f"{label:42s} torchrl overhead vs raw: {100 * values['overhead']:+.0f}% "
            f"(target <= +{target}%); float-math control: {values['control']:.2f}x"
        )
        if "speedup" in values:
            target = 3.0 if "22" in label else 2.0
            speedup = values["speedup"]
            line += f"; speed-up vs stock search: {speedup:.2f}x (target >= {target:.0f}x)"
        print(line)


if __name__ == "__main__":
    from mapets_rl import quiet_dependencies

    quiet_dependencies()
    main()
