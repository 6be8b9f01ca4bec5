"""Exact counterfactuals on the batched freeway: a road branched at a decision, the decision
replaced, every copy played to the end of its episode, each CAV's return measured.

Stepping is deterministic (:meth:`BatchedFreeway.take` copies a road's whole state), so the
difference between a branch and the policy's own continuation of its road is the exact effect
of the replaced decision, on the CAV that made it (``own``) and on the system (the CAVs'
returns summed). All of a step's copies are rolled out as one batch.

:func:`lane_change_effects` asks it of every lane change of a policy on a mainline lane: is the
move that lets the ramp traffic in also the move that pays the CAV that makes it?
(``docs/results/shapley.md``, "Are the learned lane changes near the merge selfish?").
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModuleBase

from mapets_rl.envs.freeway import CL, CR, KL
from mapets_rl.envs.freeway_merge import NEAR_MERGE
from mapets_rl.envs.references import ACTION, OBSERVATION, CooperativeMerge
from mapets_rl.envs.torch_freeway.simulator import BatchedFreeway

Decide = Callable[[torch.Tensor], torch.Tensor]
"""``observation [K, I, obs_dim] -> decisions [K, I]`` (0..3: KL, CL, CR, ES)."""

Probe = Callable[
    [torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor], torch.Tensor
]
"""``(observation [R, I, obs], action [R, I], road [K], cav [K], replacement [K]) -> [K]``:
what some model says decision ``k`` is worth (a critic's advantage,
:func:`mapets_rl.modules.critic_probe.critic_advantages`)."""

MERGE_DECISIONS = ("rule's yields", "other Change Left", "Change Right", "forcing")
"""The kinds of decision :func:`merge_decisions` asks about, in the order of its ``kind``."""


def deciding(policy: TensorDictModuleBase) -> Decide:
    """The decisions of a TensorDict policy that writes one-hot ``("agents", "action")`` from
    ``("agents", "observation")`` (a trained ``eval_policy``, a reference policy)."""

    def decide(observation: torch.Tensor) -> torch.Tensor:
        td = TensorDict({OBSERVATION: observation.float()}, batch_size=observation.shape[:1])
        return policy(td).get(ACTION).argmax(-1)

    return decide


def keep_lane(observation: torch.Tensor) -> torch.Tensor:
    """Keep Lane for every CAV: ``[K, I, obs_dim] -> [K, I]``."""
    return torch.full(observation.shape[:2], KL, dtype=torch.long)


def cav_lanes(sim: BatchedFreeway) -> tuple[torch.Tensor, torch.Tensor]:
    """The lane ids and x [m] of the CAVs, ``[roads, CAVs]`` each."""
    slot = sim.state["agents"].get("slot")
    bodies = sim.state["bodies"]
    return bodies.get("lane").gather(1, slot), bodies.get("x").gather(1, slot)


def on_mainline(sim: BatchedFreeway, lane: torch.Tensor) -> torch.Tensor:
    """bool, shaped like ``lane`` (lane ids): the lane is a mainline lane, not the ramp's."""
    return sim.geometry.table[lane] != sim.geometry.ramp_table


def near_merge(sim: BatchedFreeway, x: torch.Tensor) -> torch.Tensor:
    """bool, shaped like ``x`` [m]: from ``NEAR_MERGE`` metres before the acceleration lane to
    its end (where the behaviour counts of ``freeway-merge`` place a change near the merge)."""
    geometry = sim.geometry
    return (x >= geometry.merge_start - NEAR_MERGE) & (x <= geometry.merge_end)


