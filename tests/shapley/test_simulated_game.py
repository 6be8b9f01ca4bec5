"""The coalition game of a freeway state by simulation: branching is exact, the game's values
are the rollouts they name, and its Shapley value is efficient."""

from __future__ import annotations

import pytest
import torch

from mapets_rl.envs import make_env
from mapets_rl.envs.freeway import CL, KL
from mapets_rl.envs.torch_freeway.simulator import BatchedFreeway
from mapets_rl.shapley.game import exact_shapley
from mapets_rl.shapley.simulated import simulated_game, simulated_member_game

CONFIG = {"n_vehicles": 12, "cav_ratio": 0.25, "ramp_fraction": 0.25, "spawn_length": 300.0}


def simulator(roads: int = 2) -> BatchedFreeway:
    config = make_env("freeway-merge", backend="torch", **CONFIG).config
    sim = BatchedFreeway(config, True, roads, dtype=torch.float64, seed=5)
    for _ in range(3):
        sim.step(torch.full((roads, sim.n_cavs), KL))
    return sim


def change_left(observation: torch.Tensor, members: torch.Tensor | None = None) -> torch.Tensor:
    return torch.full(observation.shape[:-1], CL, dtype=torch.long)


def keep_lane(observation: torch.Tensor, members: torch.Tensor | None = None) -> torch.Tensor:
    return torch.full(observation.shape[:-1], KL, dtype=torch.long)


def test_a_branch_replays_its_road_bit_for_bit() -> None:
    sim = simulator()
    copies = sim.branch(1, 3)
    action = torch.tensor([KL, CL, KL])[: sim.n_cavs].expand(3, -1)
    for _ in range(5):
        ours = copies.step(action)
        theirs = sim.step(action[:2])
    assert torch.equal(ours.observation[0], theirs.observation[1])
    assert torch.equal(ours.observation[0], ours.observation[2])


def test_take_copies_several_roads_into_one_batch() -> None:
    sim = simulator()
    copies = sim.take(torch.tensor([1, 0, 1]))
    action = torch.tensor([KL, CL, KL])[: sim.n_cavs]
    for _ in range(5):
        ours = copies.step(action.expand(3, -1))
        theirs = sim.step(action.expand(2, -1))
    assert torch.equal(ours.observation[[1, 0, 2]], theirs.observation[[0, 1, 1]])
    assert not torch.equal(theirs.observation[0], theirs.observation[1])  # two roads differ
    with pytest.raises(ValueError, match=r"roads must be a non-empty list of indices in \[0, 1\]"):
        sim.take(torch.tensor([2]))


def test_values_are_the_rollouts_they_name() -> None:
    sim = simulator()
    values = simulated_game(sim, 0, change_left)
    n = sim.n_cavs
    keep = sim.branch(0, 1).rollout_returns(keep_lane)
    everyone = sim.branch(0, 1).rollout_returns(change_left)
    assert values.shape == (2**n,)
    assert float(values[0]) == pytest.approx(float(keep[0]))
    assert float(values[-1]) == pytest.approx(float(everyone[0]))
    phi = exact_shapley(values, n)
    assert float(phi.sum()) == pytest.approx(float(values[-1] - values[0]))


def test_a_policy_that_keeps_lane_is_a_null_game() -> None:
    values = simulated_game(simulator(), 1, keep_lane)
    assert torch.all(values == values[0])


def test_bad_agents_are_refused() -> None:
    sim = simulator()
    with pytest.raises(ValueError, match="distinct CAV indices"):
        simulated_game(sim, 0, change_left, agents=[0, 0])
    with pytest.raises(ValueError, match="must lie in"):
        simulated_game(sim, 0, change_left, agents=[sim.n_cavs])
    with pytest.raises(ValueError, match="road must be in"):
        sim.branch(5, 2)


def test_discounted_and_member_payoffs_are_the_rewards_they_name() -> None:
    sim = simulator()
    n = sim.n_cavs
    copy = sim.branch(0, 1)
    rewards = []
    while int(copy.state.get("steps")[0]) < int(copy.config["horizon"]):
        result = copy.step(torch.full((1, n), KL))
        rewards.append(result.reward[0].double())
        if bool(result.terminated[0] | result.truncated[0]):
            break
    rewards = torch.stack(rewards)  # [T, I]
    discounts = 0.9 ** torch.arange(rewards.shape[0], dtype=torch.float64)
    first_only = torch.zeros(1, n, dtype=torch.bool)
    first_only[0, 0] = True
    discounted = sim.branch(0, 1).rollout_returns(keep_lane, gamma=0.9, payoff=first_only)
    assert float(discounted[0]) == pytest.approx(float((discounts * rewards[:, 0]).sum()))
    with pytest.raises(ValueError, match="gamma must be in"):
        sim.rollout_returns(keep_lane, gamma=1.5)
    with pytest.raises(ValueError, match="payoff must have shape"):
        sim.rollout_returns(keep_lane, payoff=first_only)


def test_the_member_game_pays_members_only_and_plays_the_first_action() -> None:
    sim = simulator()
    n = sim.n_cavs
    first = torch.full((n,), CL)
    values = simulated_member_game(sim, 0, keep_lane, first, gamma=0.9)
    assert values.shape == (2**n,) and float(values[0]) == 0.0
    # everyone plays the same actions in every copy, so the game is additive: each CAV's
    # Shapley value is its own discounted return after the first lane change
    copy = sim.branch(0, 1)
    now = copy.step(first.unsqueeze(0)).reward[0].double()
    later = torch.stack(
        [
            copy.branch(0, 1).rollout_returns(keep_lane, gamma=0.9, payoff=one.unsqueeze(0))[0]
            for one in torch.eye(n, dtype=torch.bool)
        ]
    )
    own = torch.stack([values[1 << i] for i in range(n)])
    torch.testing.assert_close(own, now + 0.9 * later)
    phi = exact_shapley(values, n)
    torch.testing.assert_close(phi, own.to(phi.dtype))
    torch.testing.assert_close(values[-1], own.sum())
    with pytest.raises(ValueError, match="first_action must have shape"):
        simulated_member_game(sim, 0, keep_lane, first[:1], gamma=0.9)
