"""The oracle that knows every other CAV's future exactly (issue 33): the upper bound of what
sharing plans can give.

Plan sharing (:class:`~mapets_rl.planning.shared_plans.PlanSharingPlanner`) tells a CAV what
its neighbours' CEMs *predicted* they would drive. Here a CAV is told what they then *did*:
the speeds every CAV drove in a recorded rollout of the same seed replace the planner's
constant-speed guess for the CAVs it observes (leader, follower, conflicting vehicle, the other
lane's leader and follower; every observed CAV, no communication range or link failures: the
observation's 75 m reach is the only limit). Humans stay predicted.

Since the CAVs react to what they are told, a replayed future stops being exact once the new
rollout departs from the recorded one. :func:`benchmarks.multilane_diagnosis.run_episode`
(policy ``oracle-exact``) therefore iterates towards a fixed point: rollout 0 is
``oracle-shared``, rollout ``k`` replays rollout ``k - 1``'s speeds, and
:func:`schedule_exactness` says per rollout how exact the replayed futures were.

- :func:`replay_schedule`: the planner's schedule ``[I, H, S]`` from a recorded rollout;
- :class:`ExactFuturePlanner`: a batched planner that plans with it (one call for all agents);
- :func:`broadcast_schedule`: the schedule a :class:`PlanSharingPlanner` is about to use
  (for the exactness of broadcast plans, rollout 0);
- :func:`schedule_exactness`: used schedule entries against what then happened.

Time alignment (the planner's schedule convention, :func:`mapets_rl.comm.plan_schedule`):
``record[m, j]`` is CAV ``j``'s speed in the observation after ``m`` env steps (``m = 0``: the
reset); at the decision on the observation after ``n`` steps, ``schedule[i, t, columns[k]]``
is ``record[n + t + 1, j]`` for the CAV ``j`` in slot ``k`` of CAV ``i``: the speed in the state
after step ``t`` of the planner's rollout.
"""

from __future__ import annotations

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from tensordict.utils import NestedKey

from mapets_rl.comm import plan_schedule
from mapets_rl.planning import TrajectorySamplingCEM
from mapets_rl.planning.shared_plans import PlanSharingPlanner

__all__ = [
    "EXACT_TOLERANCE",
    "ExactFuturePlanner",
    "broadcast_schedule",
    "replay_schedule",
    "schedule_exactness",
]

WARM_START = ("_mean", "_elites", "_solution", "_batch_shape")
"""The :class:`TrajectorySamplingCEM` attributes that carry one decision's result to the next
(what its :meth:`~TrajectorySamplingCEM.reset` clears)."""

EXACT_TOLERANCE = 0.1
"""A schedule entry within this many m/s of the speed then driven counts as exact."""


def replay_schedule(
    record: torch.Tensor,
    step: int,
    neighbour_cav: torch.Tensor,
    columns: tuple[int, ...],
    obs_dim: int,
    horizon: int,
) -> tuple[torch.Tensor, torch.Tensor]:
    """The planner's schedule of known neighbour speeds, replayed from a recorded rollout.

    Args:
        record: ``[T + 1, I]`` each CAV's speed after ``m`` steps of the recorded rollout
            (row ``m``; NaN where that CAV no longer drove).
        step: ``n``, the env steps taken before this decision.
        neighbour_cav: ``[I, K]`` the agent index of the CAV in each observed slot (``-1``:
            a human driver, nobody, a CAV that no longer drives; floats are rounded).
        columns: the ``K`` observation columns of the slots' speeds.
        obs_dim: ``S``.
        horizon: ``H``, the planner's.

    Returns:
        ``schedule [I, H, S]``: ``schedule[i, t, columns[k]] = record[n + t + 1, j]`` for the CAV
        ``j`` in slot ``k`` of ``i`` (past the record's end its last row; NaN for humans, empty
        slots and the times after ``j`` stopped in the record: the model predicts those), NaN in
        the other columns; and ``used [I, K]`` bool: the slots with at least one known speed.
    """
    if neighbour_cav.shape[-1] != len(columns):
        raise ValueError(
            f"neighbour_cav has {neighbour_cav.shape[-1]} slots but {len(columns)} columns "
            f"were given ({columns})"
        )
    if record.ndim != 2 or neighbour_cav.ndim != 2:
        raise ValueError(
            f"record must be [T + 1, I] and neighbour_cav [I, K], got {list(record.shape)} and "
            f"{list(neighbour_cav.shape)}"
        )
    sender = neighbour_cav.round().long()  # [I, K]
    valid = sender >= 0
    times = (step + 1 + torch.arange(horizon, device=record.device)).clamp_max(len(record) - 1)
    speeds = record[times][:, sender.clamp_min(0)]  # [H, I, K]
    speeds = torch.where(valid, speeds, float("nan")).to(record.dtype)
    used = ~torch.isnan(speeds).all(0)  # [I, K]
    schedule = torch.full(
        (sender.shape[0], horizon, obs_dim), float("nan"), dtype=record.dtype,
        device=record.device,
    )  # fmt: skip
    schedule[..., list(columns)] = speeds.transpose(0, 1)
    return schedule, used


