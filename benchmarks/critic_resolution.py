"""Can a Q critic resolve one CAV's move among 30 at all? Critics fitted offline to exact
returns, probed against exact counterfactuals (issue 50).

Every learned critic of the dilemma study priced a move alike whatever its exact worth
(``benchmarks/dilemma_counterfactuals.py --runs``: |r| <= 0.08). This study removes the online
learner: no bootstrapping, no moving policy, no target network. A fixed behaviour plays
``--episodes`` episodes on each of ``--roads`` training roads of a published dilemma config:
every CAV keeps its lane, except that with probability ``--epsilon`` it plays a uniform draw of
Keep Lane / Change Left / Change Right (the learners' exploration after annealing,
``fragments/epsilon-lane-moves``). Each CAV-step's discounted return to the end of its episode
(``--gamma``) is the regression target: the CAV's own return, or the CAVs' mean (the team
reward). The stored action is the one that ran (a move the shield replaced is Keep Lane), as the
learners store it, or with ``--store proposed`` the one proposed. Each
critic of ``--critics`` (the MADDPG critic: every agent's Q reads every observation and action,
one network per agent; ``own``: each Q reads its own observation and action, one shared
network; ``-wide``: 2 x 256 units instead of 2 x 64; ``advantage``: a value of every
observation plus an advantage head of the mover's own observation and action,
:mod:`mapets_rl.modules.advantage_critic`, one network per agent, ``-shared`` one for all,
``-own`` with the value of the own observation) is fitted to each target by minibatch
regression (Adam, ``--steps`` x ``--batch`` road-steps, inputs and targets standardised on the
data), scored on held-out roads (R^2 of the returns), then asked what each decision of
:func:`mapets_rl.envs.torch_freeway.counterfactuals.merge_decisions` is worth (the advantage
over Keep Lane, :func:`mapets_rl.modules.critic_probe.critic_advantages`) on ``--probe-roads``
evaluation roads of keep-lane co-players, beside the exact effect on what it was fitted to
(``own``, or ``system / I``), at the same gamma.

A critic that resolves moves here and not in training points at the online learner; one that
does not resolve them here either points at the data and the function class.

    OMP_NUM_THREADS=1 python benchmarks/critic_resolution.py --roads 256 --episodes 16 \\
        --probe-roads 64 --steps 4000
"""

from __future__ import annotations

import argparse
import time
from dataclasses import dataclass
from functools import partial

import numpy as np
import torch
from _common import add_published_config_args, published_config
from tensordict import TensorDict
from tensordict.nn import TensorDictModule, TensorDictSequential
from torchrl.objectives.value.functional import reward2go

from mapets_rl.envs.freeway import CL, CR, KL
from mapets_rl.envs.torch_freeway.counterfactuals import MERGE_DECISIONS, merge_decisions
from mapets_rl.experiment import RunConfig
from mapets_rl.experiment.protocol import ROAD_EVAL_SEED_OFFSET, evaluation_env
from mapets_rl.machine import machine_line
from mapets_rl.modules import AgentGroupSpec, make_obs_norm, make_q_critic
from mapets_rl.modules.advantage_critic import make_advantage_q_critic
from mapets_rl.modules.critic_probe import critic_advantages
from mapets_rl.modules.keys import ACTION, OBS, Q_VALUE

CRITICS = {  # name: (advantage head, centralized, share_params, num_cells)
    "maddpg": (False, True, False, [64, 64]),
    "maddpg-wide": (False, True, False, [256, 256]),
    "own": (False, False, True, [64, 64]),
    "own-wide": (False, False, True, [256, 256]),
    "advantage": (True, True, False, [64, 64]),
    "advantage-shared": (True, True, True, [64, 64]),
    "advantage-own": (True, False, True, [64, 64]),
}
TARGETS = ("own", "team")
N_ACTIONS = 4


@dataclass
class Behaviour:
    """What the behaviour played: ``observation [N, I, obs]``, ``action [N, I]`` (the action
    that ran), ``acting [N, I]`` (bool), and the discounted returns to the episode's end
    ``own [N, I]`` and ``team [N, I]`` (the CAVs' mean), one row per road-step."""

    observation: torch.Tensor
    action: torch.Tensor
    acting: torch.Tensor
    own: torch.Tensor
    team: torch.Tensor


