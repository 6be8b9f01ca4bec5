"""``compare`` writes the rliable protocol's performance profiles, optimality gaps and
probabilities of improvement (checked against values counted by hand), draws no interval below
three runs (two runs: their values as points), keeps a count's axis above zero and labels
speeds in m/s with a second axis in mph."""

from __future__ import annotations

import json
from pathlib import Path

import matplotlib.collections
import pytest

from mapets_rl.app.comparison import compare
from mapets_rl.app.rliable_report import gap_thresholds
from tests.cli_run import run_cli
from tests.experiment.test_results import fake_run


def _methods(tmp_path: Path, finals: dict[str, list[float]]) -> list[Path]:
    """One run per final return, ``recipe`` the method, each run evaluated at frames 100 and
    200 (the final value at 200; collisions 0 throughout)."""
    return [
        fake_run(
            tmp_path / f"{method}{seed}",
            method,
            seed,
            evaluations=[
                (100, {"return": 0.0, "collisions": 0.0}),
                (200, {"return": value, "collisions": 0.0}),
            ],
        )
        for method, values in finals.items()
        for seed, value in enumerate(values)
    ]


def test_probability_of_improvement_and_profiles_of_two_methods(
    tmp_path: Path, all_figures
) -> None:
    """X's final returns (1, 2, 3), Y's (2, 2, 0): of the 9 pairs X ends above Y in 5 (1 > 0,
    2 > 0, 3 > 2 twice, 3 > 0) and ties in 2 (2 = 2), so P(X > Y) = (5 + 2/2) / 9 = 2/3 and
    P(Y > X) = 1/3. Thresholds run from 0 to 3: above tau = 0 are all 3 runs of X and 2 of Y;
    above 1.5, 2 of each; above 3, none."""
    runs = _methods(tmp_path, {"x": [1.0, 2.0, 3.0], "y": [2.0, 2.0, 0.0]})
    out = compare(runs, tmp_path / "cmp", ["return"])
    report = json.loads(out["rliable"].read_text())["return"]
    pairs = {(p["x"], p["y"]): p for p in report["probability_of_improvement"]}
    assert set(pairs) == {("x", "y"), ("y", "x")}
    assert pairs["x", "y"]["p"] == pytest.approx(2 / 3)
    assert pairs["y", "x"]["p"] == pytest.approx(1 / 3)
    low, high = pairs["x", "y"]["ci95"]
    assert 0.0 <= low < 2 / 3 < high <= 1.0
    assert pairs["x", "y"]["n_x"] == pairs["x", "y"]["n_y"] == 3
    taus = report["taus"]
    assert len(taus) == 101 and taus[0] == 0.0 and taus[-1] == 3.0 and taus[50] == 1.5
    x, y = report["profiles"]["x"], report["profiles"]["y"]
    assert [x["fraction"][i] for i in (0, 50, 100)] == pytest.approx([1.0, 2 / 3, 0.0])
    assert [y["fraction"][i] for i in (0, 50, 100)] == pytest.approx([2 / 3, 2 / 3, 0.0])
    assert all(lo <= f <= hi for f, (lo, hi) in zip(x["fraction"], x["ci95"], strict=True))
    table = out["rliable_table"].read_text()
    assert "| x | 3 | 1 [1, 1] | " in table  # above tau = 0: every run of X, every replicate
    assert "| X \\ Y | x | y |" in table
    assert f"| x |  | 0.667 [{low:.3g}, {high:.3g}] |" in table
    assert "| y | 0.333 [" in table
    assert out["profiles_plot"].is_file()
    panel = all_figures[-1].axes[0]
    assert panel.get_ylim() == (0.0, 1.0) and len(panel.collections) == 2  # a band per method
    assert [line.get_label() for line in panel.get_lines()] == ["x (n=3)", "y (n=3)"]


def test_two_runs_show_their_points_and_no_interval(tmp_path: Path, all_figures) -> None:
    """Two seeds: the learning curve is their mean and each run's values as points, with no
    band; the rliable numbers stand without intervals (P(X > Y) with X = (1, 4), Y = (2, 3):
    2 of 4 pairs). One run: its line alone."""
    runs = _methods(tmp_path, {"x": [1.0, 4.0], "y": [2.0, 3.0]})
    out = compare(runs, tmp_path / "cmp", ["return", "collisions"])
    curves_fig = all_figures[0]
    (ax,) = [a for a in curves_fig.axes if a.get_title().startswith("return")]
    assert not [c for c in ax.collections if isinstance(c, matplotlib.collections.PolyCollection)]
    points = [c for c in ax.collections if isinstance(c, matplotlib.collections.PathCollection)]
    offsets = sorted(tuple(p) for c in points for p in c.get_offsets().tolist())
    assert offsets == sorted(
        [(100.0, 0.0)] * 4 + [(200.0, 1.0), (200.0, 4.0), (200.0, 2.0), (200.0, 3.0)]
    )
    title = " ".join(curves_fig.get_suptitle().split())  # wrapped
    assert "each run's values (points) for groups of 2" in title
    report = json.loads(out["rliable"].read_text())["return"]
    pairs = {(p["x"], p["y"]): p for p in report["probability_of_improvement"]}
    assert pairs["x", "y"]["p"] == pytest.approx(0.5) and pairs["x", "y"]["ci95"] is None
    assert report["profiles"]["x"]["ci95"] is None
    assert "| x |  | 0.5 |" in out["rliable_table"].read_text()
    one = _methods(tmp_path / "one", {"z": [5.0]})
    compare(one, tmp_path / "cmp1", ["return"])
    (ax,) = [a for a in all_figures[-2].axes if a.get_title().startswith("return")]
    assert not ax.collections and len(ax.get_lines()) == 1
    assert "Probability of improvement" not in (tmp_path / "cmp1" / "rliable.md").read_text()
    flat = json.loads(out["rliable"].read_text())  # collisions 0 in every run: one threshold
    assert flat["collisions"]["taus"] == [0.0]
    assert flat["collisions"]["profiles"]["x"]["fraction"] == [0.0]


