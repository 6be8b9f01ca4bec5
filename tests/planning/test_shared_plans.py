"""PlanSharingPlanner: a CAV that reads its leader's broadcast plan brakes for a braking the
constant-speed prediction cannot see; without the link it plans as before."""

from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict

from mapets_rl.envs import FigureEightPlannerReward
from mapets_rl.envs.figure_eight import neighbour_speed_columns
from mapets_rl.envs.figure_eight_kinematics import FigureEightKinematicModel
from mapets_rl.planning import TrajectorySamplingCEM
from mapets_rl.planning.shared_plans import PlanSharingPlanner


def make_planner() -> TrajectorySamplingCEM:
    reward = FigureEightPlannerReward(headway=0.0)
    return TrajectorySamplingCEM(
        FigureEightKinematicModel(n_agents=2, obs_dim=7, action_dim=1),
        reward.reward,
        0.0,
        13.89,
        termination_fn=reward.termination_fn,
        seed=0,
        horizon=20,
        population=64,
        elites=8,
        iterations=4,
        particles=1,
        propagation="expectation",
        optimizer="icem",
        anchor_candidates=True,
        keep_best=True,
    )


def scene(linked: bool) -> TensorDict:
    """CAV 1 drives 10 m/s, 14 m behind CAV 0 (10 m/s): nobody else in range."""
    obs = torch.tensor([[10.0, 0, 0, 0.0, 10.0, 75.0, 14.0], [10.0, 0, 0, 10.0, 0.0, 14.0, 75.0]])
    links = torch.tensor([[False, linked], [linked, False]])
    neighbour = torch.tensor([[-1.0, 1.0], [0.0, -1.0]])
    return TensorDict(
        {"agents": {"observation": obs, "neighbors": links, "info": {"neighbour_cav": neighbour},
                    "mask": torch.ones(2, dtype=torch.bool)}},
        batch_size=[],
    )  # fmt: skip


@pytest.mark.parametrize("linked", [True, False])
def test_follower_brakes_for_the_leaders_broadcast_braking(linked: bool) -> None:
    """CAV 0 broadcast last step that it stops within two steps. Its follower, 14 m behind at
    the same speed, reads that and brakes now (its first target speed 3 m/s or more below the
    constant-speed plan's); the constant-speed prediction sees no conflict and drives on. A
    failed link gives today's decision exactly."""
    sharing = PlanSharingPlanner(make_planner(), neighbour_speed_columns(7))
    alone = make_planner()
    constant = alone.plan(scene(linked)["agents", "observation"])
    constant_speeds = alone.expected_states(scene(linked)["agents", "observation"])[1, :, 0]
    sharing._plans = torch.tensor([[10.0, 10.0, 0.0] + [0.0] * 17, [10.0] * 20])
    action = sharing(scene(linked))["agents", "action"]
    assert constant_speeds.min() > 8.0  # drives on
    if linked:
        assert action[1, 0] < constant[1, 0] - 3.0
        assert sharing.plans_used == 2 and sharing.broadcasts == 2  # each reads the other
    else:
        torch.testing.assert_close(action, constant)
        torch.testing.assert_close(sharing._plans[1], constant_speeds)
        assert sharing.plans_used == 0 and sharing.broadcasts == 0
    assert sharing._plans.shape == (2, 20) and not torch.isnan(sharing._plans).any()


def test_reset_forgets_the_broadcasts() -> None:
    sharing = PlanSharingPlanner(make_planner(), neighbour_speed_columns(7))
    sharing(scene(True))
    sharing.reset()
    assert sharing._plans is None and sharing.planner.last_solution is None


def test_bad_columns_are_refused() -> None:
    with pytest.raises(ValueError, match="columns"):
        PlanSharingPlanner(make_planner(), (3, 40))


def test_an_overruled_cav_broadcasts_the_fallbacks_braking() -> None:
    """A fallback that brakes CAV 1: its action is the fallback's and its broadcast is the
    expected speeds of braking over the horizon (falling to 0), not the plan it did not
    follow; CAV 0, not overruled, broadcasts what it broadcasts without the fallback."""

    def brake_cav_1(obs: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        return torch.where(torch.tensor([[False], [True]]), torch.zeros_like(action), action)

    plain = PlanSharingPlanner(make_planner(), neighbour_speed_columns(7))
    braking = PlanSharingPlanner(make_planner(), neighbour_speed_columns(7), fallback=brake_cav_1)
    reference = plain(scene(True))["agents", "action"]
    action = braking(scene(True))["agents", "action"]
    assert action[1].tolist() == [0.0] and reference[1, 0] > 5.0
    torch.testing.assert_close(action[0], reference[0])
    torch.testing.assert_close(braking._plans[0], plain._plans[0])
    speeds = braking._plans[1]
    assert (speeds.diff() < 0).all() and speeds[-1] < 1.0 < 5.0 < plain._plans[1].min()
    obs = scene(True)["agents", "observation"]
    zeros = torch.zeros(2, 20, 1)
    with pytest.raises(ValueError, match="sequences must be shaped"):
        braking.planner.expected_states(obs, None, zeros[:, :5])
