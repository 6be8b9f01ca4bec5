"""Learner throughput: frames per second of the model-free recipes on the batched torch freeway,
and where the time goes.

Each recipe trains through the iteration of ``Experiment.train`` (``train_on_batch``:
collector -> ``train_step`` -> metrics -> policy weights) on
``make_env(ENV, backend="torch", num_envs=B)``, after a warm-up
that fills its replay buffer past ``batch_size`` (and ``init_random_frames``) so that every
measured round updates at the configured ratio. A round is ``--frames`` frames (a frame is one
step of one road, all its CAVs together); per round we time, in wall-clock seconds of this
process:

- ``env``: the env's own step and reset (``TorchFreewayEnv._step`` / ``_reset``),
- ``policy``: the rest of the collector's work (policy forward, tensordict bookkeeping),
- ``learner``: ``train_step`` (replay writes and samples, losses, backward, optimiser, target
  updates, observation statistics),
- ``other``: the loop's metrics and policy-weight sync.

Evaluation, checkpoints and logging are not in the rounds (a run pays them every
``eval_interval`` / ``checkpoint_interval`` frames; see ``--budget``). The table gives the
median over rounds and the spread (min..max); ``4M-frame run`` extrapolates the median rate to
``--budget`` frames. The machine may be shared: the load average is printed before and after.

    python benchmarks/learner_throughput.py [--recipes maddpg shapley_ac] [--configs NAME ...]
        [--num-envs 256] [--vehicles 30] [--steps 4] [--frames 20480] [--rounds 3]
        [--threads 2] [--schedule openai] [--device cuda] [key=value ...]

``--device cuda`` puts the roads, the networks and the replay buffer on the GPU
(``device=cuda``, ``env_config.device=cuda``); every phase then drains the GPU's queue before
its clock stops, so that its wall time is its own.

``--configs NAME ...`` measures published configurations as they are (``mapets-rl configs``;
``--num-envs`` and ``--steps`` still set the roads and the batch), e.g. the Shapley arm of the
1M-frame study beside its fast twin and per-agent MADDPG, with each row's frames/s over the
first row's (one run, so the ratios share the machine's load)::

    python benchmarks/learner_throughput.py --recipes --configs freeway-merge/shapley-arm \
        freeway-merge/shapley-arm-fast freeway-merge/maddpg-individual --frames 10240 --threads 1

``--schedule openai`` applies :data:`mapets_rl.recipes.maddpg.OPENAI_MADDPG` (one update per 100
frames, batch 1024, ...) to every recipe (the Shapley AC and SAC configs share the fields);
``key=value`` overrides follow it (e.g. ``update_interval=400``).
"""

from __future__ import annotations

import argparse
import os
import shutil
import statistics
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from mapets_rl.machine import machine_line
from mapets_rl.threads import THREADS_ENV, prepare_process

WAIT_POLICY = prepare_process()  # OpenMP threads sleep when idle, as in `mapets-rl`

import torch  # noqa: E402  (after the OpenMP wait policy is set)

RECIPES = ("maddpg", "m3ddpg", "sac", "shapley_ac", "mappo", "coma")
PHASES = ("env", "policy", "learner", "other")


def load() -> str:
    """The 1, 5 and 15-minute load averages."""
    try:
        return " ".join(f"{x:.2f}" for x in os.getloadavg())
    except OSError:
        return "n/a"


def build_published(name: str, args: argparse.Namespace, run_dir: Path) -> Any:
    """The published configuration ``name`` as it is (its scenario, schedule and settings) on
    ``args.num_envs`` roads x ``args.steps`` steps per batch, with the command line's
    ``key=value`` overrides."""
    from mapets_rl.app.plugins import load_recipe
    from mapets_rl.experiment.published import load_published

    published = load_published(name)
    cls = load_recipe(published.recipe)
    measured = [
        f"env_config.num_envs={args.num_envs}",
        f"env_config.device={args.device}",
        f"frames_per_batch={args.num_envs * args.steps}",
        "total_frames=1000000000000",
        "eval_interval=0",
        "checkpoint_interval=0",
        "progress=false",
        "logger=none",
        f"device={args.device}",
    ]
    return cls(cls.Config.from_fields(published.fields, [*measured, *args.overrides]), run_dir)