def collect(
    config: RunConfig, roads: int, episodes: int, epsilon: float, gamma: float, seed: int,
    store: str = "executed",
) -> Behaviour:  # fmt: skip
    """``episodes`` episodes of keep lane with ``epsilon`` random lane moves on ``roads``
    training roads (seed ``seed``), every road run to the horizon; the stored action is the
    one that ran (``store="executed"``) or the one proposed (``"proposed"``)."""
    env = evaluation_env(config, roads)
    generator = torch.Generator().manual_seed(seed)
    moves = torch.tensor([KL, CL, CR])
    parts: dict[str, list[torch.Tensor]] = {k: [] for k in ("obs", "act", "acting", "r", "t")}
    try:
        env.set_seed(seed)
        sim = env.sim
        horizon = int(sim.config["horizon"])
        for _ in range(episodes):
            env.reset()
            observation = sim.observe()
            rows: dict[str, list[torch.Tensor]] = {k: [] for k in parts}
            for _ in range(horizon):
                shape = observation.shape[:2]
                explore = torch.rand(shape, generator=generator) < epsilon
                drawn = moves[torch.randint(len(moves), shape, generator=generator)]
                proposed = torch.where(explore, drawn, KL)
                result = sim.step(proposed)
                ran = proposed
                if store == "executed" and result.shielded is not None:
                    ran = torch.where(result.shielded, KL, proposed)
                paid = result.acting.to(result.reward.dtype)
                team = (result.reward * paid).sum(1, keepdim=True) / paid.sum(
                    1, keepdim=True
                ).clamp(min=1)
                rows["obs"].append(observation)
                rows["act"].append(ran)
                rows["acting"].append(result.acting)
                rows["r"].append(result.reward)
                rows["t"].append(torch.where(result.acting, team, 0.0))
                observation = result.observation
            for key, value in rows.items():
                parts[key].append(torch.stack(value, 1))  # [roads, T, ...]
    finally:
        env.close()
    stacked = {key: torch.cat(value) for key, value in parts.items()}  # [E * roads, T, ...]
    done = torch.zeros(stacked["r"].shape[:2], dtype=torch.bool)
    done[:, -1] = True

    def to_go(reward: torch.Tensor) -> torch.Tensor:  # [E * roads, T, I] -> same
        return reward2go(reward.double(), done.unsqueeze(-1).expand_as(reward), gamma,
                         time_dim=-2).float()  # fmt: skip

    def flat(x: torch.Tensor) -> torch.Tensor:
        return x.reshape(-1, *x.shape[2:])

    return Behaviour(
        flat(stacked["obs"]).float(),
        flat(stacked["act"]),
        flat(stacked["acting"]),
        flat(to_go(stacked["r"])),
        flat(to_go(stacked["t"])),
    )


class Standardised(torch.nn.Module):
    """``q * scale + shift``: a critic fitted to standardised returns, read in return units."""

    def __init__(self, shift: float, scale: float) -> None:
        super().__init__()
        self.shift, self.scale = shift, scale

    def forward(self, q: torch.Tensor) -> torch.Tensor:
        return q * self.scale + self.shift


def fit(
    name: str, spec: AgentGroupSpec, data: Behaviour, target: torch.Tensor, train: int,
    steps: int, batch: int, generator: torch.Generator,
) -> tuple[TensorDictSequential, float]:  # fmt: skip
    """Critic ``name`` fitted to ``target [N, I]`` on the first ``train`` rows; returns it (in
    return units) and its R^2 on the rest."""
    advantage, centralized, share, cells = CRITICS[name]
    norm, norm_module = make_obs_norm(spec)
    norm.update(data.observation[:train], data.acting[:train])
    if advantage:
        critic = make_advantage_q_critic(spec, cells, centralized=centralized, share_params=share,
                                         baseline_action=KL, obs_norm=norm_module)  # fmt: skip
    else:
        critic = make_q_critic(spec, cells, centralized=centralized, share_params=share,
                               obs_norm=norm_module)  # fmt: skip
    seen = target[:train][data.acting[:train]]
    shift, scale = float(seen.mean()), float(seen.std().clamp(min=1e-6))
    optimiser = torch.optim.Adam(critic.parameters(), lr=1e-3)

    def predict(rows: torch.Tensor) -> torch.Tensor:
        td = TensorDict(
            {OBS: data.observation[rows],
             ACTION: torch.nn.functional.one_hot(data.action[rows], N_ACTIONS).float()},
            batch_size=[len(rows)],
        )  # fmt: skip
        return critic(td).get(Q_VALUE)[..., 0]

    for _ in range(steps):
        rows = torch.randint(train, (batch,), generator=generator)
        mask = data.acting[rows]
        error = predict(rows) - (target[rows] - shift) / scale
        loss = error.pow(2)[mask].mean()
        optimiser.zero_grad()
        loss.backward()
        optimiser.step()
    with torch.no_grad():
        held = torch.arange(train, len(target))
        mask = data.acting[held]
        predicted = predict(held)[mask] * scale + shift
        actual = target[held][mask]
        r2 = 1.0 - float((predicted - actual).pow(2).mean() / actual.var())
    readout = TensorDictModule(Standardised(shift, scale), in_keys=[Q_VALUE], out_keys=[Q_VALUE])
    return TensorDictSequential(critic, readout), r2


