"""Decision time per step of MA-PETS and the baselines' policies (the MA-PETS paper's Table IV).

A *decision* is one call of a recipe's evaluation policy (``Experiment.eval_policy``, the
policy ``mapets-rl evaluate`` runs) on the joint observation of all ``I`` CAVs: the MA-PETS
planner (CEM over the ensemble, all CAVs in one call) or a baseline's deterministic actor.
The environment step is not included. The states are those of a random-action rollout of the
scenario, visited in order (so the planner's warm start sees consecutive states); weights are
the freshly initialised ones (decision time does not depend on what was learnt, except that
MA-PETS's CEM may stop before ``Y`` iterations once its sampling spread is below
``planner.epsilon``; the untrained models here run all of them).

Reported per method: milliseconds per joint decision (median, 10-90 % range, mean +- std over
the timed decisions) and per agent-step (the joint decision / I), next to the paper's Table IV
(single-lane loop, 8 CAVs; the paper's unit is 1e-2 s and its hardware is not stated).

Methods: MA-PETS with the ``cpu`` and ``paper`` presets (figure-eight), MADDPG, MAPPO, SAC
(figure-eight, continuous target speed; ``--loop figure-eight-multilane`` for the paper's
multi-lane row), DQN (the figure-eight's greedy choice among its discrete actions, mapped to the
target speed), FIRL (one PPO policy per CAV, their parameters stacked), SVMIX (its
decentralised actor: the graph mixer is the critic's, not part of a decision), Shapley AC (freeway
with ``I`` CAVs among ``2 I`` vehicles: it needs discrete actions). ``--device cuda`` runs the
policies on a GPU (the env stays on the CPU; observations are moved, and the clock waits for the
GPU).

Examples::

    python benchmarks/decision_time.py                       # everything, 8 CAVs, 1 thread
    python benchmarks/decision_time.py --methods mapets-cpu maddpg --decisions 50
    python benchmarks/decision_time.py --loop figure-eight-multilane --agents 22 \\
        --methods mapets-cpu-before-24 mapets-cpu-eager mapets-cpu maddpg mappo sac
    python benchmarks/decision_time.py --device cuda --paper-decisions 10
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from collections.abc import Callable
from typing import Any

import torch
from tensordict import TensorDictBase
from torchrl.envs.utils import ExplorationType, set_exploration_type

from mapets_rl.machine import machine_line

PAPER_TABLE_IV_MS = {
    "figure-eight": {
        "mapets": (88.51, 3.105),
        "firl": (76.04, 3.034),
        "mappo": (80.07, 5.486),
        "svmix": (102.8, 2.668),
    },
    "figure-eight-multilane": {
        "mapets": (97.26, 2.615),
        "firl": (81.04, 4.519),
        "mappo": (87.79, 4.607),
        "svmix": (110.6, 3.025),
    },
}
"""The paper's Table IV, ms per step (mean, std; the paper's unit is 1e-2 s): single-lane loop
MA-PETS 8.851 ± 0.3105, FIRL 7.604 ± 0.3034, MAPPO 8.007 ± 0.5486, SVMIX 10.28 ± 0.2668;
multi-lane loop MA-PETS 9.726 ± 0.2615, FIRL 8.104 ± 0.4519, MAPPO 8.779 ± 0.4607, SVMIX
11.06 ± 0.3025. Every method of the table has its row here."""


def _mapets(preset: str, **planner: Any) -> Callable[[argparse.Namespace], Any]:
    def build(args: argparse.Namespace) -> Any:
        from mapets_rl.recipes.mapets import MAPETS, MAPETSConfig

        config = MAPETSConfig(
            preset=preset,
            planner=planner,
            env=args.loop,
            env_config={"n_cavs": args.agents},
            **_common(args),
        )
        return MAPETS(config, _run_dir())

    return build


def _model_free(name: str, env: str) -> Callable[[argparse.Namespace], Any]:
    def build(args: argparse.Namespace) -> Any:
        from mapets_rl.app.plugins import load_recipe

        recipe = load_recipe(name)
        if env == "loop":
            scenario, env_config = args.loop, {"n_cavs": args.agents}
        else:
            scenario, env_config = env, {"n_vehicles": 2 * args.agents, "cav_ratio": 0.5}
        config = recipe.Config(env=scenario, env_config=env_config, **_common(args))
        return recipe(config, _run_dir())

    return build


METHODS: dict[str, tuple[str, Callable[[argparse.Namespace], Any]]] = {
    "mapets-cpu": ("mapets", _mapets("cpu")),
    "mapets-cpu-eager": ("mapets", _mapets("cpu", compile=False)),
    "mapets-cpu-before-24": ("mapets", _mapets("cpu", population=32, compile=False)),
    "mapets-paper": ("mapets", _mapets("paper")),
    "mapets-cpu-graph": ("mapets", _mapets("cpu", cuda_graph=True)),
    "mapets-paper-graph": ("mapets", _mapets("paper", cuda_graph=True)),
    "maddpg": ("maddpg", _model_free("maddpg", "loop")),
    "mappo": ("mappo", _model_free("mappo", "loop")),
    "sac": ("sac", _model_free("sac", "loop")),
    "dqn": ("dqn", _model_free("dqn", "loop")),
    "firl": ("firl", _model_free("firl", "loop")),
    "svmix": ("svmix", _model_free("svmix", "loop")),
    "shapley_ac": ("shapley_ac", _model_free("shapley_ac", "freeway")),
}
"""Method name -> (paper key, builder of the recipe's Experiment). The ``-graph`` methods plan
with ``planner.cuda_graph`` (CUDA devices only; the first, untimed warm-up decision captures),
``mapets-cpu`` compiles its rollout step (``planner.compile``, the first, untimed warm-up decision
compiles), ``mapets-cpu-eager`` does not, ``mapets-cpu-before-24`` is the cpu preset before issue
24 (Q = 32, eager)."""

_TMP: list[tempfile.TemporaryDirectory] = []


def _run_dir() -> str:
    tmp = tempfile.TemporaryDirectory(prefix="decision_time_")
    _TMP.append(tmp)
    return tmp.name


def _common(args: argparse.Namespace) -> dict[str, Any]:
    return {"device": args.device, "logger": "none", "progress": False, "seed": 0}


def _sync(device: str) -> None:
    if device.startswith("cuda"):
        torch.cuda.synchronize()


def states(exp: Any, count: int) -> list[TensorDictBase]:
    """``count`` consecutive states of a random-action rollout of ``exp``'s env (restarted
    when an episode ends), without their ``next`` entries."""
    out: list[TensorDictBase] = []
    while len(out) < count:
        rollout = exp.env.rollout(count - len(out), break_when_any_done=True)
        out += [rollout[t].exclude("next") for t in range(rollout.shape[0])]
    return out


def time_decisions(
    policy: Callable[[TensorDictBase], TensorDictBase],
    pool: list[TensorDictBase],
    decisions: int,
    warmup: int,
    device: str,
    n_agents: int,
) -> list[float]:
    """Seconds of each of ``decisions`` timed calls of ``policy`` (after ``warmup`` untimed
    ones), cycling through ``pool``; each call must return actions ``[I, ...]``."""
    reset = getattr(policy, "reset", None)
    if callable(reset):
        reset()
    times = []
    with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
        for k in range(warmup + decisions):
            td = pool[k % len(pool)].clone().to(device)
            _sync(device)
            start = time.perf_counter()
            td = policy(td)
            _sync(device)
            elapsed = time.perf_counter() - start
            action = td.get(("agents", "action"))
            if action.shape[0] != n_agents:
                raise RuntimeError(f"expected actions for {n_agents} CAVs, got {action.shape}")
            if k >= warmup:
                times.append(elapsed)
    return times


def _ms(value: float) -> str:
    """Milliseconds for the table: 3 significant digits, thousands in full (``73,012``)."""
    return f"{value:,.0f}" if value >= 1000 else f"{value:.3g}"


def _quantile(values: list[float], q: float) -> float:
    ordered = sorted(values)
    pos = q * (len(ordered) - 1)
    lo = int(pos)
    hi = min(lo + 1, len(ordered) - 1)
    return ordered[lo] + (ordered[hi] - ordered[lo]) * (pos - lo)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "--methods",
        nargs="+",
        default=None,
        choices=list(METHODS),
        help="default: all (the -graph ones with a CUDA --device only)",
    )
    parser.add_argument(
        "--loop",
        default="figure-eight",
        choices=["figure-eight", "figure-eight-multilane"],
        help="scenario of MA-PETS, MADDPG, MAPPO, SAC, DQN, FIRL, SVMIX (the paper's single- "
        "or multi-lane loop)",
    )
    parser.add_argument("--agents", type=int, default=8, help="CAVs I (paper: 8; multi-lane 22)")
    parser.add_argument("--decisions", type=int, default=30, help="timed decisions per method")
    parser.add_argument("--warmup", type=int, default=3, help="untimed decisions first")
    parser.add_argument(
        "--paper-decisions",
        type=int,
        default=1,
        help="timed decisions of mapets-paper (about 2.5 min each with 8 CAVs on 1 CPU thread)",
    )
    parser.add_argument("--paper-warmup", type=int, default=0, help="untimed mapets-paper ones")
    parser.add_argument("--threads", type=int, default=1, help="torch intra-op threads")
    parser.add_argument("--device", default="cpu", help="cpu or cuda[:N] (policies only)")
    args = parser.parse_args()
    for name, value in (("--agents", args.agents), ("--decisions", args.decisions)):
        if value < 1:
            parser.error(f"{name} must be >= 1, got {value}")
    for name, value in (("--warmup", args.warmup), ("--paper-warmup", args.paper_warmup)):
        if value < 0:
            parser.error(f"{name} must be >= 0, got {value}")
    if args.paper_decisions < 1:
        parser.error(f"--paper-decisions must be >= 1, got {args.paper_decisions}")
    if args.device.startswith("cuda") and not torch.cuda.is_available():
        parser.error(f"--device {args.device}: no CUDA device on this machine")
    cuda = args.device.startswith("cuda")
    if args.methods is None:
        args.methods = [m for m in METHODS if cuda or not m.endswith("-graph")]
    graphed = [m for m in args.methods if m.endswith("-graph")]
    if graphed and not cuda:
        parser.error(f"--methods {' '.join(graphed)}: CUDA graphs need a CUDA --device")
    torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    device_name = (
        torch.cuda.get_device_name(torch.device(args.device))
        if args.device.startswith("cuda")
        else "cpu"
    )
    print(f"# {machine_line()}; device {args.device} ({device_name}), I = {args.agents}")
    rows = []
    for name in args.methods:
        paper_key, build = METHODS[name]
        exp = build(args)
        paper = name.startswith("mapets-paper")
        decisions = args.paper_decisions if paper else args.decisions
        warmup = args.paper_warmup if paper else args.warmup
        planner = getattr(exp, "planner", None)  # MA-PETS's
        if planner is not None and (planner.cuda_graph or planner.compiled_step is not None):
            warmup = max(warmup, 1)  # the capture / compilation is not a decision's time
        pool = states(exp, max(min(decisions + warmup, 50), 1))
        times = time_decisions(exp.eval_policy, pool, decisions, warmup, args.device, args.agents)
        ms = [1e3 * t for t in times]
        median = statistics.median(ms)
        std = statistics.stdev(ms) if len(ms) > 1 else 0.0
        paper_ms = PAPER_TABLE_IV_MS.get(exp.config.env, {}).get(paper_key)
        paper_cell = f"{paper_ms[0]:.2f} ± {paper_ms[1]:.2f}" if paper_ms else "—"
        row = (
            f"| {name} | {exp.config.env} | {len(ms)} | {_ms(median)} "
            f"[{_ms(_quantile(ms, 0.1))}-{_ms(_quantile(ms, 0.9))}] | "
            f"{_ms(statistics.fmean(ms))} ± {std:.2g} | {_ms(median / args.agents)} | "
            f"{paper_cell} |"
        )
        rows.append(row)
        print(row, flush=True)
        step = None if planner is None else planner.compiled_step
        if step is not None:
            how = f"eager fallback: {step.fallback_reason}" if step.fallback_reason else "compiled"
            print(f"  ({name}: {how}; compile {step.compile_seconds:.1f} s in the warm-up)")
        exp.env.close()
    print()
    print(
        "| method | scenario | decisions | ms per joint decision, median [p10-p90] | "
        "mean ± std | ms per agent-step (median / I) | paper Table IV, ms per step |"
    )
    print("|---|---|---|---|---|---|---|")
    print("\n".join(rows))


if __name__ == "__main__":
    from mapets_rl import quiet_dependencies

    quiet_dependencies()
    main()
