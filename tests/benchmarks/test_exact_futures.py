"""benchmarks/exact_futures.py (issue 33, ``oracle-exact``): the replayed schedule at step ``n``
holds exactly the recorded speeds of steps ``n + 1 .. n + H`` of each slot's CAV (NaN for
humans, empty slots and after the CAV stopped in the record); the planner wrapper replays the
right step in one batched call; the exactness count; and the env fact the replay rests on: a
CAV's own speed is what its observers see in the slot that names it."""

from __future__ import annotations

import math
from collections.abc import Callable
from pathlib import Path
from types import ModuleType, SimpleNamespace

import pytest
import torch
from tensordict import TensorDict

ROOT = Path(__file__).resolve().parents[2]
NAN = float("nan")


@pytest.fixture
def exact(load_script: Callable[[str], ModuleType], monkeypatch) -> ModuleType:
    monkeypatch.syspath_prepend(str(ROOT / "benchmarks"))
    return load_script("benchmarks/exact_futures.py")


def coded_record(steps: int, agents: int) -> torch.Tensor:
    """record[m, j] = 100 j + m: every entry names its CAV and time."""
    return 100.0 * torch.arange(agents).float() + torch.arange(steps + 1).float().unsqueeze(-1)


def test_slot_holds_the_slot_cavs_recorded_speeds_of_the_next_h_steps(exact) -> None:
    record = coded_record(7, 3)  # [T + 1 = 8, I = 3]
    # CAV 0: leader CAV 1, follower a human; CAV 1: leader CAV 2, follower CAV 0; CAV 2: nobody
    neighbour = torch.tensor([[1, -1], [2, 0], [-1, -1]])
    schedule, used = exact.replay_schedule(record, 2, neighbour, (3, 4), obs_dim=6, horizon=3)
    assert schedule.shape == (3, 3, 6)
    assert schedule[0, :, 3].tolist() == [103.0, 104.0, 105.0]  # CAV 1 at steps 3, 4, 5
    assert schedule[1, :, 3].tolist() == [203.0, 204.0, 205.0]
    assert schedule[1, :, 4].tolist() == [3.0, 4.0, 5.0]
    assert used.tolist() == [[True, False], [True, True], [False, False]]
    filled = torch.zeros(3, 3, 6, dtype=torch.bool)
    filled[0, :, 3] = filled[1, :, 3] = filled[1, :, 4] = True
    assert torch.isnan(schedule[~filled]).all()


def test_every_step_and_slot_against_a_loop(exact) -> None:
    generator = torch.Generator().manual_seed(0)
    steps, agents, slots, horizon = 30, 5, 4, 6
    record = torch.rand(steps + 1, agents, generator=generator) * 14
    record[20:, 3] = NAN  # CAV 3 crashed at step 20 of the recorded rollout
    columns = (3, 4, 9, 11)
    for n in range(steps):
        neighbour = torch.randint(-1, agents, (agents, slots), generator=generator)
        schedule, used = exact.replay_schedule(record, n, neighbour, columns, 15, horizon)
        for i in range(agents):
            for k, column in enumerate(columns):
                j = int(neighbour[i, k])
                want = [
                    NAN if j < 0 else float(record[min(n + t + 1, steps), j])
                    for t in range(horizon)
                ]
                got = schedule[i, :, column].tolist()
                assert all(
                    (math.isnan(w) and math.isnan(g)) or w == g
                    for w, g in zip(want, got, strict=True)
                ), (n, i, k)
                assert bool(used[i, k]) == any(not math.isnan(w) for w in want)


