"""benchmarks/freeway_headroom.py: the greedy overtaking rule's decisions on constructed
observations, and a tiny end-to-end run."""

from __future__ import annotations

from collections.abc import Callable
from types import ModuleType

import pytest
import torch
from tensordict import TensorDict

from mapets_rl.envs.freeway import CL, CR, KL, OBS_DIM
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
    load_script: Callable[[str], ModuleType],
    lane: int,
    front_dx: float,
    front_dv: float,
    side_front: float,
    expected: int,
) -> None:
    headroom = load_script("benchmarks/freeway_headroom.py")
    rule = headroom.GreedyOvertaking(3, 40.0, 15.0, 15.0, torch.int64)
    obs = _observation(lane, front_dx, front_dv, side_front).expand(2, 1, OBS_DIM)
    action = rule(TensorDict({OBS: obs}, batch_size=[2])).get(ACTION)
    assert action.shape == (2, 1, 4) and action.dtype == torch.int64
    assert (action.argmax(-1) == expected).all() and (action.sum(-1) == 1).all()


def test_rear_vehicle_blocks_the_change(load_script: Callable[[str], ModuleType]) -> None:
    headroom = load_script("benchmarks/freeway_headroom.py")
    rule = headroom.GreedyOvertaking(3, 40.0, 15.0, 15.0, torch.int64)
    obs = _observation(1, 20.0, -3.0, 80.0)
    obs[4:].view(3, 2, 3)[0, 1] = torch.tensor([1.0, -5.0, 2.0])  # left rear 5 m behind
    action = rule(TensorDict({OBS: obs[None]}, batch_size=[1])).get(ACTION)
    assert action[0].argmax().item() == CR


def test_tiny_table(load_script: Callable[[str], ModuleType], capsys) -> None:
    headroom = load_script("benchmarks/freeway_headroom.py")
    headroom.main(["--ratios", "0.5", "--seeds", "0", "1", "--n-vehicles", "6",
                   "--eval-episodes", "1", "--env-override", "horizon=6"])  # fmt: skip
    out = capsys.readouterr().out
    assert "CPU capability" in out
    assert "| 0.50 | keep lane |" in out and "| 0.50 | greedy overtaking |" in out
    with pytest.raises(SystemExit):
        headroom.main(["--ratios", "0"])
