"""Why does the Shapley arm stay on keep lane? Its critic's credit for the merge moves against
exact counterfactuals (issue 32).

Per-agent-critic MADDPG, paid each CAV's own reward, leaves keep lane by 200k frames on
``freeway-merge`` (w = 1); the Shapley actor-critic, paid the same rewards reallocated by the
Shapley value of its coalition critic, with the same exploration, shield, schedule and critic
size, stays on keep lane to 1M frames (``benchmarks/cooperation_control.py``). Its actor follows
the gradient of ``phi_i(s, a)`` with respect to its own action. This script asks whether that
signal says "move": at the states of the run's own greedy episodes (``--roads`` evaluation roads
of its seed), for every CAV on a mainline lane near the merge that keeps its lane where the
cooperative merge rule (``freeway_headroom.py``) would change lanes, the rule's move is replayed
for that one step on a copy of the road (the co-players and the later steps follow the greedy
policy; :meth:`BatchedFreeway.take` rolls all copies of a step in one batch), and compared with
the copy where it keeps its lane. Over the rest of the episode, discounted by the run's gamma:

- exact: ``own`` (the mover's return with the move minus without), ``system`` (the CAVs'
  returns summed), and the **credit reference** ``(own + system) / 2``: the change of the
  Shapley value of the member game (``v(C)`` = the members' return) when only the mover's action
  changes, since in a uniformly random ordering every other CAV precedes the mover with
  probability 1/2 and a coalition without the mover does not see its action;
- the critic: ``Delta v({i})``, ``Delta phi_i`` (``--permutations`` random orderings, the same
  for both actions, the others' actions the greedy ones) and ``Delta v(N)``, each in reward
  units (divided by the run's ``reward_scale``): what it believes of own, credit and system;
- the actor: its logit margin (move minus keep lane) and the softmax probability of the move
  under the grand coalition (the evaluation view).

Also the critic's calibration at these states: ``v(N)`` (the greedy joint action) against the
simulated discounted system return, ``v({i})`` against the CAV's own.

    OMP_NUM_THREADS=1 PYTHONPATH=.:benchmarks python benchmarks/shapley_credit_at_merge.py \\
        --runs OUT/runs/shapley_epsilon_shield_w1_seed0 --roads 32 --out OUT/credit

Prints a markdown table and writes it (and the per-decision numbers) under ``--out``.
"""

from __future__ import annotations

import argparse
import json
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
)
from tensordict import TensorDict
from yield_counterfactuals import branches, deciding

from mapets_rl.app.plugins import load_recipe
from mapets_rl.envs.freeway import CL, CR, KL
from mapets_rl.experiment import Experiment, atomic_write_text
from mapets_rl.machine import machine_line
from mapets_rl.modules import ACTION, OBS, Q_VALUE
from mapets_rl.recipes.maddpg import PREACTIVATION
from mapets_rl.recipes.shapley_ac import COALITION, ShapleyAC
from mapets_rl.shapley import prefixes_with_agents, sample_permutations
from mapets_rl.statistics import bootstrap_interval

LOGITS = ("agents", "logits")
ACTIONS = 4  # KL, CL, CR, ES


def variant_of(run_dir: Path) -> str:
    """The ``cooperation_control`` variant of a run directory named ``<variant>_seed<N>...``
    (a copy may add to the name)."""
    return run_dir.name.split("_seed", 1)[0]


