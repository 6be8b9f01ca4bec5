"""Exact counterfactuals on the batched freeway (``mapets_rl.envs.torch_freeway.counterfactuals``),
on constructed scenes with known answers."""

from __future__ import annotations

import pytest
import torch

from mapets_rl.envs import make_env
from mapets_rl.envs.freeway import CL, CR, KL
from mapets_rl.envs.references import make_reference
from mapets_rl.envs.torch_freeway.counterfactuals import (
    MERGE_DECISIONS,
    branches,
    cav_lanes,
    deciding,
    lane_change_effects,
    merge_decisions,
    near_merge,
    on_mainline,
    returns_per_cav,
)
from mapets_rl.envs.torch_freeway.simulator import BatchedFreeway

HORIZON = 6


def _sim(roads: int = 3, **config) -> tuple[object, BatchedFreeway]:
    env = make_env("freeway-merge", backend="torch", num_envs=roads, n_vehicles=8,
                   cav_ratio=1.0, horizon=HORIZON, **config)  # fmt: skip
    env.set_seed(3)
    env.reset()
    return env, env.sim


def _keep(observation: torch.Tensor) -> torch.Tensor:
    return torch.full(observation.shape[:2], KL, dtype=torch.long)


def test_replacing_a_decision_by_itself_changes_nothing() -> None:
    """A branch whose replacement is the decision taken is the policy's own continuation: the
    same returns, metres and positions to the last bit, and ``sim`` is left untouched."""
    env, sim = _sim()
    action = torch.full((sim.n_roads, sim.n_cavs), KL, dtype=torch.long)
    action[:, 0] = CL
    before = sim.snapshot()
    road, cav = torch.tensor([0, 2, 2]), torch.tensor([0, 1, 0])
    returns, metres, y, base, own = branches(sim, action, road, cav, action[road, cav], _keep, 0.9)
    assert base.tolist() == [0, 1, 1] and own.tolist() == [2, 3, 4]
    assert torch.equal(returns[base], returns[own]) and torch.equal(metres[base], metres[own])
    assert torch.equal(y[base], y[own])
    assert (sim.snapshot() == before).all()
    env.close()


def test_discount_zero_is_the_first_steps_reward() -> None:
    """With ``gamma = 0`` a CAV's return is its reward of the first step, as one step of the
    road gives it."""
    env, sim = _sim(roads=2)
    first = torch.full((2, sim.n_cavs), CL, dtype=torch.long)
    returns, metres, _ = returns_per_cav(sim.take(torch.arange(2)), first, _keep, 0.0)
    step = sim.take(torch.arange(2)).step(first)
    assert torch.equal(returns, step.reward.double()) and torch.equal(
        metres, step.distance.double()
    )
    with pytest.raises(ValueError, match="gamma"):
        returns_per_cav(sim.take(torch.arange(2)), first, _keep, 1.5)
    env.close()


def test_lane_change_effects_of_keep_lane_and_of_a_change_left() -> None:
    """Keep lane makes no lane-change decision; a CAV that always asks for Change Left makes
    one per step on each road (one entry in every list). A request that moves no vehicle (a
    CAV already in the leftmost lane) changes no one's metres and costs only the CAV itself:
    its own effect is the system's."""
    env, sim = _sim(roads=4)
    assert lane_change_effects(sim, _keep) == dict.fromkeys(
        ("step", "near", "moved", "own", "own_metres", "system"), []
    )
    env.close()
    env, sim = _sim(roads=4)
    lane, x = cav_lanes(sim)
    assert lane.shape == x.shape == (4, sim.n_cavs)
    mainline = on_mainline(sim, lane)  # the ramp's CAVs start on it
    assert mainline[:, 0].all() and (~mainline).any()
    assert not near_merge(sim, torch.full_like(x, sim.geometry.merge_start - 101.0)).any()
    assert near_merge(sim, torch.full_like(x, sim.geometry.merge_end)).all()

    def change_left(observation: torch.Tensor) -> torch.Tensor:  # CAV 0 always moves left
        decisions = _keep(observation)
        decisions[:, 0] = CL
        return decisions

    effects = lane_change_effects(sim, change_left, gamma=1.0, rest=False)
    assert effects["step"] == [step for step in range(HORIZON) for _ in range(4)]
    assert all(len(values) == 4 * HORIZON for values in effects.values())
    assert any(effects["moved"]) and not all(effects["moved"])
    for moved, own, metres, system in zip(
        effects["moved"], effects["own"], effects["own_metres"], effects["system"], strict=True
    ):
        if not moved:
            assert metres == 0.0 and own == system < 0.0
    env.close()


def test_deciding_reads_a_policys_one_hot_actions() -> None:
    """``deciding``: the index of the one-hot action a reference writes, per road and CAV."""
    env, sim = _sim(roads=2)
    decide = deciding(make_reference("freeway-merge", "cooperative-merge", env))
    decisions = decide(sim.observe())
    assert decisions.shape == (2, sim.n_cavs) and set(decisions.unique().tolist()) <= {KL, CL}
    env.close()


def test_opting_out_for_the_rest_of_the_episode_forgoes_every_later_change() -> None:
    """``rest``: the CAV keeps its lane to the end, not for one step only. The same decisions
    are replayed; where Change Left moves nothing (the leftmost lane), opting out for good
    also forgoes the comfort cost of every later Change Left, so it is worth at least as
    much to the CAV as opting out once, and strictly more somewhere."""
    effects = {}
    for rest in (False, True):
        env, sim = _sim(roads=2)
        effects[rest] = lane_change_effects(sim, lambda o: torch.full(o.shape[:2], CL),
                                            gamma=1.0, rest=rest)  # fmt: skip
        env.close()
    once, always = effects[False], effects[True]
    assert once["step"] == always["step"] and once["moved"] == always["moved"]
    still = [i for i, moved in enumerate(always["moved"]) if not moved]
    assert still and all(always["own"][i] <= once["own"][i] + 1e-9 for i in still)
    assert any(always["own"][i] < once["own"][i] - 0.5 for i in still)


def test_merge_decisions_ask_each_kind_its_own_move() -> None:
    """Every decision's probe sees the move of its kind (Change Right for moves right, Change
    Left otherwise); on the dilemma variant (``ramp_forcing`` off) no forcing move runs; a move
    that did not run changes no return."""

    def replacement(observation, action, road, cav, moves):
        return moves.double()

    env, sim = _sim(roads=4, ramp_forcing=False)
    found = merge_decisions(sim, 0.99, [replacement])
    kind = found["kind"]
    assert set(kind.tolist()) <= set(range(len(MERGE_DECISIONS)))
    right = kind == MERGE_DECISIONS.index("Change Right")
    assert torch.equal(found["probe0"], torch.where(right, CR, CL).double())
    still = ~found["moved"]
    assert torch.equal(found["own"][still], torch.zeros_like(found["own"][still]))
    assert torch.equal(found["system"][still], torch.zeros_like(found["system"][still]))
    forcing_ran = found["moved"][kind == MERGE_DECISIONS.index("forcing")]
    assert forcing_ran.numel() > 0
    assert not forcing_ran.any()
    assert found["moved"].any()
    env.close()


def test_merge_decisions_refuse_a_road_without_a_merge() -> None:
    env = make_env("freeway", backend="torch", num_envs=2, n_vehicles=6, horizon=HORIZON)
    env.reset()
    with pytest.raises(ValueError, match="freeway-merge"):
        merge_decisions(env.sim, 0.99)
    env.close()