def build(recipe: str, args: argparse.Namespace, run_dir: Path) -> Any:
    """The ``recipe`` experiment on ``args.num_envs`` roads of the batched torch freeway; a
    name with a ``/`` is a published configuration (:func:`build_published`)."""
    from mapets_rl.app.plugins import load_recipe
    from mapets_rl.recipes.maddpg import OPENAI_MADDPG

    if "/" in recipe:
        return build_published(recipe, args, run_dir)
    cls = load_recipe(recipe)
    env_config = {
        "backend": "torch",
        "num_envs": args.num_envs,
        "n_vehicles": args.vehicles,
        "cav_ratio": args.cav_ratio,
        "device": args.device,
    }
    config = cls.Config(
        env=args.env,
        env_config=env_config,
        frames_per_batch=args.num_envs * args.steps,
        total_frames=10**12,
        eval_interval=0,
        checkpoint_interval=0,
        progress=False,
        logger="none",
        device=args.device,
    )
    fields = set(cls.Config.field_names())
    schedule = OPENAI_MADDPG if args.schedule == "openai" else ()
    # the recipe's fields of the schedule, then the command line's (which win)
    overrides = {o.partition("=")[0]: o for o in schedule if o.partition("=")[0] in fields}
    overrides.update({o.partition("=")[0]: o for o in args.overrides})
    return cls(config.with_overrides(list(overrides.values())), run_dir)


def drain(device: str) -> None:
    """Wait for the GPU's queued work (nothing to wait for on the CPU)."""
    if device == "cuda":
        torch.cuda.synchronize()


def timed(owner: Any, name: str, clock: dict[str, float], key: str, device: str) -> None:
    """Replace method ``name`` of ``owner`` by one that adds its wall time to ``clock[key]``."""
    method: Callable[..., Any] = getattr(owner, name)

    def wrapper(*a: Any, **kw: Any) -> Any:
        drain(device)
        start = time.perf_counter()
        try:
            return method(*a, **kw)
        finally:
            drain(device)
            clock[key] += time.perf_counter() - start

    setattr(owner, name, wrapper)


def measure(recipe: str, args: argparse.Namespace, run_dir: Path) -> list[dict[str, float]]:
    """Per round: frames/s and the seconds of each phase."""
    exp = build(recipe, args, run_dir)
    clock = dict.fromkeys(("env", "collect", "learner"), 0.0)
    exp.reset_collector()
    env = exp.collector.env
    timed(env, "_step", clock, "env", args.device)
    timed(env, "_reset", clock, "env", args.device)
    timed(exp.collector, "next", clock, "collect", args.device)
    timed(exp, "train_step", clock, "learner", args.device)
    cfg = exp.config
    warm = max(getattr(cfg, "batch_size", 0), getattr(cfg, "init_random_frames", 0))
    warm = max(warm + cfg.frames_per_batch, args.warmup_frames)
    while exp.frames < warm:
        exp.train_on_batch()
    rounds = []
    for _ in range(args.rounds):
        for key in clock:
            clock[key] = 0.0
        drain(args.device)
        start, frames = time.perf_counter(), exp.frames
        while exp.frames - frames < args.frames:
            exp.train_on_batch()
        drain(args.device)
        wall = time.perf_counter() - start
        rounds.append(
            {
                "fps": (exp.frames - frames) / wall,
                "frames": exp.frames - frames,
                "wall": wall,
                "env": clock["env"],
                "policy": clock["collect"] - clock["env"],
                "learner": clock["learner"],
                "other": wall - clock["collect"] - clock["learner"],
            }
        )
    exp.collector.shutdown()
    exp.close()
    if torch.get_num_threads() != args.threads:
        raise RuntimeError(f"ran on {torch.get_num_threads()} threads, not {args.threads}")
    return rounds


