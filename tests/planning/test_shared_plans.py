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
