"""benchmarks/planner_rules.py (issue 33): each rule on constructed observations (who becomes
whose leader, who goes first at the crossing, who must brake), the wrapper, and a tiny run that
resumes and refuses bad input before any episode."""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path
from types import ModuleType

import pytest
import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModuleBase

from mapets_rl.envs import FigureEightPlannerReward

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture
def rules(load_script: Callable[[str], ModuleType], monkeypatch) -> ModuleType:
    monkeypatch.syspath_prepend(str(ROOT / "benchmarks"))
    return load_script("benchmarks/planner_rules.py")


def two_lane_obs(rows: list[dict]) -> torch.Tensor:
    """``[I, 15]`` observations: v, lane position, own and other-lane leaders, crossing."""
    obs = torch.zeros(len(rows), 15)
    for i, r in enumerate(rows):
        obs[i, 0] = r.get("v", 8.0)
        obs[i, 3], obs[i, 5] = r.get("v_ahead", 8.0), r.get("gap", 40.0)
        obs[i, 7], obs[i, 8], obs[i, 9] = (
            r.get("cross", 75.0),
            r.get("conflict", 75.0),
            r.get("v_conflict", 0.0),
        )
        obs[i, 10] = r.get("lane", 0.0)
        obs[i, 11], obs[i, 13] = r.get("v_other", 8.0), r.get("gap_other", 40.0)
    return obs


def test_a_vehicle_between_lanes_occupies_both(rules: ModuleType) -> None:
    obs = two_lane_obs(
        [
            {"lane": 0.5, "gap": 30.0, "v_ahead": 5.0, "gap_other": 10.0, "v_other": 3.0},
            {"lane": 1.0, "gap": 20.0, "gap_other": 6.0, "v_other": 4.0},  # CAV 2 moves in
            {"lane": 0.4, "gap": 5.0, "gap_other": 50.0},  # between lanes, own leader nearer
            {"lane": 0.0, "gap": 20.0, "gap_other": 6.0},  # settled, other leader settled
        ]
    )
    neighbour = torch.full((4, 5), -1)
    neighbour[0, 3], neighbour[1, 3], neighbour[3, 3] = 3, 2, 1
    links = torch.ones(4, 4, dtype=torch.bool) & ~torch.eye(4, dtype=torch.bool)
    planned, slots, swap = rules.occupy_both_lanes(obs, neighbour, links)
    assert swap.tolist() == [True, True, False, False]
    torch.testing.assert_close(planned[:2, [3, 5]], torch.tensor([[3.0, 10.0], [4.0, 6.0]]))
    torch.testing.assert_close(planned[2:], obs[2:])
    assert slots[:, 0].tolist() == [3, 2, -1, -1]
    # CAV 1 does not hear CAV 2: it cannot know CAV 2 is moving over
    links[1, 2] = links[2, 1] = False
    assert rules.occupy_both_lanes(obs, neighbour, links)[2].tolist() == [True, False, False, False]


def test_the_nearer_linked_cav_goes_first_if_the_other_can_stop(rules: ModuleType) -> None:
    obs = two_lane_obs(
        [
            {"cross": 10.0, "conflict": 30.0, "v_conflict": 5.0},  # goes first
            {"cross": 30.0, "conflict": 10.0, "v_conflict": 8.0},  # yields
            {"cross": 10.0, "conflict": 12.0, "v_conflict": 13.0},  # the other cannot stop
            {"cross": 20.0, "conflict": 20.0, "v_conflict": 5.0},  # tie with CAV 4
            {"cross": 20.0, "conflict": 20.0, "v_conflict": 5.0},
        ]
    )
    neighbour = torch.full((5, 5), -1)
    neighbour[:, 2] = torch.tensor([1, 0, 1, 4, 3])
    links = torch.ones(5, 5, dtype=torch.bool) & ~torch.eye(5, dtype=torch.bool)
    planned, slots, go = rules.crossing_order(obs, neighbour, links, crossing_gap=6.0)
    assert go.tolist() == [True, False, False, True, False]
    assert planned[0, 8] == 75.0 and planned[0, 9] == 0.0 and slots[0, 2] == -1
    torch.testing.assert_close(planned[1], obs[1])
    assert slots[:, 2].tolist() == [-1, 0, 1, -1, 3]
    links[0, 1] = links[1, 0] = False  # a failed link: nobody goes first
    assert not rules.crossing_order(obs, neighbour, links, 6.0)[2][0]


