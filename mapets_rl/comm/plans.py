"""Plan sharing over the communication graph: what a CAV's planner knows of its neighbours'
future speeds (MA-PETS ``comm.share_plans``).

Every step each CAV broadcasts the speeds its chosen plan predicts for itself over the horizon;
the CAVs linked to it (within ``d``, the link not failed: the
:class:`~mapets_rl.comm.CommunicationRange` graph of the step) receive them. At the next step a
receiver whose observed leader, follower, conflicting vehicle or other-lane neighbour is that
CAV uses the broadcast, shifted by the one step that has passed, as that neighbour's speed in
its own predicted states, instead of the model's guess. Humans, CAVs out of range and failed
links leave the prediction as it was.
"""

from __future__ import annotations

import torch

__all__ = ["linked_senders", "plan_schedule"]


def linked_senders(
    neighbour_cav: torch.Tensor, links: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """Which CAV each observed vehicle slot holds, and whether the receiver hears it.

    Args:
        neighbour_cav: ``[*, I, K]`` the agent index of the CAV in each slot (``-1``: a human
            driver or nobody; floats are rounded).
        links: ``[*, I, I]`` bool, who hears whom this step.

    Returns:
        ``(index [*, I, K], heard [*, I, K])``: the slot's agent index (0 where there is no
        CAV) and whether it is a CAV linked to the receiver.
    """
    sender = neighbour_cav.round().long()
    index = sender.clamp_min(0)
    return index, torch.gather(links, -1, index) & (sender >= 0)


def plan_schedule(
    plans: torch.Tensor,
    neighbour_cav: torch.Tensor,
    links: torch.Tensor,
    columns: tuple[int, ...],
    obs_dim: int,
) -> tuple[torch.Tensor, torch.Tensor]:
    """The planner's schedule of known neighbour speeds from last step's broadcast plans.

    Args:
        plans: ``[*, I, H]`` each CAV's broadcast of the previous step: index ``k`` is its own
            predicted speed ``k + 1`` steps after that decision, i.e. ``k`` steps after now
            (NaN: no plan, e.g. at the episode's start or after a crash).
        neighbour_cav: ``[*, I, K]`` the agent index of the CAV in each observed vehicle slot
            (``-1``: a human driver or nobody; floats are rounded).
        links: ``[*, I, I]`` bool, who hears whom this step (symmetric, no self-links).
        columns: the ``K`` observation columns that hold the slots' speeds.
        obs_dim: ``S``.

    Returns:
        ``schedule [*, I, H, S]``: ``schedule[..., i, t, columns[k]]`` is the speed that the
        CAV in slot ``k`` of CAV ``i`` planned for the state after step ``t`` of ``i``'s
        rollout (now + ``t + 1``; the last planned speed held beyond its horizon) where that
        CAV is linked to ``i`` and has a plan, NaN elsewhere; and ``used [*, I, K]`` bool,
        the slots so filled.
    """
    horizon = plans.shape[-1]
    if neighbour_cav.shape[-1] != len(columns):
        raise ValueError(
            f"neighbour_cav has {neighbour_cav.shape[-1]} slots but {len(columns)} columns "
            f"were given ({columns})"
        )
    index, heard = linked_senders(neighbour_cav, links)  # [*, I, K]
    # the broadcast of step k + 1 onwards: the receiver's step t reads the sender's k = t + 1
    later = torch.cat([plans[..., 1:], plans[..., -1:]], dim=-1)  # [*, I, H]
    speeds = torch.gather(
        later.unsqueeze(-3).expand(*later.shape[:-2], index.shape[-2], *later.shape[-2:]),
        -2,
        index.unsqueeze(-1).expand(*index.shape, horizon),
    )  # [*, I (receiver), K, H]
    used = heard & ~torch.isnan(speeds).any(-1)
    speeds = torch.where(used.unsqueeze(-1), speeds, float("nan"))
    schedule = torch.full(
        (*plans.shape[:-1], horizon, obs_dim), float("nan"), dtype=plans.dtype, device=plans.device
    )
    schedule[..., list(columns)] = speeds.transpose(-1, -2)
    return schedule, used
