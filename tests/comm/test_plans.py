"""plan_schedule: a neighbour's broadcast plan, shifted by one step, lands in the receiver's
slot column; humans, failed links and missing plans leave the model's prediction (NaN)."""

from __future__ import annotations

import torch

from mapets_rl.comm.plans import plan_schedule


def test_a_linked_cav_plan_fills_the_slot_shifted_by_one_step() -> None:
    # CAV 1 follows CAV 0 (slot 0: leader); CAV 0's follower is CAV 1 (slot 1)
    plans = torch.tensor([[10.0, 9.0, 8.0, 7.0], [5.0, 6.0, 7.0, 8.0]])  # [I=2, H=4]
    neighbour = torch.tensor([[-1, 1], [0, -1]])
    links = torch.tensor([[False, True], [True, False]])
    schedule, used = plan_schedule(plans, neighbour, links, (3, 4), obs_dim=7)
    assert schedule.shape == (2, 4, 7)
    # receiver 1 reads its leader 0's plan from index 1 on, the last value held
    assert schedule[1, :, 3].tolist() == [9.0, 8.0, 7.0, 7.0]
    assert schedule[0, :, 4].tolist() == [6.0, 7.0, 8.0, 8.0]
    assert used.tolist() == [[False, True], [True, False]]
    others = torch.ones(2, 4, 7, dtype=torch.bool)
    others[1, :, 3] = others[0, :, 4] = False
    assert torch.isnan(schedule[others]).all()


def test_failed_links_humans_and_missing_plans_leave_the_prediction() -> None:
    plans = torch.tensor([[10.0, 9.0], [float("nan")] * 2, [4.0, 3.0]])
    neighbour = torch.tensor([[1, 2], [0, -1], [-1, -1]])
    links = torch.ones(3, 3, dtype=torch.bool) & ~torch.eye(3, dtype=torch.bool)
    links[0, 2] = links[2, 0] = False  # the link 0-2 failed
    schedule, used = plan_schedule(plans, neighbour, links, (3, 4), obs_dim=5)
    # 0's leader 1 has no plan, its follower 2 is out of reach; 1 hears its leader 0
    assert used.tolist() == [[False, False], [True, False], [False, False]]
    assert torch.isnan(schedule[0]).all() and torch.isnan(schedule[2]).all()
    assert schedule[1, :, 3].tolist() == [9.0, 9.0]


def test_batched_roads_are_independent() -> None:
    plans = torch.stack([torch.full((2, 3), 1.0), torch.full((2, 3), 2.0)])  # [B=2, I, H]
    neighbour = torch.tensor([[[1.0], [-1.0]], [[1.0], [-1.0]]])  # floats are rounded
    links = torch.tensor([[[False, True], [True, False]], [[False, False], [False, False]]])
    schedule, used = plan_schedule(plans, neighbour, links, (3,), obs_dim=4)
    assert used[..., 0].tolist() == [[True, False], [False, False]]
    assert schedule[0, 0, :, 3].tolist() == [1.0, 1.0, 1.0]
    assert torch.isnan(schedule[1]).all()
