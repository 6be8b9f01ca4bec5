"""benchmarks/safety_agility_frontier.py (issue 33): a tiny sweep of the oracle with and
without plan sharing gives one point per planner and margin setting with bootstrap intervals
and a figure; a second call finds its episodes done and runs none; the oracle with exact
futures (``oracle-exact``) records every rollout and its rollout 0 as the oracle-shared row,
the same as an oracle-shared episode; bad margins are refused before any episode."""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path
from types import ModuleType

import pytest

ROOT = Path(__file__).resolve().parents[2]
TINY = [
    "--scenario",
    "figure-eight",
    "--steps",
    "15",
    "--seeds",
    "0",
    "1",
    "--planner",
    "compile=false",
]


@pytest.fixture
def frontier(load_script: Callable[[str], ModuleType], monkeypatch) -> ModuleType:
    monkeypatch.syspath_prepend(str(ROOT / "benchmarks"))  # it imports multilane_diagnosis
    return load_script("benchmarks/safety_agility_frontier.py")


def test_points_intervals_figure_and_resume(frontier: ModuleType, tmp_path: Path) -> None:
    argv = [*TINY, "--policies", "oracle", "oracle-shared", "--headway", "0", "0.5"]
    points = frontier.main([*argv, "--out", str(tmp_path)])
    assert len(points) == 4 and all(p["seeds"] == 2 for p in points)
    for p in points:
        estimate, low, high = p["safety"]
        assert 0.0 <= low <= estimate <= high <= 1.0
    shared = [p for p in points if p["policy"] == "oracle-shared"]
    assert all(p["plan_messages"] > 0 for p in shared)
    assert (tmp_path / "frontier.png").stat().st_size > 0
    rows = (tmp_path / "rows.jsonl").read_text().splitlines()
    assert len(rows) == 8
    assert json.loads(rows[0])["scenario"] == "figure-eight horizon=15 | planner compile=false"
    frontier.main([*argv, "--out", str(tmp_path)])  # resumes: nothing left to run
    assert len((tmp_path / "rows.jsonl").read_text().splitlines()) == 8


def test_exact_futures_rollouts_and_the_shared_row_of_its_rollout_0(
    frontier: ModuleType, tmp_path: Path
) -> None:
    argv = [*TINY, "--policies", "oracle-shared", "oracle-exact", "--headway", "0.5"]
    points = frontier.main([*argv, "--replay-iterations", "2", "--out", str(tmp_path)])
    rows = [json.loads(line) for line in (tmp_path / "rows.jsonl").read_text().splitlines()]
    assert [r["policy"] for r in rows] == ["oracle-exact", "oracle-shared"] * 2  # none twice
    exact, shared = rows[0], rows[1]
    assert [r["policy"] for r in exact["rollouts"]] == ["oracle-shared", *["oracle-exact"] * 2]
    assert exact["replay_iterations"] == 2 and shared["from"] == "oracle-exact rollout 0"
    assert exact["safety"] == exact["rollouts"][-1]["safety"]
    assert exact["plans_used"] > 0 and exact["plan_messages"] == 0
    for rollout in exact["rollouts"]:
        assert 0.0 <= rollout["exact"] <= 1.0 and rollout["mae"] >= 0.0
    reward = frontier.FigureEightPlannerReward(headway=0.5)
    alone = frontier.run_episode(
        "oracle-shared", 0, 15, reward, "figure-eight", anchor_candidates=True,
        keep_best=True, compile=False,
    )  # fmt: skip
    assert (alone["safety"], alone["agility"]) == (shared["safety"], shared["agility"])
    point = next(p for p in points if p["policy"] == "oracle-exact")
    assert len(point["rollouts"]) == 3 and point["seeds"] == 2
    # another number of iterations is another experiment: run again, shared rows kept
    frontier.main([*argv, "--replay-iterations", "1", "--out", str(tmp_path)])
    rows = [json.loads(line) for line in (tmp_path / "rows.jsonl").read_text().splitlines()]
    assert [r["policy"] for r in rows[4:]] == ["oracle-exact"] * 2


@pytest.mark.parametrize(
    "bad",
    [
        ["--headway", "-1"],
        ["--lane-change-gap", "-2"],
        ["--env", "n_cavs=-1"],
        ["--replay-iterations", "0"],
    ],
)
def test_bad_settings_are_refused_before_any_episode(
    frontier: ModuleType, tmp_path: Path, bad: list[str]
) -> None:
    with pytest.raises(SystemExit):
        frontier.main([*TINY, *bad, "--out", str(tmp_path)])
    assert not (tmp_path / "rows.jsonl").exists()
