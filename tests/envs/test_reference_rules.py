"""The reference rules of ``mapets_rl.envs.references`` on constructed observations, case by
case (each CAV's decision is a known answer): ``GreedyOvertaking``'s gaps and
``CooperativeMerge``'s window around the ramp vehicle and room in the left lane."""

from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict

from mapets_rl.envs.freeway import CL, CR, KL, OBS_DIM
from mapets_rl.envs.freeway_merge import OBS_DIM as MERGE_OBS_DIM
from mapets_rl.envs.references import CooperativeMerge, GreedyOvertaking
from mapets_rl.modules import ACTION, OBS

PERCEPTION = 100.0


def _observation(lane: int, front_dx: float, front_dv: float, left_front: float) -> torch.Tensor:
    """One CAV at 25 m/s in ``lane`` of 3; left and right lanes empty except a front vehicle
    ``left_front`` m ahead in the left lane (and in the right one)."""
    obs = torch.zeros(OBS_DIM)
    obs[:2] = torch.tensor([25.0, float(lane)])
    nb = obs[4:].view(3, 2, 3)
    for k in range(3):
        nb[k, 0] = torch.tensor([0.0, PERCEPTION, 0.0])
        nb[k, 1] = torch.tensor([0.0, -PERCEPTION, 0.0])
    nb[1, 0] = torch.tensor([1.0, front_dx, front_dv])
    nb[0, 0] = nb[2, 0] = torch.tensor([1.0, left_front, 0.0])
    return obs


@pytest.mark.parametrize(
    ("lane", "front_dx", "front_dv", "side_front", "expected"),
    [
        (1, 20.0, -3.0, 80.0, CL),  # blocked, left lane free: left first
        (0, 20.0, -3.0, 80.0, CR),  # no lane on the left: right
        (1, 20.0, -3.0, 30.0, KL),  # adjacent front gaps not 15 m longer
        (1, 60.0, -3.0, 100.0, KL),  # leader far
        (1, 20.0, 1.0, 100.0, KL),  # leader not slower
    ],
)
def test_overtaking_rule(
    lane: int,
    front_dx: float,
    front_dv: float,
    side_front: float,
    expected: int,
) -> None:
    rule = GreedyOvertaking(3, 40.0, 15.0, 15.0, dtype=torch.int64)
    obs = _observation(lane, front_dx, front_dv, side_front).expand(2, 1, OBS_DIM)
    action = rule(TensorDict({OBS: obs}, batch_size=[2])).get(ACTION)
    assert action.shape == (2, 1, 4) and action.dtype == torch.int64
    assert (action.argmax(-1) == expected).all() and (action.sum(-1) == 1).all()


def test_rear_vehicle_blocks_the_change() -> None:
    rule = GreedyOvertaking(3, 40.0, 15.0, 15.0, dtype=torch.int64)
    obs = _observation(1, 20.0, -3.0, 80.0)
    obs[4:].view(3, 2, 3)[0, 1] = torch.tensor([1.0, -5.0, 2.0])  # left rear 5 m behind
    action = rule(TensorDict({OBS: obs[None]}, batch_size=[1])).get(ACTION)
    assert action[0].argmax().item() == CR


def _merge_observation(
    lane: int, to_start: float, ramp_dx: float | None, left_rear: tuple[float, float]
) -> torch.Tensor:
    """A freeway-merge observation: one CAV at 25 m/s in ``lane`` of 3, ``to_start`` metres
    before the acceleration lane (which is 60 m long), a ramp vehicle ``ramp_dx`` metres ahead
    (or behind, negative) in the right block (none if ``None``), the left lane's front vehicle
    80 m ahead and its rear vehicle at ``left_rear = (dx, dv)``."""
    obs = torch.zeros(MERGE_OBS_DIM)
    obs[:OBS_DIM] = _observation(lane, 60.0, 0.0, 80.0)
    nb = obs[4:OBS_DIM].view(3, 2, 3)
    nb[2, 0] = torch.tensor([0.0, PERCEPTION, 0.0])
    nb[0, 1] = torch.tensor([1.0, *left_rear])
    if ramp_dx is not None:
        nb[2, 0 if ramp_dx >= 0 else 1] = torch.tensor([1.0, ramp_dx, -10.0])
    obs[OBS_DIM:] = torch.tensor([to_start, to_start + 60.0]).clamp(-PERCEPTION, PERCEPTION)
    return obs


@pytest.mark.parametrize(
    ("lane", "to_start", "ramp_dx", "left_rear", "expected"),
    [
        (2, 50.0, -20.0, (-40.0, 0.0), CL),  # ramp vehicle just behind: make room
        (2, 50.0, 50.0, (-40.0, 0.0), CL),  # ramp vehicle ahead within 60 m
        (2, -30.0, -20.0, (-40.0, 0.0), CL),  # beside the acceleration lane
        (2, 50.0, -40.0, (-40.0, 0.0), KL),  # ramp vehicle more than 30 m behind
        (2, 50.0, 70.0, (-40.0, 0.0), KL),  # ramp vehicle more than 60 m ahead
        (2, 50.0, None, (-40.0, 0.0), KL),  # empty ramp
        (2, 150.0, -20.0, (-40.0, 0.0), KL),  # merge more than 100 m ahead
        (2, -70.0, -5.0, (-40.0, 0.0), KL),  # past the merge point
        (1, 50.0, -20.0, (-40.0, 0.0), KL),  # not in the rightmost lane
        (2, 50.0, -20.0, (-10.0, 0.0), KL),  # left rear vehicle too close
        (2, 50.0, -20.0, (-25.0, 10.0), KL),  # left rear 25 m behind but 10 m/s faster
        (2, 50.0, -20.0, (-25.0, -10.0), CL),  # ... 10 m/s slower: room
    ],
)
def test_cooperative_merge_rule(
    lane: int,
    to_start: float,
    ramp_dx: float | None,
    left_rear: tuple[float, float],
    expected: int,
) -> None:
    rule = CooperativeMerge(3, 100.0, 60.0, 30.0, 15.0, 15.0, 1.5, dtype=torch.int64)
    obs = _merge_observation(lane, to_start, ramp_dx, left_rear).expand(2, 1, MERGE_OBS_DIM)
    action = rule(TensorDict({OBS: obs}, batch_size=[2])).get(ACTION)
    assert action.shape == (2, 1, 4) and action.dtype == torch.int64
    assert (action.argmax(-1) == expected).all() and (action.sum(-1) == 1).all()


def test_cooperative_rule_needs_merge_observations() -> None:
    rule = CooperativeMerge(3, 100.0, 60.0, 30.0, 15.0, 15.0, 1.5, dtype=torch.int64)
    with pytest.raises(ValueError, match="needs freeway-merge observations"):
        rule(TensorDict({OBS: torch.zeros(1, 2, OBS_DIM)}, batch_size=[1]))
