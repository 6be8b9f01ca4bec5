"""Coalition games of a traffic state computed by simulation (issue 32).

Two characteristic functions of a state of the batched freeway, both exact for the simulator
(no critic involved; every coalition plays on its own copy of the road,
:meth:`BatchedFreeway.branch`: all ``2**n`` copies are the roads of one batched simulator):

- :func:`simulated_game`, the *credit* game: ``v(C)`` = the system return over the rest of the
  episode when the CAVs in ``C`` follow a policy (a learned actor or a scripted rule) and the
  others keep their lane. Its Shapley value is what each CAV's way of driving causes; it shows
  where the game is additive (each CAV's Shapley value its own marginal gain, the paper's
  Proposition 2) and where coordinated moves make it not.
- :func:`simulated_member_game`, the game a coalition critic ``v(s, a, C)`` learns (Shapley AC,
  Algorithm 1): after the joint action ``a``, every CAV plays the policy on its coalition view
  (members see each other) and ``v(C)`` is the members' discounted return. Comparing a critic
  with it separates fitting error from what the critic's game means.

Policies are ``policy(observation [K, I, obs_dim], members [K, I] bool) -> actions [K, I]``
(KL, CL, CR, ES): ``members`` is copy ``k``'s coalition, for policies that read it (a coalition
actor's view ``s^C``); scripted rules may ignore it.
"""

from __future__ import annotations

from collections.abc import Callable

import torch

from mapets_rl.envs.freeway import KL
from mapets_rl.envs.torch_freeway.simulator import BatchedFreeway
from mapets_rl.shapley.game import coalition_masks

__all__ = ["simulated_game", "simulated_member_game"]

CoalitionPolicy = Callable[[torch.Tensor, torch.Tensor], torch.Tensor]


def _coalition_copies(
    sim: BatchedFreeway, road: int, agents: torch.Tensor | None
) -> tuple[BatchedFreeway, torch.Tensor]:
    """``2**n`` copies of road ``road`` and each copy's members ``[2**n, I]`` (bool)."""
    n_cavs = sim.n_cavs
    agents = torch.arange(n_cavs) if agents is None else torch.as_tensor(agents).long()
    if agents.ndim != 1 or agents.numel() < 1 or len(set(agents.tolist())) != agents.numel():
        raise ValueError(f"agents must be distinct CAV indices, got {agents.tolist()}")
    if int(agents.min()) < 0 or int(agents.max()) >= n_cavs:
        raise ValueError(f"agents must lie in [0, {n_cavs - 1}], got {agents.tolist()}")
    masks = coalition_masks(agents.numel(), device=sim.device)  # [K, n]
    members = torch.zeros(masks.shape[0], n_cavs, dtype=torch.bool, device=sim.device)
    members[:, agents.to(sim.device)] = masks
    return sim.branch(road, masks.shape[0]), members


def simulated_game(
    sim: BatchedFreeway,
    road: int,
    member_policy: CoalitionPolicy,
    agents: torch.Tensor | None = None,
    *,
    gamma: float = 1.0,
) -> torch.Tensor:
    """The credit game: ``v(C)`` for every coalition ``C`` of the CAVs ``agents`` of road
    ``road`` of ``sim`` = the system return from now on (discounted by ``gamma``; default 1:
    the rest of the episode's return) when ``C`` plays ``member_policy`` and every other CAV
    keeps its lane.

    Args:
        sim: the batched freeway, at the state to value (its other roads are untouched).
        road: which road's state.
        member_policy: see the module docstring; only the members' actions are used.
        agents: ``[n]`` indices of the CAVs that form coalitions (default: all ``I``; the
            others keep their lane in every copy). ``2**n`` copies of the road are simulated.
        gamma: discount in ``[0, 1]``.

    Returns:
        ``values [2**n]``, ``values[k] = v(C_k)`` with ``C_k`` the CAVs ``agents[i]`` for the set
        bits ``i`` of ``k`` (the layout of :func:`~mapets_rl.shapley.game.exact_shapley`).
    """
    copies, members = _coalition_copies(sim, road, agents)

    def decide(observation: torch.Tensor) -> torch.Tensor:
        return torch.where(members, member_policy(observation, members).to(sim.device), KL)

    return copies.rollout_returns(decide, gamma=gamma)


def simulated_member_game(
    sim: BatchedFreeway,
    road: int,
    policy: CoalitionPolicy,
    first_action: torch.Tensor,
    agents: torch.Tensor | None = None,
    *,
    gamma: float,
) -> torch.Tensor:
    """The game a coalition critic learns: ``v(C)`` = the discounted return (``gamma``) of the
    members of ``C`` from now on, when every CAV first plays ``first_action [I]`` (the critic's
    ``a``) and then ``policy`` with copy ``k``'s coalition. ``v(empty) = 0``.

    Args, returns: as :func:`simulated_game` (the CAVs outside ``agents`` are never members but
    play ``policy`` too).
    """
    copies, members = _coalition_copies(sim, road, agents)
    first = torch.as_tensor(first_action, device=sim.device).long()
    if tuple(first.shape) != (sim.n_cavs,):
        raise ValueError(f"first_action must have shape [{sim.n_cavs}], got {tuple(first.shape)}")
    now = copies.step(first.expand_as(members)).reward.double()
    first_reward = (now * members.double()).sum(1)
    later = copies.rollout_returns(
        lambda observation: policy(observation, members).to(sim.device),
        gamma=gamma,
        payoff=members,
    )
    return first_reward + gamma * later
