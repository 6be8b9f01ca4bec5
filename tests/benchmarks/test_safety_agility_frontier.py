"""benchmarks/safety_agility_frontier.py (issue 33): a tiny sweep of the oracle with and
without plan sharing gives one point per planner and margin setting with bootstrap intervals
and a figure; a second call finds its episodes done and runs none; bad margins are refused
before any episode."""

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


@pytest.mark.parametrize(
    "bad", [["--headway", "-1"], ["--lane-change-gap", "-2"], ["--env", "n_cavs=-1"]]
)
def test_bad_settings_are_refused_before_any_episode(
    frontier: ModuleType, tmp_path: Path, bad: list[str]
) -> None:
    with pytest.raises(SystemExit):
        frontier.main([*TINY, *bad, "--out", str(tmp_path)])
    assert not (tmp_path / "rows.jsonl").exists()