def joint_actions(
    greedy: torch.Tensor, cav: torch.Tensor, move: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """One-hot joint actions ``[K, n, A]`` of ``K`` decisions: the greedy ones (``greedy
    [K, n]``), and the same with CAV ``cav[k]`` making ``move[k]`` instead."""
    keep = torch.nn.functional.one_hot(greedy, ACTIONS).float()
    moved = keep.clone()
    moved[torch.arange(cav.numel()), cav] = torch.nn.functional.one_hot(move, ACTIONS).float()
    return keep, moved


@torch.no_grad()
def critic_deltas(
    exp: ShapleyAC,
    observation: torch.Tensor,
    greedy: torch.Tensor,
    cav: torch.Tensor,
    move: torch.Tensor,
    permutations: int,
) -> dict[str, torch.Tensor]:
    """The critic's view of one-step moves: for ``K`` decisions (the state's observations
    ``[K, n, obs]``, greedy decisions ``[K, n]``, the mover ``[K]`` and its move ``[K]``),
    ``Delta v({i})``, ``Delta phi_i`` and ``Delta v(N)`` (move minus keep lane), ``v(N)`` and
    ``v({i})`` at the greedy joint action, each ``[K]`` in reward units."""
    critic, n = exp.critic, observation.shape[-2]
    scale = exp.config.reward_scale
    keep, moved = joint_actions(greedy, cav, move)
    # coalitions of the mover: a random prefix plus the mover, per decision [K, P, n]
    with_mover = prefixes_with_agents(sample_permutations(permutations, n, antithetic=True), cav)
    single = torch.nn.functional.one_hot(cav, n).bool().unsqueeze(-2)  # [K, 1, n]
    grand = torch.ones_like(single)
    masks = torch.cat([single, with_mover, grand], dim=-2)  # [K, 2 + P, n]
    obs = observation.float()
    values = {
        name: critic.coalition_values(obs, action, masks) / scale
        for name, action in (("keep", keep), ("move", moved))
    }
    delta = values["move"] - values["keep"]
    return {
        "critic_own": delta[:, 0],
        "critic_credit": delta[:, 1:-1].mean(-1),
        "critic_system": delta[:, -1],
        "critic_v_grand": values["keep"][:, -1],
        "critic_v_single": values["keep"][:, 0],
    }


@torch.no_grad()
def maddpg_view(
    exp: Experiment,
    observation: torch.Tensor,
    greedy: torch.Tensor,
    cav: torch.Tensor,
    move: torch.Tensor,
) -> dict[str, torch.Tensor]:
    """A MADDPG run's critic and actor at the same decisions: ``Delta Q_i`` (move minus keep
    lane, the others' actions the Shapley run's greedy ones), ``Q_i`` at the greedy joint
    action, the actor's logit margin and softmax probability of the move, each ``[K]``."""
    rows = torch.arange(cav.numel())
    keep, moved = joint_actions(greedy, cav, move)
    q = {}
    for name, action in (("keep", keep), ("move", moved)):
        td = TensorDict({OBS: observation.float(), ACTION: action}, batch_size=[cav.numel()])
        q[name] = exp.critic(td).get(Q_VALUE)[rows, cav, 0]
    td = TensorDict({OBS: observation.float()}, batch_size=[cav.numel()])
    logits = exp.eval_policy(td).get(PREACTIVATION)[rows, cav]
    return {
        "maddpg_own": q["move"] - q["keep"],
        "maddpg_q": q["keep"],
        "maddpg_logit_margin": logits[rows, move] - logits[rows, KL],
        "maddpg_move_prob": logits.softmax(-1)[rows, move],
    }


@torch.no_grad()
def decisions(run_dir: Path, args: argparse.Namespace) -> dict[str, list]:
    """Per decision (a mainline CAV near the merge keeping its lane where the rule moves):
    the exact and the critic's effects of the rule's move and the actor's preference (and,
    with ``--maddpg``, that run's critic and actor at the same decisions)."""
    exp = ShapleyAC.from_run_dir(run_dir)
    other = None
    if args.maddpg is not None:
        other = load_recipe("maddpg").from_run_dir(args.maddpg)
    variant, seed = variant_of(run_dir), int(exp.config.seed)
    gamma = float(exp.config.gamma)
    n_vehicles = int(exp.config.env_config["n_vehicles"])
    decide = deciding(exp.eval_policy)
    rule = deciding(cooperative_rule(n_vehicles))
    env = evaluation_env(args.roads, n_vehicles, {**env_settings(variant), "team_reward": False})
    env.set_seed(EVAL_SEED_OFFSET + seed)
    env.reset()
    sim = env.sim
    torch.manual_seed(args.seed)
    out: dict[str, list] = {}
    observation = sim.observe()
    for step in range(int(env.config["horizon"])):
        greedy = decide(observation)
        wanted = rule(observation)
        lane, x = cav_lanes(sim)
        alive = sim.state["agents"].get("alive")
        chosen = (
            alive
            & (greedy == KL)
            & ((wanted == CL) | (wanted == CR))
            & on_mainline(sim, lane)
            & near_merge(sim, x)
        )
        if bool(chosen.any()):
            road, cav = chosen.nonzero(as_tuple=True)  # [K]
            move = wanted[road, cav]
            returns, _, y, base, moving = branches(sim, greedy, road, cav, move, decide, gamma)
            own = returns[moving, cav] - returns[base, cav]
            system = returns[moving].sum(-1) - returns[base].sum(-1)
            rows = torch.arange(road.numel())
            td = TensorDict({OBS: observation[road].float()}, batch_size=[road.numel()])
            td.set(COALITION, torch.ones(road.numel(), observation.shape[1], dtype=torch.bool))
            logits = exp.actor(td).get(LOGITS)[rows, cav]  # [K, A]
            prob = logits.softmax(-1)
            fields = {
                "step": torch.full_like(road, step),
                "moved": (y[moving] != y[base]).any(-1),
                "own": own,
                "system": system,
                "reference_credit": (own + system) / 2,
                "sim_v_grand": returns[base].sum(-1),
                "sim_v_single": returns[base, cav],
                "logit_margin": logits[rows, move] - logits[rows, KL],
                "move_prob": prob[rows, move],
                **critic_deltas(exp, observation[road], greedy[road], cav, move, args.permutations),
            }
            if other is not None:
                fields.update(maddpg_view(other, observation[road], greedy[road], cav, move))
            for key, value in fields.items():
                out.setdefault(key, []).extend(value.tolist())
        observation = sim.step(greedy).observation
    env.close()
    exp.close()
    if other is not None:
        other.close()
    return out


def pearson(a: np.ndarray, b: np.ndarray) -> float:
    """Pearson's correlation (NaN when either side is constant)."""
    if a.size < 2 or a.std() == 0 or b.std() == 0:
        return float("nan")
    return float(np.corrcoef(a, b)[0, 1])


def mean_ci(values: np.ndarray) -> str:
    """``mean [bootstrap 95%]`` over decisions."""
    mean, low, high = bootstrap_interval(values)
    return f"{mean:+.1f} [{low:+.1f}, {high:+.1f}]"


def table(rows: dict[str, dict[str, np.ndarray]], roads: int) -> str:
    """The markdown tables of the runs' decisions (only those where the move moved the car)."""
    effects = [
        "| run | decisions per episode | exact own | exact system | credit reference "
        "(own + system) / 2 | critic Delta v({i}) | critic Delta phi_i | critic Delta v(N) "
        "| sign(Delta phi) = sign(reference) | corr(Delta phi, reference) "
        "| corr(Delta v({i}), own) | actor logit margin (move - keep) | actor p(move) |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    calibration = [
        "| run | sim. system return | critic v(N) | corr | sim. own return | critic v({i}) "
        "| corr |",
        "|---|---|---|---|---|---|---|",
    ]
    for name, d in rows.items():
        m = d.get("moved", np.zeros(0)).astype(bool)
        if not m.any():
            effects.append(f"| {name} | 0 | | | | | | | | | | | |")
            continue
        ref, phi = d["reference_credit"][m], d["critic_credit"][m]
        effects.append(
            f"| {name} | {m.sum() / roads:.1f} | {mean_ci(d['own'][m])} "
            f"| {mean_ci(d['system'][m])} "
            f"| {mean_ci(ref)} | {mean_ci(d['critic_own'][m])} | {mean_ci(phi)} "
            f"| {mean_ci(d['critic_system'][m])} | {(np.sign(phi) == np.sign(ref)).mean():.2f} "
            f"| {pearson(phi, ref):.2f} | {pearson(d['critic_own'][m], d['own'][m]):.2f} "
            f"| {d['logit_margin'][m].mean():+.2f} "
            f"| {d['move_prob'][m].mean():.3f} |"
        )
        calibration.append(
            f"| {name} | {d['sim_v_grand'][m].mean():.1f} | {d['critic_v_grand'][m].mean():.1f} "
            f"| {pearson(d['critic_v_grand'][m], d['sim_v_grand'][m]):.2f} "
            f"| {d['sim_v_single'][m].mean():.1f} | {d['critic_v_single'][m].mean():.1f} "
            f"| {pearson(d['critic_v_single'][m], d['sim_v_single'][m]):.2f} |"
        )
    text = "\n".join(effects) + "\n\n" + "\n".join(calibration)
    others = [
        "| at the decisions of | MADDPG critic Delta Q_i | sign = sign(exact own) "
        "| corr(Delta Q_i, exact own) | MADDPG Q_i | sim. own return | actor logit margin "
        "| actor p(move) |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for name, d in rows.items():
        if "maddpg_own" not in d or not d["moved"].astype(bool).any():
            continue
        m = d["moved"].astype(bool)
        dq, own = d["maddpg_own"][m], d["own"][m]
        others.append(
            f"| {name} | {mean_ci(dq)} | {(np.sign(dq) == np.sign(own)).mean():.2f} "
            f"| {pearson(dq, own):.2f} | {d['maddpg_q'][m].mean():.1f} "
            f"| {d['sim_v_single'][m].mean():.1f} | {d['maddpg_logit_margin'][m].mean():+.2f} "
            f"| {d['maddpg_move_prob'][m].mean():.3f} |"
        )
    return text + ("\n\n" + "\n".join(others) if len(others) > 2 else "")


def main(argv: list[str] | None = None) -> str:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--runs", nargs="+", required=True, type=Path)
    parser.add_argument("--roads", type=int, default=32)
    parser.add_argument("--permutations", type=int, default=64)
    parser.add_argument("--seed", type=int, default=0, help="seed of the orderings")
    parser.add_argument(
        "--maddpg",
        type=Path,
        help="a MADDPG run of cooperation_control.py whose critic and actor are read at the "
        "same decisions",
    )
    parser.add_argument("--out", required=True, type=Path)
    args = parser.parse_args(argv)
    if args.roads < 1:
        parser.error(f"--roads must be >= 1, got {args.roads}")
    if args.permutations < 2 or args.permutations % 2:
        parser.error(f"--permutations must be even and >= 2, got {args.permutations}")
    for run_dir in args.runs:
        if "_seed" not in run_dir.name or not run_dir.name.startswith("shapley"):
            parser.error(f"--runs: {run_dir} is not a Shapley run of cooperation_control.py")
        if not (run_dir / "config.yaml").is_file():
            parser.error(f"--runs: {run_dir} has no config.yaml")
    print(f"# {machine_line()}")
    rows = {}
    for run_dir in args.runs:
        tag = "" if args.maddpg is None else f"_vs_{args.maddpg.name}"
        path = args.out / f"{run_dir.name}_{args.roads}roads{tag}.json"
        if path.is_file():
            data = json.loads(path.read_text())
        else:
            data = decisions(run_dir, args)
            args.out.mkdir(parents=True, exist_ok=True)
            atomic_write_text(path, json.dumps(data))
        rows[run_dir.name] = {k: np.asarray(v) for k, v in data.items()}
    text = table(rows, args.roads)
    args.out.mkdir(parents=True, exist_ok=True)
    atomic_write_text(args.out / f"credit_{args.roads}roads.md", text + "\n")
    print(text)
    return text


if __name__ == "__main__":
    main()