def broadcast_schedule(
    sharing: PlanSharingPlanner, tensordict: TensorDictBase
) -> tuple[torch.Tensor, torch.Tensor] | None:
    """The schedule ``[I, H, S]`` and its slots' senders ``[I, K]`` that ``sharing`` is about to
    plan with on ``tensordict`` (None before its first broadcast): its last step's plans through
    :func:`plan_schedule`, as in :meth:`PlanSharingPlanner.forward`."""
    plans = sharing._plans  # the broadcasts of the step before (read-only here)
    if plans is None:
        return None
    obs = tensordict.get(sharing.planner.in_keys[0])
    links = tensordict.get(sharing.neighbors_key).to(torch.bool)
    neighbour = tensordict.get(sharing.neighbour_key)
    driving = tensordict.get(sharing.mask_key, None)
    if driving is not None:
        neighbour = torch.where(driving.to(torch.bool).reshape(obs.shape[:-1]).unsqueeze(-1),
                                neighbour, -1)  # fmt: skip
    schedule, used = plan_schedule(
        plans, neighbour, links, sharing.columns, sharing.planner.model.obs_dim
    )
    return schedule, torch.where(used, neighbour.round().long(), -1)


class ExactFuturePlanner(TensorDictModuleBase):
    """Wraps a :class:`TrajectorySamplingCEM`: every agent plans, in one batched call, with its
    observed CAVs' speeds replayed from :attr:`record` (:func:`replay_schedule`).

    Reads the observation ``[I, S]``, ``neighbour_key`` ``[I, K]`` and, when present,
    ``mask_key`` ``[I]``; writes the action. Without a record it plans like the wrapped planner.

    Attributes:
        record: ``[T + 1, I]`` the recorded rollout's speeds (set before :meth:`reset`).
        last_schedule: the schedule ``[I, H, S]`` and the senders ``[I, K]`` (``-1``: slot not
            used) of the latest decision.
        plans_used: slots filled from the record since :meth:`reset`.
        step: decisions since :meth:`reset` (``n`` of :func:`replay_schedule`).
    """

    def __init__(
        self,
        planner: TrajectorySamplingCEM,
        columns: tuple[int, ...],
        record: torch.Tensor | None = None,
        *,
        neighbour_key: NestedKey = ("agents", "info", "neighbour_cav"),
        mask_key: NestedKey = ("agents", "mask"),
    ) -> None:
        super().__init__()
        self.planner = planner
        self.columns = tuple(int(c) for c in columns)
        self.record = record
        self.neighbour_key, self.mask_key = neighbour_key, mask_key
        self.in_keys = [*planner.in_keys, neighbour_key]
        self.out_keys = list(planner.out_keys)
        self.reset()

    def reset(self) -> None:
        """Start an episode: forget the warm start, replay from the record's first row."""
        self.planner.reset()
        self.step = 0
        self.plans_used = 0
        self.last_schedule: tuple[torch.Tensor, torch.Tensor] | None = None

    def state(self) -> dict:
        """What the next decisions depend on besides the record and the observations: the
        step, the counts, the planner's warm start and its random generator (for
        :meth:`load_state`: a window of ``oracle-exact-windowed`` restarts from it)."""
        planner = self.planner
        warm = {name: getattr(planner, name) for name in WARM_START}
        return {
            "step": self.step,
            "plans_used": self.plans_used,
            "warm": {k: v.clone() if isinstance(v, torch.Tensor) else v for k, v in warm.items()},
            "generator": planner.generator.get_state(),
        }

    def load_state(self, state: dict) -> None:
        """Back to a :meth:`state`."""
        self.step, self.plans_used = state["step"], state["plans_used"]
        for name, value in state["warm"].items():
            setattr(self.planner, name, value.clone() if isinstance(value, torch.Tensor) else value)
        self.planner.generator.set_state(state["generator"])
        self.last_schedule = None

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        planner = self.planner
        obs = tensordict.get(planner.in_keys[0])
        is_init = tensordict.get(planner.is_init_key, None)
        schedule = None
        if self.record is not None:
            neighbour = tensordict.get(self.neighbour_key).round().long()
            driving = tensordict.get(self.mask_key, None)
            if driving is not None:  # rows of CAVs that no longer drive say nothing
                neighbour = torch.where(
                    driving.to(torch.bool).reshape(obs.shape[:-1]).unsqueeze(-1), neighbour, -1
                )
            schedule, used = replay_schedule(
                self.record, self.step, neighbour, self.columns, planner.model.obs_dim,
                planner.config.horizon,
            )  # fmt: skip
            self.last_schedule = (schedule, torch.where(used, neighbour, -1))
            self.plans_used += int(used.sum())
        self.step += 1
        action = planner.plan(obs, is_init=is_init, schedule=schedule)
        return tensordict.set(planner.out_keys[0], action)


