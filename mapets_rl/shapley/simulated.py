"""The coalition game of a traffic state computed by simulation (issue 32).

For a state of the batched freeway and a policy for the CAVs (a learned actor or a scripted
rule), the characteristic function is ``v(C)`` = the system return over the rest of the episode
when the CAVs in ``C`` follow the policy and the others keep their lane. Every coalition plays on
its own copy of the road (:meth:`BatchedFreeway.branch`: all ``2**n`` copies are the roads of
one batched simulator), so ``v`` is exact for the simulator, with no critic involved: the
reference against which a coalition critic's Shapley value can be checked, and the measure of
where the game is additive (each CAV's Shapley value its own marginal gain, the paper's
Proposition 2) and where coordinated moves make it not.
"""

from __future__ import annotations

from collections.abc import Callable

import torch

from mapets_rl.envs.freeway import KL
from mapets_rl.envs.torch_freeway.simulator import BatchedFreeway
from mapets_rl.shapley.game import coalition_masks

__all__ = ["simulated_game"]


def simulated_game(
    sim: BatchedFreeway,
    road: int,
    member_policy: Callable[[torch.Tensor], torch.Tensor],
    agents: torch.Tensor | None = None,
) -> torch.Tensor:
    """``v(C)`` for every coalition ``C`` of the CAVs ``agents`` of road ``road`` of ``sim``.

    Args:
        sim: the batched freeway, at the state to value (its other roads are untouched).
        road: which road's state.
        member_policy: observations ``[K, I, obs_dim]`` -> actions ``[K, I]`` (KL, CL, CR, ES)
            played by the coalition's members.
        agents: ``[n]`` indices of the CAVs that form coalitions (default: all ``I``; the
            others keep their lane in every copy). ``2**n`` copies of the road are simulated.

    Returns:
        ``values [2**n]``, ``values[k] = v(C_k)`` with ``C_k`` the CAVs ``agents[i]`` for the set
        bits ``i`` of ``k`` (the layout of :func:`~mapets_rl.shapley.game.exact_shapley`).
    """
    n_cavs = sim.n_cavs
    agents = torch.arange(n_cavs) if agents is None else torch.as_tensor(agents).long()
    if agents.ndim != 1 or agents.numel() < 1 or len(set(agents.tolist())) != agents.numel():
        raise ValueError(f"agents must be distinct CAV indices, got {agents.tolist()}")
    if int(agents.min()) < 0 or int(agents.max()) >= n_cavs:
        raise ValueError(f"agents must lie in [0, {n_cavs - 1}], got {agents.tolist()}")
    masks = coalition_masks(agents.numel(), device=sim.device)  # [K, n]
    members = torch.zeros(masks.shape[0], n_cavs, dtype=torch.bool, device=sim.device)
    members[:, agents.to(sim.device)] = masks
    copies = sim.branch(road, masks.shape[0])

    def decide(observation: torch.Tensor) -> torch.Tensor:
        return torch.where(members, member_policy(observation).to(sim.device), KL)

    return copies.rollout_returns(decide)