def returns_per_cav(
    copies: BatchedFreeway,
    first: torch.Tensor,
    decide: Decide,
    gamma: float,
    keeping: torch.Tensor | None = None,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Every road of ``copies`` plays ``first [K, I]`` now and ``decide`` after (the CAVs of
    ``keeping [K, I]`` (bool) Keep Lane instead), to the end of its episode. Returns each CAV's
    return from now on ``[K, I]`` and the metres it drives (float64, the step ``k`` steps from
    now weighted by ``gamma ** k``), and the bodies' lateral positions after the first step
    ``[K, N]``."""
    if not 0.0 <= gamma <= 1.0:
        raise ValueError(f"gamma must be in [0, 1], got {gamma}")
    policy = decide
    if keeping is not None:

        def policy(observation: torch.Tensor) -> torch.Tensor:
            return torch.where(keeping, KL, decide(observation))

    result = copies.step(first)
    y = copies.state["bodies"].get("y").clone()
    total = result.reward.double().clone()
    metres = result.distance.double().clone()
    running = ~(result.truncated | result.terminated)
    discount = 1.0
    while bool(running.any()):
        result = copies.step(policy(result.observation))
        discount *= gamma
        on = running.unsqueeze(-1)
        total += torch.where(on, discount * result.reward.double(), 0.0)
        metres += torch.where(on, discount * result.distance.double(), 0.0)
        running &= ~(result.truncated | result.terminated)
    return total, metres, y


def branches(
    sim: BatchedFreeway,
    action: torch.Tensor,
    road: torch.Tensor,
    cav: torch.Tensor,
    replacement: torch.Tensor,
    decide: Decide,
    gamma: float,
    *,
    keep_lane_after: bool = False,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Decision ``k`` (CAV ``cav[k]`` of road ``road[k]``, ``[K]`` each) replayed on its own
    copy of the road with that CAV's action this step replaced by ``replacement[k]``, beside one
    copy per road that plays ``action [B, I]`` unchanged; all copies then follow ``decide``
    (with ``keep_lane_after``, the replaced CAVs keep their lane instead, to the end), in one
    batch (:func:`returns_per_cav`). ``sim`` is left as it was. Returns the copies'
    ``returns``, ``metres`` and ``y`` rows and, ``[K]`` each, the row of every decision's
    unchanged copy and of its own copy."""
    bases = road.unique()  # sorted: the policy's own continuation of each road
    copies = sim.take(torch.cat([bases, road]))
    first = action[torch.cat([bases, road])].clone()
    branch = torch.arange(bases.numel(), bases.numel() + road.numel())
    first[branch, cav] = replacement
    keeping = None
    if keep_lane_after:
        keeping = torch.zeros_like(first, dtype=torch.bool)
        keeping[branch, cav] = True
    returns, metres, y = returns_per_cav(copies, first, decide, gamma, keeping)
    return returns, metres, y, torch.searchsorted(bases, road), branch


@torch.no_grad()
def lane_change_effects(
    sim: BatchedFreeway, decide: Decide, *, gamma: float = 0.95, rest: bool = True
) -> dict[str, list]:
    """Play ``decide`` on every road of ``sim`` (just reset) to the horizon; at every step, each
    lane-change decision (CL or CR, not overruled by the shield) of a CAV on a mainline lane is
    replayed on a copy of its road where that CAV keeps its lane instead, for the ``rest`` of
    the episode (else for this step only), everything else the same (:func:`branches`).

    Returns lists with one entry per decision: ``step``; ``near`` (made near the merge);
    ``moved`` (the move changed some vehicle's lateral position: a Change Left in the leftmost
    lane does not); ``own`` and ``own_metres``, what the change earns the CAV that makes it (its
    return with the change minus its return with Keep Lane, discounted by ``gamma``) and the
    metres driven in it; ``system``, what it earns the CAVs together."""
    out: dict[str, list] = {key: [] for key in ("step", "near", "moved", "own", "own_metres")}
    out["system"] = []
    observation = sim.observe()
    for step in range(int(sim.config["horizon"])):
        action = decide(observation)
        safe = sim.shield(action)[0] if sim.config["shield"] else action
        lane, x = cav_lanes(sim)
        alive = sim.state["agents"].get("alive")
        chosen = alive & ((safe == CL) | (safe == CR)) & on_mainline(sim, lane)
        if bool(chosen.any()):
            road, cav = chosen.nonzero(as_tuple=True)  # [K]
            returns, metres, y, base, kept = branches(
                sim, action, road, cav, torch.full_like(cav, KL), decide, gamma,
                keep_lane_after=rest,
            )  # fmt: skip
            out["moved"] += (y[base] != y[kept]).any(-1).tolist()
            out["step"] += [step] * road.numel()
            out["near"] += near_merge(sim, x)[road, cav].tolist()
            out["own"] += (returns[base, cav] - returns[kept, cav]).tolist()
            out["own_metres"] += (metres[base, cav] - metres[kept, cav]).tolist()
            out["system"] += (returns[base].sum(-1) - returns[kept].sum(-1)).tolist()
        observation = sim.step(action).observation
    return out


@torch.no_grad()
def merge_decisions(
    sim: BatchedFreeway, gamma: float, probes: Sequence[Probe] = ()
) -> dict[str, torch.Tensor]:
    """Every alternative decision of every CAV on every road of ``sim`` (a merge road, just
    reset) as every CAV keeps its lane to the horizon. At every step each alternative is
    replayed on a copy of its road where that CAV alone plays it for the step, then keeps its
    lane again, everything else the same (:func:`branches`). The kinds
    (:data:`MERGE_DECISIONS`): the Change Left that the cooperative merge rule would play (a
    CAV in the rightmost lane before the merge point, a ramp vehicle beside it, room on the
    left); every other Change Left and every Change Right of a CAV on a mainline lane near the
    merge (:func:`near_merge`), where the lane exists; a ramp CAV's Change Left on the
    acceleration lane (forcing).

    Returns one entry per decision ``[D]``: ``kind`` (index into :data:`MERGE_DECISIONS`),
    ``road``; ``moved`` (bool: some vehicle's lateral position differs after the step; a move
    the shield refuses runs as Keep Lane); ``own``, the mover's return with the move minus
    without it, and ``system``, the CAVs' summed returns with minus without (discounted by
    ``gamma``, float64); ``probe{j}``, what ``probes[j]`` says of the decision."""
    if not sim.merge:
        raise ValueError("merge_decisions needs a freeway-merge road (sim.merge is False)")
    lanes = int(sim.config["lanes"])
    rule = deciding(CooperativeMerge(lanes))
    keys = ("kind", "road", "moved", "own", "system", *(f"probe{j}" for j in range(len(probes))))
    out: dict[str, list[torch.Tensor]] = {key: [] for key in keys}
    observation = sim.observe()
    for _ in range(int(sim.config["horizon"])):
        action = keep_lane(observation)
        lane, x = cav_lanes(sim)
        number = sim.geometry.number[lane]
        alive = sim.state["agents"].get("alive")
        driving = alive & on_mainline(sim, lane) & near_merge(sim, x)
        yields = driving & (rule(observation) == CL)
        chosen = (
            (yields, CL),
            (driving & ~yields & (number >= 1), CL),
            (driving & (number <= lanes - 2), CR),
            (alive & (lane == lanes), CL),
        )
        found = [(kind, *mask.nonzero(as_tuple=True), move)
                 for kind, (mask, move) in enumerate(chosen)]  # fmt: skip
        road = torch.cat([r for _, r, _, _ in found])
        if road.numel():
            cav = torch.cat([c for _, _, c, _ in found])
            replacement = torch.cat([torch.full_like(c, move) for _, _, c, move in found])
            returns, _, y, base, branch = branches(
                sim, action, road, cav, replacement, keep_lane, gamma
            )
            out["kind"].append(torch.cat([torch.full_like(c, kind) for kind, _, c, _ in found]))
            out["road"].append(road)
            out["moved"].append((y[base] != y[branch]).any(-1))
            out["own"].append(returns[branch, cav] - returns[base, cav])
            out["system"].append(returns[branch].sum(-1) - returns[base].sum(-1))
            for j, probe in enumerate(probes):
                out[f"probe{j}"].append(probe(observation, action, road, cav, replacement))
        observation = sim.step(action).observation
    empty = {"kind": torch.long, "road": torch.long, "moved": torch.bool}
    return {
        key: torch.cat(value) if value else torch.zeros(0, dtype=empty.get(key, torch.float64))
        for key, value in out.items()
    }
