"""The coalition game of a freeway state by simulation: branching is exact, the game's values
are the rollouts they name, and its Shapley value is efficient."""

from __future__ import annotations

import pytest
import torch

from mapets_rl.envs import make_env
from mapets_rl.envs.freeway import CL, KL
from mapets_rl.envs.torch_freeway.simulator import BatchedFreeway
from mapets_rl.shapley.game import exact_shapley
from mapets_rl.shapley.simulated import simulated_game

CONFIG = {"n_vehicles": 12, "cav_ratio": 0.25, "ramp_fraction": 0.25, "spawn_length": 300.0}


def simulator(roads: int = 2) -> BatchedFreeway:
    config = make_env("freeway-merge", backend="torch", **CONFIG).config
    sim = BatchedFreeway(config, True, roads, dtype=torch.float64, seed=5)
    for _ in range(3):
        sim.step(torch.full((roads, sim.n_cavs), KL))
    return sim


def change_left(observation: torch.Tensor) -> torch.Tensor:
    return torch.full(observation.shape[:-1], CL, dtype=torch.long)


def test_a_branch_replays_its_road_bit_for_bit() -> None:
    sim = simulator()
    copies = sim.branch(1, 3)
    action = torch.tensor([KL, CL, KL])[: sim.n_cavs].expand(3, -1)
    for _ in range(5):
        ours = copies.step(action)
        theirs = sim.step(action[:2])
    assert torch.equal(ours.observation[0], theirs.observation[1])
    assert torch.equal(ours.observation[0], ours.observation[2])


def test_values_are_the_rollouts_they_name() -> None:
    sim = simulator()
    values = simulated_game(sim, 0, change_left)
    n = sim.n_cavs
    keep = sim.branch(0, 1).rollout_returns(lambda obs: torch.full(obs.shape[:-1], KL))
    everyone = sim.branch(0, 1).rollout_returns(change_left)
    assert values.shape == (2**n,)
    assert float(values[0]) == pytest.approx(float(keep[0]))
    assert float(values[-1]) == pytest.approx(float(everyone[0]))
    phi = exact_shapley(values, n)
    assert float(phi.sum()) == pytest.approx(float(values[-1] - values[0]))


def test_a_policy_that_keeps_lane_is_a_null_game() -> None:
    values = simulated_game(simulator(), 1, lambda obs: torch.full(obs.shape[:-1], KL))
    assert torch.all(values == values[0])


def test_bad_agents_are_refused() -> None:
    sim = simulator()
    with pytest.raises(ValueError, match="distinct CAV indices"):
        simulated_game(sim, 0, change_left, agents=[0, 0])
    with pytest.raises(ValueError, match="must lie in"):
        simulated_game(sim, 0, change_left, agents=[sim.n_cavs])
    with pytest.raises(ValueError, match="road must be in"):
        sim.branch(5, 2)