def test_brake_inside_the_margin_while_closing(rules: ModuleType) -> None:
    obs = two_lane_obs(
        [
            {"v": 5.0, "v_ahead": 0.0, "gap": 1.5},  # inside 2 m, closing
            {"v": 1.0, "v_ahead": 3.0, "gap": 1.5},  # inside 2 m, opening: still every plan
            {"v": 6.0, "v_ahead": 3.0, "gap": 4.0},  # inside 2 + 0.5 * 6 = 5 m, closing
            {"v": 6.0, "v_ahead": 7.0, "gap": 4.0},  # inside 5 m, opening: free
        ]
    )
    reward = FigureEightPlannerReward(headway=0.5)
    assert reward.lost(obs).tolist() == [True, True, True, False]

    class Forward(TensorDictModuleBase):
        in_keys, out_keys = [("agents", "observation")], [("agents", "action")]

        def forward(self, td):
            return td.set(("agents", "action"), torch.tensor([[13.0, 1.0]]).expand(4, 2))

    policy = rules.RulePolicy(Forward(), "brake", reward)
    action = policy(TensorDict({"agents": {"observation": obs}}))["agents", "action"]
    assert action.tolist() == [[0.0, 0.0], [0.0, 0.0], [0.0, 0.0], [13.0, 1.0]]
    assert policy.applied == 3
    with pytest.raises(ValueError, match="rule must be one of"):
        rules.RulePolicy(Forward(), "yield", reward)


def test_tiny_run_resumes_and_refuses_bad_input(rules: ModuleType, tmp_path: Path) -> None:
    argv = ["--out", str(tmp_path), "--steps", "6", "--seeds", "0", "--headway", "0.5"]
    rows = rules.main([*argv, "--rules", "none", "brake"])
    assert sorted(r["rule"] for r in rows) == ["brake", "none"]
    assert all(0 <= r["safety"] <= 1 and r["applied"] >= 0 for r in rows)
    assert "| 0.5 | brake | 1 |" in (tmp_path / "rules.md").read_text()
    lines = (tmp_path / "rows.jsonl").read_text().splitlines()
    assert len(lines) == 2 and json.loads(lines[0])["tag"].startswith("oracle-shared")
    again = rules.main([*argv, "--rules", "none", "brake"])  # done: nothing is run again
    assert len((tmp_path / "rows.jsonl").read_text().splitlines()) == 2 and len(again) == 2
    for bad in (["--reward", "headway=1"], ["--env", "observation=paper"], ["--steps", "0"]):
        with pytest.raises(SystemExit):
            rules.main([*argv, *bad])
    assert len((tmp_path / "rows.jsonl").read_text().splitlines()) == 2


def test_recover_lifts_the_gap_just_outside_the_test_for_every_first_action(
    rules: ModuleType,
) -> None:
    """After ``recover``, neither braking nor full throttle is predicted to crash at the first
    step (the exact own-motion model), so the planner can choose; a CAV outside its margin
    plans with its observation as it is."""
    from mapets_rl.envs.figure_eight_kinematics import FigureEightKinematicModel

    obs = two_lane_obs(
        [
            {"v": 5.0, "v_ahead": 0.0, "gap": 1.5},
            {"v": 8.0, "v_ahead": 6.0, "gap": 4.0},
            {"v": 8.0, "v_ahead": 8.0, "gap": 30.0},
        ]
    )
    reward = FigureEightPlannerReward(headway=0.5)
    lifted = rules.recover_gap(obs, reward, dt=0.1)
    assert lifted[0, 5] > obs[0, 5] and lifted[1, 5] > obs[1, 5]
    torch.testing.assert_close(lifted[2], obs[2])
    torch.testing.assert_close(lifted[:, [0, 1, 2, 3, 4, 6]], obs[:, [0, 1, 2, 3, 4, 6]])
    model = FigureEightKinematicModel(n_agents=3, obs_dim=15, action_dim=2)
    for target in (0.0, 13.89):
        action = torch.tensor([[target, 0.0]]).expand(3, 2)
        before = reward.collision(obs, action, obs + model.predict(obs, action)[0])
        after = reward.collision(lifted, action, lifted + model.predict(lifted, action)[0])
        assert before[:2].all() and not after.any()
