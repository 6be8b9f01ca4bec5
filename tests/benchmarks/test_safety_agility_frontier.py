"""benchmarks/safety_agility_frontier.py (issue 33): a tiny sweep of the oracle with and
without plan sharing gives one point per planner and margin setting with bootstrap intervals
and a figure; a second call finds its episodes done and runs none; bad margins are refused
before any episode; trained runs are one point per family of seeds."""

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
    monkeypatch.syspath_prepend(str(ROOT / "benchmarks"))  # it imports _common
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
    "bad",
    [
        ["--headway", "-1"],
        ["--lane-change-gap", "-2"],
        ["--env", "n_cavs=-1"],
    ],
)
def test_bad_settings_are_refused_before_any_episode(
    frontier: ModuleType, tmp_path: Path, bad: list[str]
) -> None:
    with pytest.raises(SystemExit):
        frontier.main([*TINY, *bad, "--out", str(tmp_path)])
    assert not (tmp_path / "rows.jsonl").exists()


def _fake_run(path: Path, recipe: str, env: str, safety: float, agility: float) -> Path:
    path.mkdir(parents=True)
    evaluation = {"frames": 6000, "metrics": {"safety": safety, "agility": agility}}
    first = {"frames": 400, "metrics": {"safety": 0.0, "agility": 0.0}}
    results = {"recipe": recipe, "env": env, "seed": 0, "config": {},
               "evaluations": [first, evaluation], "train": []}  # fmt: skip
    (path / "results.json").write_text(json.dumps(results))
    return path


def test_baselines_are_one_point_per_recipe_from_their_last_evaluation(
    frontier: ModuleType, tmp_path: Path
) -> None:
    runs = [
        _fake_run(tmp_path / f"mappo_seed{s}", "mappo", "figure-eight", 0.4 + 0.1 * s, 0.7)
        for s in range(3)
    ]
    runs.append(_fake_run(tmp_path / "sac_seed0", "sac", "figure-eight", 0.3, 1.1))
    mapets = tmp_path / "share100_s0"  # a MA-PETS run: training episodes, no evaluation
    mapets.mkdir()
    episodes = [
        {"frames": 400 * k, "metrics": {"safety": 0.1 * k, "agility": 0.4}} for k in range(1, 6)
    ]
    results = {"recipe": "mapets", "env": "figure-eight", "seed": 0, "config": {},
               "evaluations": [], "train": episodes}  # fmt: skip
    (mapets / "results.json").write_text(json.dumps(results))
    points = frontier.baseline_points([*runs, mapets], "figure-eight")
    assert [p["policy"] for p in points] == ["mappo", "sac", "share100"]
    assert points[2]["safety"][0] == pytest.approx(0.4)  # episodes 3-5 of 5
    assert points[2]["frames"] == [2000]
    mappo = points[0]
    assert mappo["seeds"] == 3 and mappo["frames"] == [6000] * 3
    assert mappo["safety"][0] == pytest.approx(0.5)  # the last evaluations, not the first
    assert mappo["safety"][1] <= 0.5 <= mappo["safety"][2]
    assert mappo["agility"][0] == pytest.approx(0.7)
    other = _fake_run(tmp_path / "two_lanes", "mappo", "figure-eight-multilane", 0.5, 0.7)
    with pytest.raises(SystemExit):  # a run of another road is refused before any episode
        frontier.main([*TINY, "--baselines", str(other), "--out", str(tmp_path / "out")])
    assert not (tmp_path / "out").exists()