def test_past_the_record_the_last_row_holds_and_after_a_crash_the_model_predicts(exact) -> None:
    record = coded_record(7, 2)
    record[6:, 1] = NAN  # CAV 1 stopped driving at step 6
    neighbour = torch.tensor([[1], [0]])
    schedule, used = exact.replay_schedule(record, 4, neighbour, (3,), obs_dim=4, horizon=4)
    assert schedule[1, :, 3].tolist() == [5.0, 6.0, 7.0, 7.0]  # steps 5, 6, 7, then 7 held
    assert schedule[0, 0, 3] == 105.0 and torch.isnan(schedule[0, 1:, 3]).all()
    assert used.tolist() == [[True], [True]]
    schedule, used = exact.replay_schedule(record, 6, neighbour, (3,), obs_dim=4, horizon=2)
    assert used.tolist() == [[False], [True]] and torch.isnan(schedule[0]).all()


def test_mismatched_slots_are_refused(exact) -> None:
    with pytest.raises(ValueError, match="slots"):
        exact.replay_schedule(torch.zeros(3, 2), 0, torch.zeros(2, 2), (3,), 4, 2)


class RecordingPlanner:
    """What ExactFuturePlanner needs of a TrajectorySamplingCEM; keeps the schedules."""

    in_keys = [("agents", "observation")]
    out_keys = [("agents", "action")]
    is_init_key = "is_init"

    def __init__(self, agents: int, obs_dim: int, horizon: int) -> None:
        self.model = SimpleNamespace(obs_dim=obs_dim)
        self.config = SimpleNamespace(horizon=horizon)
        self.agents = agents
        self.calls: list[torch.Tensor | None] = []

    def reset(self) -> None:
        self.calls.clear()

    def plan(self, obs, is_init=None, schedule=None) -> torch.Tensor:
        self.calls.append(schedule)
        return torch.zeros(self.agents, 1)


def test_the_wrapper_replays_the_step_it_is_at_in_one_call(exact) -> None:
    record = coded_record(10, 3)
    planner = RecordingPlanner(3, 6, 4)
    policy = exact.ExactFuturePlanner(planner, (3, 4), record)
    neighbour = torch.tensor([[1.0, 2.0], [-1.0, 0.0], [0.0, 1.0]])
    td = TensorDict(
        {
            ("agents", "observation"): torch.zeros(3, 6),
            ("agents", "info", "neighbour_cav"): neighbour,
            ("agents", "mask"): torch.tensor([True, True, False]),  # CAV 2 crashed
        }
    )
    for _ in range(3):
        policy(td)
    assert len(planner.calls) == 3 and policy.step == 3
    want, _ = exact.replay_schedule(
        record, 2, torch.tensor([[1, 2], [-1, 0], [-1, -1]]), (3, 4), 6, 4
    )
    torch.testing.assert_close(planner.calls[2], want, equal_nan=True)
    assert planner.calls[2][0, :, 3].tolist() == [103.0, 104.0, 105.0, 106.0]
    schedule, senders = policy.last_schedule
    assert senders.tolist() == [[1, 2], [-1, 0], [-1, -1]]
    assert policy.plans_used == 3 * 3
    policy.reset()
    assert policy.step == 0 and policy.plans_used == 0
    exact.ExactFuturePlanner(planner, (3, 4))(td)  # no record: plans like the planner
    assert planner.calls[-1] is None


def test_exactness_of_a_replay_against_its_own_record_and_a_changed_one(exact) -> None:
    record = coded_record(10, 3)
    neighbour = torch.tensor([[1, -1], [2, 0], [-1, -1]])
    schedules = []
    for n in range(10):
        schedule, used = exact.replay_schedule(record, n, neighbour, (3, 4), 6, 3)
        schedules.append((n, schedule, torch.where(used, neighbour, -1)))
    same = exact.schedule_exactness(schedules, record, (3, 4))
    assert same["exact"] == 1.0 and same["mae"] == 0.0 and same["entries"] == 9.0
    assert same["compared"] == pytest.approx(1 - 3 * (1 + 2) / 90)  # none past the end
    changed = record.clone()
    changed[:, 2] += 0.5  # CAV 2 drove 0.5 m/s faster: a third of the entries are off
    other = exact.schedule_exactness(schedules, changed, (3, 4))
    assert other["exact"] == pytest.approx(2 / 3) and other["mae"] == pytest.approx(0.5 / 3)


