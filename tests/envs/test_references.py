"""Reference policies: the registry by scenario and the rules' decisions on constructed
observations (known answers)."""

from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict

from mapets_rl.envs import make_env
from mapets_rl.envs.freeway import CL, CR, KL, OBS_DIM
from mapets_rl.envs.references import (
    CooperativeMerge,
    GreedyOvertaking,
    check_reference_names,
    make_reference,
    reference_names,
    register_reference,
)


def _observation(
    lane: float,
    neighbours: dict[tuple[int, int], tuple[float, float]],
    to_start: float | None = None,
    to_end: float | None = None,
) -> torch.Tensor:
    """One CAV's freeway(-merge) observation: own lane, and ``(lane block, front/rear) ->
    (dx, dv)`` for present neighbours (lane block 0 left, 1 own, 2 right)."""
    obs = torch.zeros(OBS_DIM + (2 if to_start is not None else 0))
    obs[1] = lane
    for (block, side), (dx, dv) in neighbours.items():
        base = 4 + 3 * (2 * block + side)
        obs[base : base + 3] = torch.tensor([1.0, dx, dv])
    if to_start is not None:
        obs[OBS_DIM], obs[OBS_DIM + 1] = to_start, to_end
    return obs


def _decide(policy, *observations: torch.Tensor) -> list[int]:
    td = TensorDict({("agents", "observation"): torch.stack(observations)[None]}, [1])
    return policy(td).get(("agents", "action"))[0].argmax(-1).tolist()


def test_cooperative_merge_yields_only_beside_a_ramp_vehicle_with_room() -> None:
    rule = CooperativeMerge(lanes=3)
    room = {(0, 0): (50.0, 0.0), (0, 1): (-40.0, 0.0)}
    beside = _observation(2, {**room, (2, 0): (20.0, -5.0)}, to_start=30.0, to_end=75.0)
    no_ramp = _observation(2, room, to_start=30.0, to_end=75.0)
    no_room = _observation(2, {(0, 0): (50.0, 0.0), (0, 1): (-10.0, 0.0), (2, 0): (20.0, -5.0)},
                           to_start=30.0, to_end=75.0)  # fmt: skip
    past_merge = _observation(2, {**room, (2, 0): (20.0, -5.0)}, to_start=-60.0, to_end=-15.0)
    middle_lane = _observation(1, {**room, (2, 0): (20.0, -5.0)}, to_start=30.0, to_end=75.0)
    assert _decide(rule, beside, no_ramp, no_room, past_merge, middle_lane) == [CL, KL, KL, KL, KL]


def test_cooperative_merge_refuses_plain_freeway_observations() -> None:
    with pytest.raises(ValueError, match="freeway-merge observations"):
        _decide(CooperativeMerge(lanes=3), _observation(2, {}))


def test_greedy_overtaking_passes_a_slow_leader_left_first() -> None:
    rule = GreedyOvertaking(lanes=3)
    slow = {(1, 0): (20.0, -3.0)}
    both_free = {**slow, (0, 0): (80.0, 0.0), (0, 1): (-30.0, 0.0), (2, 0): (80.0, 0.0),
                 (2, 1): (-30.0, 0.0)}  # fmt: skip
    right_free = {**slow, (0, 0): (25.0, 0.0), (2, 0): (80.0, 0.0), (2, 1): (-30.0, 0.0)}
    fast_leader = {(1, 0): (20.0, 1.0), (0, 0): (80.0, 0.0)}
    decisions = _decide(
        rule,
        _observation(1, both_free),
        _observation(1, right_free),
        _observation(1, fast_leader),
        _observation(0, {**slow, (2, 0): (80.0, 0.0), (2, 1): (-30.0, 0.0)}),  # leftmost lane
    )
    assert decisions == [CL, CR, KL, CR]


def test_references_are_registered_per_scenario() -> None:
    assert reference_names("freeway-merge") == ["keep-lane", "greedy-overtaking",
                                                "cooperative-merge"]  # fmt: skip
    assert reference_names("freeway") == ["keep-lane", "greedy-overtaking"]
    assert reference_names("figure-eight") == ["idm"]
    with pytest.raises(ValueError, match="'cooperative-merge' is not a reference policy of "
                       "'freeway' \\(choose from: keep-lane, greedy-overtaking\\)"):  # fmt: skip
        check_reference_names("freeway", ["keep-lane", "cooperative-merge"])


def test_a_registered_reference_is_built_for_the_env_in_its_action_format() -> None:
    env = make_env("freeway-merge", backend="torch", num_envs=2, n_vehicles=6,
                   categorical_actions=True)  # fmt: skip
    register_reference("freeway-merge", "always-left", lambda e: GreedyOvertaking(3))
    try:
        assert "always-left" in reference_names("freeway-merge")
        rule = make_reference("freeway-merge", "cooperative-merge", env)
        action = rule(env.reset()).get(("agents", "action"))
        assert action.shape == env.full_action_spec[("agents", "action")].shape
        assert set(action.unique().tolist()) <= {KL, CL}
    finally:
        from mapets_rl.envs import references

        del references._REFERENCES["freeway-merge"]["always-left"]
    env.close()