def test_count_axes_stay_above_zero_and_speeds_read_m_per_s(tmp_path: Path, all_figures) -> None:
    """Collisions 0 in every run: the axis starts at 0, not below; a speed's title is
    'average_velocity [m/s]' (no 'x 2.237 = mph'), its mph on a second axis."""
    runs = [
        fake_run(
            tmp_path / f"r{s}",
            seed=s,
            evaluations=[(100, {"collisions": 0.0, "average_velocity": 20.0 + s})],
        )
        for s in range(3)
    ]
    compare(runs, tmp_path / "cmp", ["collisions", "average_velocity"])
    axes = {a.get_title(): a for a in all_figures[0].axes if a.get_title()}
    assert set(axes) == {"collisions [CAVs]", "average_velocity [m/s]"}
    assert axes["collisions [CAVs]"].get_ylim()[0] == 0.0
    speed = axes["average_velocity [m/s]"]
    (mph,) = [c for c in speed.child_axes if c.get_ylabel() == "mph"]
    low, high = speed.get_ylim()
    assert mph.get_ylim() == pytest.approx((low * 2.23694, high * 2.23694), rel=1e-4)


def test_the_optimality_gap_of_two_methods(tmp_path: Path, capsys) -> None:
    """gamma = 2.5 on the final returns: X's (1, 2, 3) fall short by 1.5, 0.5 and 0, a gap of
    2/3; Y's (2, 2, 0) by 0.5, 0.5 and 2.5, a gap of 7/6. collisions (range [0, inf)) has no
    gamma by default, safety's is 1 (the top of its range). The CLI takes --optimality-gap
    METRIC=GAMMA and refuses a metric not compared or a value that is no number."""
    runs = _methods(tmp_path, {"x": [1.0, 2.0, 3.0], "y": [2.0, 2.0, 0.0]})
    out = compare(
        runs, tmp_path / "cmp", ["return", "collisions"], optimality_thresholds={"return": 2.5}
    )
    report = json.loads(out["rliable"].read_text())
    gap = report["return"]["optimality_gap"]
    assert gap["gamma"] == 2.5
    x, y = gap["groups"]["x"], gap["groups"]["y"]
    assert x["gap"] == pytest.approx(2 / 3) and y["gap"] == pytest.approx(7 / 6)
    assert x["n"] == 3 and 0.0 <= x["ci95"][0] < 2 / 3 < x["ci95"][1] <= 1.5
    assert report["collisions"]["optimality_gap"] is None
    table = out["rliable_table"].read_text()
    assert "Optimality gap of return [per CAV] below gamma = 2.5" in table
    assert f"| x | 3 | 0.667 [{x['ci95'][0]:.3g}, {x['ci95'][1]:.3g}] |" in table
    assert "| y | 3 | 1.17 [" in table
    assert gap_thresholds(["safety", "return", "collisions"]) == {"safety": 1.0}
    two = _methods(tmp_path / "two", {"z": [1.0, 4.0]})
    out = compare(two, tmp_path / "cmp2", ["return"], optimality_thresholds={"return": 3.0})
    (row,) = json.loads(out["rliable"].read_text())["return"]["optimality_gap"]["groups"].values()
    assert row == {"n": 2, "gap": pytest.approx(1.0), "ci95": None}  # 2 and 0: no interval
    code, _, err = run_cli(
        ["compare", *map(str, runs), "--out", str(tmp_path / "cli"), "--metrics", "return",
         "--optimality-gap", "return=2.5"],
        capsys,
    )  # fmt: skip
    assert code == 0, err
    cli_gap = json.loads((tmp_path / "cli" / "rliable.json").read_text())["return"]
    assert cli_gap["optimality_gap"] == gap
    for bad, message in (
        ("return=high", "--optimality-gap must be METRIC=GAMMA"),
        ("safety=1", "optimality_thresholds names ['safety'], which are not compared"),
        ("return=inf", "optimality_thresholds['return'] must be a finite number"),
    ):
        code, _, err = run_cli(
            ["compare", *map(str, runs), "--out", str(tmp_path / "bad"), "--metrics", "return",
             "--optimality-gap", bad],
            capsys,
        )  # fmt: skip
        assert code == 2 and message in err, err
        assert not (tmp_path / "bad").exists()