def test_a_cavs_own_speed_is_what_its_observers_see_in_its_slot() -> None:
    """The replay records each CAV's own speed (column 0): the value that the CAVs observing
    it see in the speed column of the slot that names it."""
    from mapets_rl.envs import ScriptedCAVPolicy, make_env
    from mapets_rl.envs.figure_eight import neighbour_speed_columns

    env = make_env("figure-eight-multilane", seed=3, horizon=20)
    policy = ScriptedCAVPolicy(env)
    td = env.reset()
    columns = neighbour_speed_columns(td["agents", "observation"].shape[-1])
    checked = 0
    for _ in range(20):
        obs = td["agents", "observation"]
        neighbour = td["agents", "info", "neighbour_cav"].long()
        for k, column in enumerate(columns):
            rows = torch.nonzero(neighbour[:, k] >= 0).flatten()
            assert torch.equal(obs[rows, column], obs[neighbour[rows, k], 0])
            checked += len(rows)
        td = env.step(policy(td))
        if bool(td["next", "done"].all()):
            break
        td = td["next"]
    env.close()
    assert checked > 100


def test_a_replay_that_changes_nothing_is_exact_end_to_end(
    load_script: Callable[[str], ModuleType], monkeypatch
) -> None:
    """The time alignment through a real episode: a planner that is told the recorded speeds
    but ignores them drives the recorded rollout again, so every known speed it was told is
    the speed then driven (exact share 1, error 0)."""
    monkeypatch.syspath_prepend(str(ROOT / "benchmarks"))
    diagnosis = load_script("benchmarks/multilane_diagnosis.py")
    reward = diagnosis.FigureEightPlannerReward()
    args = (0, 25, reward, "figure-eight-multilane")
    _row, first = diagnosis.drive("oracle", *args, compile=False)
    plan = diagnosis.TrajectorySamplingCEM.plan
    monkeypatch.setattr(
        diagnosis.TrajectorySamplingCEM,
        "plan",
        lambda self, obs, is_init=None, schedule=None: plan(self, obs, is_init),
    )
    _row, again = diagnosis.drive("oracle-exact", *args, record=first["speeds"], compile=False)
    torch.testing.assert_close(again["speeds"], first["speeds"], equal_nan=True)
    columns = diagnosis.neighbour_speed_columns(again["obs_dim"])
    exactness = diagnosis.schedule_exactness(again["schedules"], again["speeds"], columns)
    assert len(again["schedules"]) == 25 and exactness["entries"] > 50
    assert exactness["exact"] == 1.0 and exactness["mae"] == 0.0


def test_windowed_replay_commits_one_episode_that_its_actions_drive_again(
    load_script: Callable[[str], ModuleType], monkeypatch
) -> None:
    """oracle-exact-windowed: windows of 8 steps, 2 replays each; the committed actions drive
    the committed speeds again (run_windowed checks it), its known speeds are scored against
    them, and its rollout 0 is the oracle-shared episode of the seed."""
    monkeypatch.syspath_prepend(str(ROOT / "benchmarks"))
    diagnosis = load_script("benchmarks/multilane_diagnosis.py")
    reward = diagnosis.FigureEightPlannerReward()
    row = diagnosis.run_episode(
        "oracle-exact-windowed", 0, 20, reward, "figure-eight", replay_iterations=2,
        replay_window=8, compile=False,
    )  # fmt: skip
    assert [r["policy"] for r in row["rollouts"]] == ["oracle-shared", "oracle-exact-windowed"]
    assert row["replay_window"] == 8 and row["replay_iterations"] == 2
    committed = row["rollouts"][1]
    assert committed["safety"] == row["safety"] and row["plans_used"] > 0
    assert 0.0 <= committed["exact"] <= 1.0 and committed["entries"] > 0
    shared = diagnosis.run_episode("oracle-shared", 0, 20, reward, "figure-eight", compile=False)
    assert shared["agility"] == row["rollouts"][0]["agility"]
