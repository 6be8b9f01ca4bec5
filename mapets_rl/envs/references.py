"""Reference policies: scripted CAV policies that a learned policy is scored against, registered
by name per scenario.

A reference is a factory ``env -> TensorDictModuleBase`` whose module writes
``("agents", "action")`` from ``("agents", "observation")`` (one-hot or categorical, as the
env's action spec says). The built-in ones:

- ``keep-lane`` (freeways): every CAV keeps its lane under IDM (:class:`ScriptedCAVPolicy`);
- ``greedy-overtaking`` (freeways): :class:`GreedyOvertaking`, a CAV stuck behind a slower
  leader changes to an adjacent lane with a longer front gap and room behind;
- ``cooperative-merge`` (``freeway-merge``): :class:`CooperativeMerge`, a CAV in the rightmost
  lane before the merge moves left when a ramp vehicle is beside it and the left lane has room;
- ``idm`` (figure-eights): IDM and first come, first served at the crossing
  (:class:`ScriptedCAVPolicy`).

Their settings are those every published table used (``docs/results/scenarios.md``,
"headroom"). A scenario of another package registers its own with :func:`register_reference`.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torchrl.data import OneHot
from torchrl.envs import EnvBase

from mapets_rl.envs.freeway import CL, CR, KL, OBS_DIM
from mapets_rl.envs.freeway_merge import OBS_DIM as MERGE_OBS_DIM
from mapets_rl.envs.scripted import ScriptedCAVPolicy, scenario_config

ACTION = ("agents", "action")
OBSERVATION = ("agents", "observation")

ReferenceFactory = Callable[[EnvBase], TensorDictModuleBase]
"""``env -> module`` writing ``("agents", "action")`` for every CAV of ``env``."""

_REFERENCES: dict[str, dict[str, ReferenceFactory]] = {}


def _write_decisions(
    tensordict: TensorDictBase, index: torch.Tensor, one_hot: bool, dtype: torch.dtype
) -> TensorDictBase:
    """Write the freeway decisions ``index`` ``[*, n]`` (0..3) as the env's action: one-hot
    ``[*, n, 4]`` when ``one_hot``, else the indices."""
    action = torch.nn.functional.one_hot(index.long(), 4) if one_hot else index.long()
    tensordict.set(ACTION, action.to(dtype))
    return tensordict


def _neighbours(obs: torch.Tensor) -> torch.Tensor:
    """The neighbour block of a freeway observation ``[*, n, >= 22]`` as ``[*, n, 3, 2, 3]``:
    lane (left, own, right) x (front, rear) x (present, dx [m], dv [m/s])."""
    return obs[..., 4:OBS_DIM].unflatten(-1, (3, 2, 3))


class LaneRule(TensorDictModuleBase):
    """A scripted freeway rule: reads ``("agents", "observation")`` and writes each CAV's
    decision as the env's action (one-hot ``[*, n, 4]`` when ``one_hot``, else the indices
    ``[*, n]``, in ``dtype``), on a road of ``lanes`` mainline lanes."""

    in_keys = [OBSERVATION]
    out_keys = [ACTION]

    def __init__(self, lanes: int, one_hot: bool, dtype: torch.dtype) -> None:
        super().__init__()
        if lanes < 1:
            raise ValueError(f"lanes must be >= 1, got {lanes}")
        self.lanes, self.one_hot, self.dtype = lanes, one_hot, dtype

    @classmethod
    def for_env(cls, env: EnvBase) -> LaneRule:
        """The rule with its default settings for ``env`` (made by ``make_env``, either
        backend): its scenario's lanes, its action's format."""
        spec = env.full_action_spec[ACTION]
        lanes = int(scenario_config(env)["lanes"])
        return cls(lanes, one_hot=isinstance(spec, OneHot), dtype=spec.dtype)

    def decide(self, tensordict: TensorDictBase, index: torch.Tensor) -> TensorDictBase:
        """Write the decisions ``index`` ``[*, n]`` (0..3) into ``tensordict``."""
        return _write_decisions(tensordict, index, self.one_hot, self.dtype)


class GreedyOvertaking(LaneRule):
    """Overtake a slow leader, vectorised over CAVs: observation ``[*, n, >= 22]`` -> action.

    A CAV whose leader in its lane is closer than ``follow_gap`` metres and slower (by more than
    0.5 m/s) changes to an adjacent lane, left first, when that lane's front gap is longer by
    ``gain_gap`` metres and its rear gap exceeds ``rear_gap`` metres; otherwise it keeps its
    lane."""

    def __init__(
        self,
        lanes: int,
        follow_gap: float = 40.0,
        gain_gap: float = 15.0,
        rear_gap: float = 15.0,
        *,
        one_hot: bool = True,
        dtype: torch.dtype = torch.int64,
    ) -> None:
        super().__init__(lanes, one_hot, dtype)
        self.follow_gap, self.gain_gap, self.rear_gap = follow_gap, gain_gap, rear_gap

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        obs = tensordict.get(OBSERVATION)
        lane = obs[..., 1]
        nb = _neighbours(obs)
        front_dx, front_dv = nb[..., 1, 0, 1], nb[..., 1, 0, 2]
        blocked = (nb[..., 1, 0, 0] > 0) & (front_dx < self.follow_gap) & (front_dv < -0.5)

        def free(k: int, exists: torch.Tensor) -> torch.Tensor:
            longer = nb[..., k, 0, 1] > front_dx + self.gain_gap
            clear_behind = -nb[..., k, 1, 1] > self.rear_gap
            return exists & longer & clear_behind

        left = blocked & free(0, lane >= 1)
        right = blocked & ~left & free(2, lane <= self.lanes - 2)
        index = torch.where(left, CL, torch.where(right, CR, KL))
        return self.decide(tensordict, index)


class CooperativeMerge(LaneRule):
    """The cooperative rule of ``freeway-merge``, vectorised over CAVs: observation
    ``[*, n, 24]`` (the freeway's 22 entries, whose right block is the ramp for a CAV in the
    rightmost lane; then the distances [m] to the acceleration lane's start and to the merge
    point) -> action.

    A CAV in the rightmost lane (``lanes - 1``) less than ``approach`` metres before the
    acceleration lane and before the merge point changes left when a ramp vehicle is beside it
    (the nearest ramp vehicle ahead within ``ramp_ahead`` metres or behind within
    ``ramp_behind`` metres) and the left lane has room (front gap > ``front_gap``, rear gap >
    ``rear_gap`` + ``closing_time`` x the speed at which the left rear vehicle comes up);
    every other CAV keeps its lane (a CAV on the ramp merges by MOBIL under Keep Lane)."""

    def __init__(
        self,
        lanes: int,
        approach: float = math.inf,
        ramp_ahead: float = 60.0,
        ramp_behind: float = 30.0,
        front_gap: float = 15.0,
        rear_gap: float = 15.0,
        closing_time: float = 1.5,
        *,
        one_hot: bool = True,
        dtype: torch.dtype = torch.int64,
    ) -> None:
        super().__init__(lanes, one_hot, dtype)
        self.approach, self.ramp_ahead, self.ramp_behind = approach, ramp_ahead, ramp_behind
        self.front_gap, self.rear_gap, self.closing_time = front_gap, rear_gap, closing_time

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        obs = tensordict.get(OBSERVATION)
        if obs.shape[-1] != MERGE_OBS_DIM:
            raise ValueError(
                f"CooperativeMerge needs freeway-merge observations ({MERGE_OBS_DIM} entries), "
                f"got {obs.shape[-1]}"
            )
        lane = obs[..., 1]
        nb = _neighbours(obs)
        to_start, to_end = obs[..., OBS_DIM], obs[..., OBS_DIM + 1]
        near = (lane == self.lanes - 1) & (to_start < self.approach) & (to_end > 0)
        ramp_front = (nb[..., 2, 0, 0] > 0) & (nb[..., 2, 0, 1] <= self.ramp_ahead)
        ramp_rear = (nb[..., 2, 1, 0] > 0) & (-nb[..., 2, 1, 1] <= self.ramp_behind)
        closing = nb[..., 0, 1, 2].clamp(min=0.0)  # how fast the left rear vehicle comes up
        room = (nb[..., 0, 0, 1] > self.front_gap) & (
            -nb[..., 0, 1, 1] > self.rear_gap + self.closing_time * closing
        )
        index = torch.where(near & (ramp_front | ramp_rear) & room, CL, KL)
        return self.decide(tensordict, index)


def register_reference(scenario: str, name: str, factory: ReferenceFactory) -> None:
    """Register ``factory`` as the reference policy ``name`` of ``scenario`` (replacing one of
    the same name)."""
    if not name or not isinstance(name, str):
        raise ValueError(f"name must be a non-empty string, got {name!r}")
    if not callable(factory):
        raise ValueError(f"factory must be callable (env -> module), got {factory!r}")
    _REFERENCES.setdefault(scenario, {})[name] = factory


def reference_names(scenario: str) -> list[str]:
    """The reference policies registered for ``scenario``, in registration order."""
    return list(_REFERENCES.get(scenario, {}))


def make_reference(scenario: str, name: str, env: EnvBase) -> TensorDictModuleBase:
    """The reference policy ``name`` of ``scenario`` built for ``env``; ValueError naming the
    scenario's references when ``name`` is not one of them."""
    check_reference_names(scenario, [name])
    return _REFERENCES[scenario][name](env)


def check_reference_names(scenario: str, names: list[str] | tuple[str, ...]) -> None:
    """ValueError naming the first of ``names`` that is not a reference of ``scenario`` (before
    any env is built)."""
    known = reference_names(scenario)
    for name in names:
        if name not in known:
            raise ValueError(
                f"references: {name!r} is not a reference policy of {scenario!r} (choose from: "
                f"{', '.join(known) or 'none registered'})"
            )


for _scenario in ("freeway", "freeway-merge"):
    register_reference(_scenario, "keep-lane", ScriptedCAVPolicy)
    register_reference(_scenario, "greedy-overtaking", GreedyOvertaking.for_env)
register_reference("freeway-merge", "cooperative-merge", CooperativeMerge.for_env)
for _scenario in ("figure-eight", "figure-eight-multilane"):
    register_reference(_scenario, "idm", ScriptedCAVPolicy)