def spread(values: list[float], fmt: str = "{:.0f}") -> str:
    """``median (min..max)``."""
    med = statistics.median(values)
    return f"{fmt.format(med)} ({fmt.format(min(values))}..{fmt.format(max(values))})"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--recipes", nargs="*", default=["maddpg", "shapley_ac"], choices=RECIPES)
    parser.add_argument(
        "--configs",
        nargs="*",
        default=[],
        metavar="NAME",
        help="published configurations measured as they are (mapets-rl configs), after "
        "--recipes; the last column is each row's frames/s over the first row's",
    )
    parser.add_argument("--env", default="freeway-merge", choices=["freeway", "freeway-merge"])
    parser.add_argument("--num-envs", type=int, default=256, help="roads B of the batched env")
    parser.add_argument("--vehicles", type=int, default=30, help="n_vehicles")
    parser.add_argument("--cav-ratio", type=float, default=1.0, help="cav_ratio")
    parser.add_argument("--steps", type=int, default=4, help="steps of every road per batch")
    parser.add_argument("--frames", type=int, default=20_480, help="frames per measured round")
    parser.add_argument("--rounds", type=int, default=3, help="measured rounds per recipe")
    parser.add_argument("--warmup-frames", type=int, default=0, help="frames before round 1")
    parser.add_argument("--threads", type=int, default=torch.get_num_threads())
    parser.add_argument("--schedule", choices=["default", "openai"], default="default")
    parser.add_argument("--budget", type=int, default=4_000_000, help="frames to extrapolate to")
    parser.add_argument("--device", choices=["cpu", "cuda"], default="cpu")
    parser.add_argument("overrides", nargs="*", metavar="key=value", help="config overrides")
    args = parser.parse_args()
    if args.device == "cuda" and not torch.cuda.is_available():
        parser.error("--device cuda needs a CUDA device")
    if args.num_envs < 1 or args.steps < 1 or args.frames < 1 or args.rounds < 1:
        parser.error("--num-envs, --steps, --frames and --rounds must be >= 1")
    if args.threads < 1:
        parser.error("--threads must be >= 1")
    # an explicit count: the experiments keep it (they would choose by the load otherwise)
    os.environ[THREADS_ENV] = str(args.threads)
    torch.set_num_threads(args.threads)
    print(f"# {machine_line()}, OpenMP wait policy {WAIT_POLICY}")
    print(
        f"{args.env}, {args.vehicles} vehicles (cav_ratio {args.cav_ratio}), B = {args.num_envs} "
        f"roads x {args.steps} steps per batch; schedule {args.schedule} {' '.join(args.overrides)}"
    )
    if args.device == "cuda":
        print(f"GPU: {torch.cuda.get_device_name()}; roads, networks and replay on the GPU")
    print(f"load average before: {load()}")
    rows = [*args.recipes, *args.configs]
    if not rows:
        parser.error("give --recipes or --configs")
    width = max(11, *map(len, rows))
    header = f"{'recipe':<{width}} {'frames/s':>20} " + " ".join(f"{p + ' %':>14}" for p in PHASES)
    print(header + f" {'budget run (h)':>15} {'x first row':>12}")
    root = Path(tempfile.mkdtemp(prefix="learner_throughput_"))
    first = None
    try:
        for index, row in enumerate(rows):
            rounds = measure(row, args, root / str(index))
            shares = {p: [100 * r[p] / r["wall"] for r in rounds] for p in PHASES}
            fps = [r["fps"] for r in rounds]
            first = first or statistics.median(fps)
            hours = args.budget / statistics.median(fps) / 3600
            cells = " ".join(f"{spread(shares[p], '{:.1f}'):>14}" for p in PHASES)
            ratio = statistics.median(fps) / first
            print(f"{row:<{width}} {spread(fps):>20} {cells} {hours:>15.2f} {ratio:>12.2f}")
    finally:
        shutil.rmtree(root, ignore_errors=True)
    print(f"load average after: {load()}")


if __name__ == "__main__":
    main()