def probe_rows(label: str, found: dict[str, np.ndarray], j: int, team_of: int | None) -> list[str]:
    """Rows per decision kind, then for the mainline kinds pooled (the decisions that ran): the
    exact effect on the critic's target and the critic's advantage (means), their correlation
    per decision."""
    rows = []
    ran = found["moved"].astype(bool)
    mainline = found["kind"] < MERGE_DECISIONS.index("forcing")
    kinds = [(name, found["kind"] == kind) for kind, name in enumerate(MERGE_DECISIONS)]
    for name, of_kind in [*kinds, ("every mainline move near the merge", mainline)]:
        chosen = ran & of_kind
        if chosen.sum() < 2:
            continue
        exact = found["own"][chosen] if team_of is None else found["system"][chosen] / team_of
        critic = found[f"probe{j}"][chosen]
        r = np.corrcoef(exact, critic)[0, 1]
        rows.append(f"| {label} | {name} | {chosen.sum()} | {exact.mean():+.3f} "
                    f"| {critic.mean():+.3f} | {r:+.2f} |")  # fmt: skip
    return rows


def main(argv: list[str] | None = None) -> str:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    add_published_config_args(parser, "freeway-merge-dilemma/maddpg-individual")
    parser.add_argument("--roads", type=int, default=256, help="training roads of the data")
    parser.add_argument("--episodes", type=int, default=16, help="episodes per training road")
    parser.add_argument("--epsilon", type=float, default=0.05, help="random lane-move rate")
    parser.add_argument("--gamma", type=float, default=0.99)
    parser.add_argument("--store", choices=["executed", "proposed"], default="executed",
                        help="the action stored where the shield replaced a move")  # fmt: skip
    parser.add_argument("--probe-roads", type=int, default=64)
    parser.add_argument("--steps", type=int, default=4000, help="regression steps per critic")
    parser.add_argument("--batch", type=int, default=256, help="road-steps per regression step")
    parser.add_argument("--critics", nargs="+", default=list(CRITICS), choices=list(CRITICS))
    parser.add_argument("--targets", nargs="+", default=list(TARGETS), choices=list(TARGETS))
    args = parser.parse_args(argv)
    if min(args.roads, args.episodes, args.probe_roads, args.steps, args.batch) < 1:
        parser.error("--roads, --episodes, --probe-roads, --steps and --batch must be >= 1")
    if not (0.0 <= args.epsilon <= 1.0 and 0.0 <= args.gamma <= 1.0):
        parser.error("--epsilon and --gamma must be in [0, 1]")
    if args.episodes < 2:
        parser.error("--episodes must be >= 2 (the last one is held out)")
    config = published_config(args)
    print(f"# {machine_line()}")
    print(f"# {args.config} {' '.join(args.set)}; behaviour: keep lane, epsilon {args.epsilon}; "
          f"stored: the {args.store} action")  # fmt: skip
    started = time.perf_counter()
    data = collect(config, args.roads, args.episodes, args.epsilon, args.gamma, config.seed,
                   args.store)  # fmt: skip
    train = len(data.action) * (args.episodes - 1) // args.episodes
    moves = (data.action != KL) & data.acting
    print(f"# {len(data.action)} road-steps ({train} for fitting), {int(moves.sum())} moves that "
          f"ran; collected in {time.perf_counter() - started:.0f} s")  # fmt: skip
    probe_env = evaluation_env(config, args.probe_roads)
    spec = AgentGroupSpec.from_env(probe_env)
    generator = torch.Generator().manual_seed(config.seed)
    fitted, labels, quality = [], [], []
    for name in args.critics:
        for target in args.targets:
            tic = time.perf_counter()
            critic, r2 = fit(name, spec, data, getattr(data, target), train, args.steps,
                             args.batch, generator)  # fmt: skip
            fitted.append(critic)
            labels.append((name, target))
            quality.append(f"| {name} | {target} | {r2:.3f} | {time.perf_counter() - tic:.0f} |")
    try:
        probe_env.set_seed(config.seed + ROAD_EVAL_SEED_OFFSET)
        probe_env.reset()
        probes = [partial(critic_advantages, critic, n_actions=N_ACTIONS) for critic in fitted]
        found = {key: value.numpy() for key, value in
                 merge_decisions(probe_env.sim, args.gamma, probes).items()}  # fmt: skip
        cavs = probe_env.sim.n_cavs
    finally:
        probe_env.close()
    rows = ["| critic | target | R^2, held-out returns | fit [s] |", "|---|---|---|---|", *quality,
            "", "| critic, target | decision (every co-player keeps its lane) | decisions "
            "| exact effect on the target | critic's advantage over Keep Lane | correlation |",
            "|---|---|---|---|---|---|"]  # fmt: skip
    for j, (name, target) in enumerate(labels):
        rows += probe_rows(f"{name}, {target}", found, j, cavs if target == "team" else None)
    table = "\n".join(rows)
    print(table)
    print(f"# {time.perf_counter() - started:.0f} s")
    return table


if __name__ == "__main__":
    main()