def schedule_exactness(
    schedules: list[tuple[int, torch.Tensor, torch.Tensor]],
    record: torch.Tensor,
    columns: tuple[int, ...],
    tolerance: float = EXACT_TOLERANCE,
) -> dict[str, float]:
    """How exact the known speeds a planner used were, against the rollout then driven.

    Args:
        schedules: per decision ``(n, schedule [I, H, S], senders [I, K])`` (``n``: env steps
            before it; ``senders``: the CAV whose speeds each slot holds, ``-1``: not used).
        record: ``[T + 1, I]`` the speeds then driven (NaN: not driving).
        columns: the slots' speed columns.

    Returns:
        ``exact``: the share of compared entries within ``tolerance`` m/s; ``mae``: their mean
        absolute error [m/s]; ``entries``: used (finite) entries per decision; ``compared``:
        the share of them with a speed to compare to (the sender still drove, within the
        episode).
    """
    errors, used, compared = [], 0, 0
    last = len(record) - 1
    for n, schedule, senders in schedules:
        horizon = schedule.shape[-2]
        speeds = schedule[..., list(columns)]  # [I, H, K]
        times = n + 1 + torch.arange(horizon)  # [H]
        actual = record[times.clamp_max(last)][:, senders.clamp_min(0)]  # [H, I, K]
        actual = actual.transpose(0, 1)  # [I, H, K]
        known = ~torch.isnan(speeds) & (senders >= 0).unsqueeze(-2)
        there = known & ~torch.isnan(actual) & (times <= last).view(1, -1, 1)
        used += int(known.sum())
        compared += int(there.sum())
        errors.append((speeds - actual)[there].abs())
    error = torch.cat(errors) if errors else torch.zeros(0)
    return {
        "exact": float((error <= tolerance).float().mean()) if len(error) else float("nan"),
        "mae": float(error.mean()) if len(error) else float("nan"),
        "entries": used / max(len(schedules), 1),
        "compared": compared / used if used else float("nan"),
    }
