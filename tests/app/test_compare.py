"""``compare`` cannot silently mislead: the source of every curve (deterministic evaluations
or training entries) is stated, runs on different scenarios are refused unless allowed,
``group_by`` splits a sweep into groups and ``x`` lines up episodes."""

from __future__ import annotations

import json
import logging
from pathlib import Path

import pytest

from mapets_rl.app.cli import main as cli_main
from mapets_rl.app.comparison import compare
from mapets_rl.metrics import metric_range
from mapets_rl.statistics import bootstrap_interval
from tests.cli_run import run_cli
from tests.experiment.test_results import ENV_CONFIG, eval_entries, fake_run, train_entries


# ------------------------------------------------------------------------------- sources
def test_default_source_falls_back_to_training_entries_and_says_so(tmp_path: Path, caplog) -> None:
    """MA-PETS (no ``eval_interval``: it evaluates on request only) falls back quietly, with a
    note; a run whose recipe evaluates during training but has not yet gets a warning."""
    runs = [
        fake_run(tmp_path / f"mapets{s}", "mapets", s, train=train_entries(0.2, 0.4))
        for s in (0, 1)
    ]
    runs += [
        fake_run(tmp_path / f"mappo{s}", "mappo", s, evaluations=eval_entries(1.0, 2.0))
        for s in (0, 1)
    ]
    with caplog.at_level(logging.INFO, logger="mapets_rl"):
        out = compare(runs, tmp_path / "cmp", ["safety"])
    assert not [r for r in caplog.records if r.levelno >= logging.WARNING]
    assert any(
        "training entries (the recipe evaluates on request only" in r.getMessage()
        and str(runs[0]) in r.getMessage()
        for r in caplog.records
    )
    early = fake_run(tmp_path / "early", "mappo", 2, eval_interval=100, train=train_entries(0.2))
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="mapets_rl"):
        compare([early], tmp_path / "cmp_early", ["safety"])
    assert any(
        "no evaluations; comparing their training entries instead" in r.getMessage()
        and str(early) in r.getMessage()
        for r in caplog.records
    )
    summary = json.loads(out["summary"].read_text())
    assert set(summary) == {"mapets (train)", "mappo (eval)"}
    assert summary["mapets (train)"]["safety"]["source"] == "train"
    assert summary["mappo (eval)"]["safety"]["source"] == "eval"
    table = out["table"].read_text()
    assert table.startswith(
        "Last entry of each run: deterministic evaluations, training "
        "entries for the groups marked (train);"
    )
    assert "| mapets (train) | training entries |" in table
    assert "| mappo (eval) | deterministic evaluations |" in table


def test_source_train_compares_training_entries_only(tmp_path: Path) -> None:
    run = fake_run(tmp_path / "both", train=train_entries(0.2, 0.4), evaluations=eval_entries(9.0))
    out = compare([run], tmp_path / "cmp", ["safety"], source="train")
    assert json.loads(out["summary"].read_text())["toy"]["safety"]["mean"] == 0.4
    assert out["table"].read_text().startswith("Last entry of each run: training entries;")
    out = compare([run], tmp_path / "cmp2", ["safety"])
    assert json.loads(out["summary"].read_text())["toy"]["safety"]["mean"] == 0.5
    evals_only = fake_run(tmp_path / "evals", evaluations=eval_entries(1.0))
    with pytest.raises(ValueError, match="has no training entries"):
        compare([run, evals_only], tmp_path / "cmp3", source="train")
    assert not (tmp_path / "cmp3").exists()


def test_old_mapets_results_can_be_read_as_training_entries(tmp_path: Path, caplog) -> None:
    run = tmp_path / "old"
    run.mkdir()
    (run / "results.json").write_text(
        json.dumps(
            {
                "recipe": "mapets",
                "env": "figure-eight",
                "seed": 0,
                "config": {"env_config": ENV_CONFIG},
                "evaluations": [{"frames": 21, "metrics": {"episode": 1.0, "safety": 0.3}}],
            }
        )
    )
    with caplog.at_level(logging.WARNING, logger="mapets_rl"):
        out = compare([run], tmp_path / "cmp", source="train", legacy_as="train")
    assert any("predates the split" in r.getMessage() for r in caplog.records)
    assert json.loads(out["summary"].read_text())["mapets"]["safety"]["source"] == "train"


def _write_evaluation(run: Path, frames: int, metrics: dict[str, float]) -> None:
    """``evaluation.json`` as ``mapets-rl evaluate`` writes it."""
    (run / "evaluation.json").write_text(
        json.dumps({"frames": frames, "episodes": 10, "metrics": metrics})
    )


def test_the_table_compares_the_final_evaluations_of_mapets_evaluate(
    tmp_path: Path, caplog
) -> None:
    """MA-PETS runs with evaluate's output: the curves are their training episodes, the table
    their final evaluations, without a warning; a group where one run lacks it (or holds an
    older one) compares the last entries."""
    runs = [
        fake_run(tmp_path / f"mapets{s}", "mapets", s, train=train_entries(0.2, 0.4 + 0.2 * s))
        for s in (0, 1, 2)
    ]
    for seed, run in enumerate(runs):
        _write_evaluation(run, 41, {"safety": 0.9 + 0.05 * seed, "return": 9.0})
    with caplog.at_level(logging.WARNING, logger="mapets_rl"):
        out = compare(runs, tmp_path / "cmp", ["safety"])
    assert not caplog.records
    summary = json.loads(out["summary"].read_text())["mapets"]["safety"]
    assert summary["source"] == "evaluate" and summary["mean"] == pytest.approx(0.95)
    assert summary["n"] == 3 and summary["frames"] == 41
    table = out["table"].read_text()
    assert "or its final evaluation (evaluation.json, written by mapets-rl evaluate)" in table
    assert "| mapets | final evaluations (evaluate) | 41 | 0.95 [0.9, 1] (n=3) |" in table
    curves = json.loads(out["curves"].read_text())["groups"]["mapets"]
    assert curves["source"] == "train"
    assert curves["metrics"]["safety"]["mean"] == pytest.approx([0.2, 0.6])
    (runs[2] / "evaluation.json").unlink()
    _write_evaluation(runs[1], 20, {"safety": 0.0})  # evaluated before the last episode
    out = compare(runs, tmp_path / "cmp2", ["safety"])
    summary = json.loads(out["summary"].read_text())["mapets"]["safety"]
    assert summary["source"] == "train" and summary["mean"] == pytest.approx(0.6)
    (runs[0] / "evaluation.json").write_text('{"frames": 41}')
    with pytest.raises(ValueError, match="evaluation.json' is not an evaluation file"):
        compare(runs, tmp_path / "cmp3", ["safety"])
    assert not (tmp_path / "cmp3").exists()


def test_marl_eval_export(tmp_path: Path) -> None:
    """marl-eval's raw-data layout: env, task (env_config keys off the scenario's defaults),
    algorithm (the group), runs, steps with their frames, absolute metrics from evaluate's
    output or the last entry."""
    runs = [
        fake_run(
            tmp_path / f"d{d}_{s}",
            "mapets",
            s,
            comm={"comm_range": d},
            train=train_entries(0.1 * s, 0.5),
        )
        for d in (0, 100)
        for s in (0, 1)
    ]
    _write_evaluation(runs[0], 41, {"safety": 0.8, "return": 8.0})
    out = compare(runs, tmp_path / "cmp", ["safety", "return"], group_by="comm.comm_range")
    assert "marl_eval" not in out and not (tmp_path / "cmp" / "marl_eval.json").exists()
    out = compare(runs, tmp_path / "cmp2", ["safety"], group_by="comm.comm_range", marl_eval=True)
    data = json.loads(out["marl_eval"].read_text())
    assert list(data) == ["figure-eight"]
    assert list(data["figure-eight"]) == ["horizon=20,n_cavs=4"]  # 8 CAVs, 200 steps by default
    algorithms = data["figure-eight"]["horizon=20,n_cavs=4"]
    assert list(algorithms) == ["mapets comm.comm_range=0", "mapets comm.comm_range=100"]
    assert list(algorithms["mapets comm.comm_range=0"]) == ["run_0", "run_1"]
    run_0 = algorithms["mapets comm.comm_range=0"]["run_0"]
    assert run_0 == {
        "step_0": {"step_count": 20, "safety": [0.0]},
        "step_1": {"step_count": 41, "safety": [0.5]},
        "absolute_metrics": {"safety": [0.8]},  # evaluate's output
    }
    run_1 = algorithms["mapets comm.comm_range=0"]["run_1"]
    assert run_1["absolute_metrics"] == {"safety": [0.5]}  # the last entry
    assert list(run_1)[-1] == "absolute_metrics"  # marl-eval reads it as the last key
    argv = ["compare", *map(str, runs), "--out", str(tmp_path / "cli"), "--metrics", "safety"]
    argv += ["--group-by", "comm.comm_range"]
    assert cli_main([*argv, "--marl-eval"]) == 0
    assert json.loads((tmp_path / "cli" / "marl_eval.json").read_text()) == data


# ----------------------------------------------------------------------------- scenarios
def test_runs_on_different_scenarios_are_refused(tmp_path: Path) -> None:
    a = fake_run(tmp_path / "a", evaluations=eval_entries(1.0))
    b = fake_run(
        tmp_path / "b",
        seed=1,
        env_config={"n_cavs": 8, "horizon": 20},
        evaluations=eval_entries(2.0),
    )
    c = fake_run(
        tmp_path / "c",
        seed=2,
        env="freeway",
        env_config={"horizon": 20},
        evaluations=eval_entries(3.0),
    )
    d = fake_run(
        tmp_path / "d",
        seed=3,
        env="freeway",
        env_config={"horizon": 20},
        evaluations=eval_entries(3.0),
    )
    with pytest.raises(ValueError) as err:
        compare([a, b, c, d], tmp_path / "cmp")
    message = str(err.value)
    assert "\n" not in message and "allow_mixed_env" in message
    # one short line naming the scenarios: the freeway's other keys are not listed one by one
    assert message == (
        f"the runs are on different scenarios: figure-eight, n_cavs=4 (run {a}), "
        f"figure-eight, n_cavs=8 (run {b}), freeway (run {c} and 1 more); pass "
        "allow_mixed_env=True (--allow-mixed-env) to compare them anyway, or group_by the "
        "keys that differ (env, env_config.n_cavs)"
    )
    assert not (tmp_path / "cmp").exists()


def test_a_key_set_to_its_scenario_default_equals_the_key_left_unset(tmp_path: Path) -> None:
    """Two-lane runs that spell out the scenario's defaults (22 CAVs, 400 steps) compare
    with runs that leave them unset; a value that differs from the default is still refused."""
    unset = fake_run(
        tmp_path / "a", env="figure-eight-multilane", env_config={}, evaluations=eval_entries(1.0)
    )
    spelled = fake_run(
        tmp_path / "b",
        seed=1,
        env="figure-eight-multilane",
        env_config={"n_cavs": 22, "horizon": 400, "observation": "crossing"},
        evaluations=eval_entries(2.0),
    )
    compare([unset, spelled], tmp_path / "cmp", ["return"])
    other = fake_run(
        tmp_path / "c",
        seed=2,
        env="figure-eight-multilane",
        env_config={"n_cavs": 20},
        evaluations=eval_entries(3.0),
    )
    with pytest.raises(ValueError, match=r"figure-eight-multilane, n_cavs=22 .* n_cavs=20"):
        compare([unset, other], tmp_path / "cmp2", ["return"])


def test_allow_mixed_env_warns_and_labels_groups_with_their_scenario(
    tmp_path: Path, caplog
) -> None:
    a = fake_run(tmp_path / "a", evaluations=eval_entries(1.0))
    b = fake_run(
        tmp_path / "b",
        seed=1,
        env_config={"n_cavs": 8, "horizon": 20},
        evaluations=eval_entries(2.0),
    )
    with caplog.at_level(logging.WARNING, logger="mapets_rl"):
        out = compare([a, b], tmp_path / "cmp", ["return"], allow_mixed_env=True)
    assert any(
        "different scenarios" in r.getMessage() and "n_cavs=8" in r.getMessage()
        for r in caplog.records
    )
    summary = json.loads(out["summary"].read_text())
    assert summary["toy [n_cavs=4]"]["return"]["mean"] == 1.0
    assert summary["toy [n_cavs=8]"]["return"]["mean"] == 2.0


# ------------------------------------------------------------------------------ group_by
def test_group_by_splits_a_sweep_with_bands_per_value(tmp_path: Path) -> None:
    runs = []
    for d, returns in ((100.0, [(1.0, 3.0), (2.0, 5.0)]), (0.0, [(0.0, 1.0), (0.5, 1.5)])):
        for seed, values in enumerate(returns):
            runs.append(
                fake_run(
                    tmp_path / f"d{d:g}_seed{seed}",
                    seed=seed,
                    comm_range=d,
                    evaluations=eval_entries(*values),
                )
            )
    out = compare(runs, tmp_path / "cmp", ["return"], group_by="comm_range")
    curves = json.loads(out["curves"].read_text())["groups"]
    assert list(curves) == ["toy comm_range=100", "toy comm_range=0"]
    d100 = curves["toy comm_range=100"]
    assert d100["group"] == {"comm_range": 100.0} and d100["x"] == [100, 200]
    assert d100["n"] == [2, 2]
    assert d100["metrics"]["return"]["mean"][1] == pytest.approx(4.0)
    assert d100["metrics"]["return"]["mean_ci95"] == [None, None]  # two runs: no interval
    assert d100["metrics"]["return"]["std"][1] == pytest.approx(2**0.5)
    with pytest.raises(ValueError, match="group_by field 'nope' is not in the config"):
        compare(runs, tmp_path / "cmp2", group_by="nope")


def test_group_by_splits_the_recipes_that_have_the_field_and_keeps_the_others_whole(
    tmp_path: Path,
) -> None:
    """MA-PETS by communication range beside a baseline without one (paper Figs. 3-4)."""
    runs = [
        fake_run(
            tmp_path / f"mapets_d{d}_{s}",
            "mapets",
            s,
            train=train_entries(0.1 * s, 0.2),
            comm={"comm_range": d},
        )
        for d in (0, 100)
        for s in (0, 1)
    ]
    runs += [
        fake_run(tmp_path / f"mappo{s}", "mappo", s, evaluations=eval_entries(1.0, 2.0))
        for s in (0, 1)
    ]
    out = compare(runs, tmp_path / "cmp", ["return"], group_by="comm.comm_range")
    groups = json.loads(out["curves"].read_text())["groups"]
    assert sorted(groups) == [
        "mapets comm.comm_range=0 (train)",
        "mapets comm.comm_range=100 (train)",
        "mappo (eval)",
    ]
    assert groups["mappo (eval)"]["group"] == {} and len(groups["mappo (eval)"]["runs"]) == 2
    partial = fake_run(tmp_path / "mapets_flat", "mapets", 2, train=train_entries(0.1, 0.2))
    with pytest.raises(ValueError, match="other mapets runs have it"):
        compare([*runs, partial], tmp_path / "cmp2", group_by="comm.comm_range")
    assert not (tmp_path / "cmp2").exists()


def test_x_grid_lines_up_runs_that_log_at_different_frames(tmp_path: Path) -> None:
    """Episodes that end early (190, 370 frames) share a curve with runs logged every 200."""
    ragged = fake_run(
        tmp_path / "a",
        "mapets",
        0,
        train=[(190, {"safety": 0.2}), (370, {"safety": 0.4}), (570, {"safety": 0.6})],
    )
    regular = fake_run(
        tmp_path / "b",
        "mapets",
        1,
        train=[(200, {"safety": 0.4}), (400, {"safety": 0.6}), (600, {"safety": 0.8})],
    )
    plain = compare([ragged, regular], tmp_path / "plain", ["safety"], source="train")
    assert json.loads(plain["curves"].read_text())["groups"]["mapets"]["n"] == [1] * 6
    out = compare([ragged, regular], tmp_path / "grid", ["safety"], source="train", x_grid=200)
    group = json.loads(out["curves"].read_text())["groups"]["mapets"]
    assert group["x"] == [200, 400, 600] and group["n"] == [2, 2, 2]
    assert group["metrics"]["safety"]["mean"] == pytest.approx([0.3, 0.5, 0.7])
    for bad in (0, -1.0, float("nan")):
        with pytest.raises(ValueError, match="x_grid must be a finite number > 0"):
            compare([ragged], tmp_path / "bad", x_grid=bad)


def test_group_by_an_env_config_field_exempts_it_from_the_scenario_check(tmp_path: Path) -> None:
    runs = [
        fake_run(
            tmp_path / f"{obs}",
            env_config={**ENV_CONFIG, "observation": obs},
            evaluations=eval_entries(1.0),
        )
        for obs in ("paper", "crossing")
    ]
    with pytest.raises(ValueError, match="env_config.observation"):
        compare(runs, tmp_path / "cmp")
    out = compare(runs, tmp_path / "cmp", group_by=["env_config.observation"])
    assert set(json.loads(out["summary"].read_text())) == {
        "toy env_config.observation=paper",
        "toy env_config.observation=crossing",
    }


def test_x_episode_lines_up_episodes_of_different_lengths(tmp_path: Path) -> None:
    runs = [
        fake_run(tmp_path / "s0", train=train_entries(0.2, 0.4, 0.6, length=20)),
        fake_run(tmp_path / "s1", seed=1, train=train_entries(0.4, 0.8, length=30)),
    ]
    out = compare(runs, tmp_path / "cmp", ["safety"], source="train", x="episode")
    group = json.loads(out["curves"].read_text())["groups"]["toy"]
    assert group["x"] == [1.0, 2.0, 3.0] and group["n"] == [2, 2, 1]
    assert group["metrics"]["safety"]["mean"] == pytest.approx([0.3, 0.6, 0.6])
    with pytest.raises(ValueError, match="x 'nope' is not a metric of every compared entry"):
        compare(runs, tmp_path / "cmp2", source="train", x="nope")


# ----------------------------------------------------------------------------------- CLI
def test_cli_compare_options(tmp_path: Path, capsys) -> None:
    runs = [
        str(
            fake_run(
                tmp_path / f"d{d}_seed{s}",
                "mapets",
                s,
                comm_range=float(d),
                train=train_entries(0.1 * s, 0.2 + d / 1000),
            )
        )
        for d in (0, 100)
        for s in (0, 1)
    ]
    code, out, err = run_cli(
        [
            "compare",
            *runs,
            "--out",
            str(tmp_path / "cmp"),
            "--source",
            "train",
            "--group-by",
            "comm_range",
            "--x",
            "episode",
        ],
        capsys,
    )
    assert code == 0, err
    assert "| mapets comm_range=0 | training entries |" in out
    assert "| mapets comm_range=100 | training entries |" in out

    other = str(
        fake_run(
            tmp_path / "n8",
            "mapets",
            2,
            env_config={"n_cavs": 8, "horizon": 20},
            train=train_entries(0.5),
        )
    )
    code, _, err = run_cli(["compare", runs[0], other, "--out", str(tmp_path / "cmp2")], capsys)
    assert code == 2 and err.count("\n") == 1 and "env_config.n_cavs" in err
    assert err.startswith("mapets-rl: error: the runs are on different scenarios")
    code, out, err = run_cli(
        ["compare", runs[0], other, "--out", str(tmp_path / "cmp3"), "--allow-mixed-env"], capsys
    )
    assert code == 0
    assert "mapets-rl: warning: comparing runs on different scenarios" in err
    assert "no evaluations" not in err  # MA-PETS evaluates on request only
    assert "| mapets [n_cavs=4] | training entries |" in out
    code, _, err = run_cli(
        ["compare", runs[0], "--out", str(tmp_path / "cmp4"), "--group-by", ","], capsys
    )
    assert code == 2 and "--group-by must name at least one config field" in err


# ------------------------------------------------------------------ what a researcher reads
def _panels(fig) -> dict[str, object]:
    """Metric name (the panel title up to its unit) -> the visible axes of that panel."""
    return {ax.get_title().split(" [")[0]: ax for ax in fig.axes if ax.get_visible()}


def _band_ys(ax) -> list[float]:
    """The y values of the vertices of every shaded band (``fill_between``) of ``ax``."""
    return [
        float(y)
        for coll in ax.collections
        for path in coll.get_paths()
        for y in path.vertices[:, 1]
    ]


def test_a_single_run_shows_n_1_and_no_interval(tmp_path: Path, figures) -> None:
    run = fake_run(
        tmp_path / "one",
        evaluations=[
            (100, {"return": 1.0, "average_velocity": 20.0}),
            (200, {"return": 2.0, "average_velocity": 22.0}),
        ],
    )
    out = compare([run], tmp_path / "cmp")
    table = out["table"].read_text()
    assert "| toy | deterministic evaluations | 200 | 22 (49.21 mph) (n=1) | 2 (n=1) |" in table
    assert "[" not in table.splitlines()[-1]
    summary = json.loads(out["summary"].read_text())["toy"]["return"]
    assert summary["n"] == 1 and summary["mean_ci95"] is None and summary["iqm_ci95"] is None
    curves = json.loads(out["curves"].read_text())["groups"]["toy"]["metrics"]["return"]
    assert curves["mean_ci95"] == [None, None] and curves["std"] == [None, None]
    (fig,) = figures
    assert all(not ax.collections for ax in fig.axes)  # no band
    assert [line.get_label() for line in fig.axes[0].get_lines()] == ["toy (n=1)"]


@pytest.mark.parametrize(
    ("returns", "mean_cell", "iqm_cell"),
    [
        ([4.0], "4 (n=1)", "4 (n=1)"),
        ([1.0, 4.0], "2.5 {{1, 4}} (n=2)", "2.5 {{1, 4}} (n=2)"),
        (
            [1.0, 4.0, 7.0],
            "4 [{low:.4g}, {high:.4g}] (n=3)",
            "4 [{iqm_low:.4g}, {iqm_high:.4g}] (n=3)",
        ),
    ],
)
def test_the_tables_give_an_interval_from_three_runs_and_each_runs_value_below(
    tmp_path: Path, returns: list[float], mean_cell: str, iqm_cell: str
) -> None:
    """Final returns 4 / (1, 4) / (1, 4, 7): one run shows its value, two their mean (2.5; the
    IQM of fewer than 4 runs is their mean) and each run's value in braces with no interval,
    three the mean 4 with its bootstrap interval (that of bootstrap_interval); summary.json
    agrees (intervals null below 3 runs, each run's value listed)."""
    runs = [
        fake_run(tmp_path / f"s{seed}", seed=seed, evaluations=eval_entries(0.0, value))
        for seed, value in enumerate(returns)
    ]
    out = compare(runs, tmp_path / "cmp", ["return"])
    low, high = bootstrap_interval(returns)[1:]
    iqm_low, iqm_high = bootstrap_interval(returns, statistic="iqm")[1:]
    known = {"low": low, "high": high, "iqm_low": iqm_low, "iqm_high": iqm_high}
    table = out["table"].read_text()
    rows = [line for line in table.splitlines() if line.startswith("| toy |")]
    assert rows == [
        f"| toy | deterministic evaluations | 200 | {mean_cell.format(**known)} |",
        f"| toy | deterministic evaluations | 200 | {iqm_cell.format(**known)} |",
    ]
    assert ("in braces" in table.splitlines()[0]) == (len(returns) == 2)
    summary = json.loads(out["summary"].read_text())["toy"]["return"]
    assert summary["values"] == returns and summary["n"] == len(returns)
    banded = len(returns) >= 3
    assert (summary["mean_ci95"] is not None) == banded == (summary["iqm_ci95"] is not None)
    if banded:
        assert summary["mean_ci95"] == pytest.approx([low, high]) and low < 4.0 < high


def test_runs_of_different_lengths_are_compared_at_the_last_x_all_reached(tmp_path: Path) -> None:
    long = fake_run(tmp_path / "long", evaluations=eval_entries(1.0, 2.0, 3.0))
    short = fake_run(tmp_path / "short", seed=1, evaluations=eval_entries(1.0, 4.0))
    out = compare([long, short], tmp_path / "cmp", ["return"])
    summary = json.loads(out["summary"].read_text())["toy"]["return"]
    assert (
        summary["mean"] == pytest.approx(3.0) and summary["frames"] == 200
    )  # 2 and 4, not 3 and 4
    header = out["table"].read_text().splitlines()[0]
    assert header.startswith("Last entry of each run: deterministic evaluations;")
    assert "toy at frames 200 (its runs end at frames 200 to 300)" in header
    # episodes of different lengths: the runs' second episodes, frames 41 and 61
    runs = [
        fake_run(tmp_path / "s0", train=train_entries(0.2, 0.4, 0.6, length=20)),
        fake_run(tmp_path / "s1", seed=1, train=train_entries(0.4, 0.8, length=30)),
    ]
    out = compare(runs, tmp_path / "cmp2", ["episode", "safety"], source="train")
    assert (
        "| toy | training entries | 41 | 2 {2, 2} (n=2) | 0.6 {0.4, 0.8} (n=2) |"
        in out["table"].read_text()
    )
    out = compare(runs, tmp_path / "cmp3", ["safety"], source="train", x="episode")
    assert json.loads(out["summary"].read_text())["toy"]["safety"]["mean"] == pytest.approx(0.6)
    # runs of equal length: the header says nothing more
    same = fake_run(tmp_path / "same", seed=2, evaluations=eval_entries(5.0, 6.0))
    out = compare([short, same], tmp_path / "cmp4", ["return"])
    assert out["table"].read_text().splitlines()[0] == (
        "Last entry of each run: deterministic evaluations; over runs, intervals clipped to "
        "each metric's range (n = runs). Groups of fewer than 3 runs have no interval (the "
        "bootstrap interval of two runs is their range): each run's value in braces, "
        "{run, run}."
    )


def test_runs_that_share_no_x_are_refused_in_one_line(tmp_path: Path) -> None:
    a = fake_run(tmp_path / "a", evaluations=eval_entries(1.0, every=100))
    b = fake_run(tmp_path / "b", seed=1, evaluations=eval_entries(1.0, 2.0, every=150))
    with pytest.raises(ValueError) as err:
        compare([a, b], tmp_path / "cmp", ["return"])
    message = str(err.value)
    assert "\n" not in message and "x_grid" in message
    assert f"run_dir {str(b)!r} has no entry at frames <= 100" in message and str(a) in message
    assert not (tmp_path / "cmp").exists()
    out = compare([a, b], tmp_path / "grid", ["return"], x_grid=150)
    assert json.loads(out["summary"].read_text())["toy"]["return"]["mean"] == pytest.approx(1.0)


def test_the_default_shows_the_task_metrics_and_all_shows_every_metric(
    tmp_path: Path, figures, capsys
) -> None:
    metrics = {
        "return": 1.0,
        "safety": 0.5,
        "collisions": 1.0,
        "step_time": 0.01,
        "train_time": 3.0,
        "random": 0.2,
        "episode": 1.0,
        "transitions_shared": 5.0,
        "loss": 0.3,
    }
    runs = [fake_run(tmp_path / f"r{s}", seed=s, evaluations=[(100, metrics)]) for s in (0, 1)]
    out = compare(runs, tmp_path / "cmp")
    assert set(json.loads(out["summary"].read_text())["toy"]) == {"collisions", "return", "safety"}
    assert "step_time" not in out["table"].read_text()
    assert sorted(_panels(figures[-1])) == ["collisions", "return", "safety"]
    out = compare(runs, tmp_path / "all", "all")
    assert set(json.loads(out["summary"].read_text())["toy"]) == set(metrics)
    assert len(_panels(figures[-1])) == len(metrics)
    out = compare(runs, tmp_path / "named", ["step_time", "return"])
    assert sorted(_panels(figures[-1])) == ["return", "step_time"]
    code, out, err = run_cli(
        ["compare", *map(str, runs), "--out", str(tmp_path / "cli"), "--metrics", "all"], capsys
    )
    assert code == 0, err
    assert "step_time [s/step]" in out and "| random |" in out
    # a recipe that records no task metric: every common metric
    other = [
        fake_run(tmp_path / f"o{s}", seed=s, evaluations=[(100, {"score": 1.0 + s})])
        for s in (0, 1)
    ]
    out = compare(other, tmp_path / "other")
    assert set(json.loads(out["summary"].read_text())["toy"]) == {"score"}


def test_no_plotted_band_leaves_its_metric_range(tmp_path: Path, figures) -> None:
    """Seeds at the ends of safety's [0, 1] and velocity's [0, inf) (a Student-t band of n = 3
    reached safety 1.35 and velocity -30 mph): the bands are the bootstrap intervals of
    curves.json, inside each metric's range; an unbounded metric's band is not cut."""
    values = [(0.0, 0.0, -9.0), (1.0, 0.0, 1.0), (1.0, 30.0, 2.0)]
    runs = [
        fake_run(
            tmp_path / f"r{s}",
            seed=s,
            evaluations=[
                (100, {"safety": safety, "average_velocity": v, "return": r}),
                (200, {"safety": safety, "average_velocity": v, "return": r}),
            ],
        )
        for s, (safety, v, r) in enumerate(values)
    ]
    out = compare(runs, tmp_path / "cmp")
    curves = json.loads(out["curves"].read_text())["groups"]["toy"]["metrics"]
    panels = _panels(figures[-1])
    for metric, ax in panels.items():
        low, high = metric_range(metric)
        ys = _band_ys(ax)
        assert ys and low <= min(ys) and max(ys) <= high, (metric, min(ys), max(ys))
        assert min(ys) == pytest.approx(min(i[0] for i in curves[metric]["mean_ci95"]))
        assert max(ys) == pytest.approx(max(i[1] for i in curves[metric]["mean_ci95"]))
    assert max(_band_ys(panels["safety"])) == pytest.approx(1.0)
    assert min(_band_ys(panels["return"])) == pytest.approx(-9.0)
    summary = json.loads(out["summary"].read_text())["toy"]["safety"]
    assert summary["mean"] == pytest.approx(2 / 3) and summary["iqm"] == pytest.approx(2 / 3)
    assert 0.0 <= summary["mean_ci95"][0] < summary["mean_ci95"][1] <= 1.0


@pytest.mark.parametrize("x", ["frames", "episode"])
def test_frames_and_episodes_get_integer_ticks(tmp_path: Path, figures, x: str) -> None:
    runs = [
        fake_run(tmp_path / f"s{s}", seed=s, train=train_entries(0.2, 0.4 + s, length=1))
        for s in (0, 1)
    ]
    compare(runs, tmp_path / "cmp", ["safety"], source="train", x=x)
    (ax,) = _panels(figures[-1]).values()
    lo, hi = ax.get_xlim()
    ticks = [t for t in ax.get_xticks() if lo <= t <= hi]
    assert len(ticks) >= 2 and all(float(t).is_integer() for t in ticks), ticks


def test_a_run_given_twice_is_refused(tmp_path: Path, capsys) -> None:
    run = fake_run(tmp_path / "run", evaluations=eval_entries(1.0))
    other = fake_run(tmp_path / "other", seed=1, evaluations=eval_entries(2.0))
    (tmp_path / "link").symlink_to(run)
    for again in (run, tmp_path / "link", tmp_path / "other" / ".." / "run"):
        with pytest.raises(ValueError) as err:
            compare([run, other, again], tmp_path / "cmp")
        message = str(err.value)
        assert "\n" not in message
        assert message.startswith(f"run_dir {str(again)!r} is {str(run)!r} again")
    assert not (tmp_path / "cmp").exists()
    code, _, err = run_cli(["compare", str(run), str(run), "--out", str(tmp_path / "cmp")], capsys)
    assert code == 2 and err.count("\n") == 1 and "again" in err


def test_out_inside_a_run_directory_is_refused(tmp_path: Path, capsys) -> None:
    run = fake_run(tmp_path / "run", evaluations=eval_entries(1.0))
    other = fake_run(tmp_path / "other", seed=1, evaluations=eval_entries(2.0))
    before = sorted(p.name for p in run.iterdir())
    for out in (run, run / "cmp", tmp_path / "other" / ".." / "run" / "cmp"):
        with pytest.raises(ValueError) as err:
            compare([other, run], out)
        message = str(err.value)
        assert "\n" not in message
        assert f"out_dir {str(out)!r} is inside run_dir {str(run)!r}" in message
    assert sorted(p.name for p in run.iterdir()) == before
    code, _, err = run_cli(["compare", str(run), "--out", str(run)], capsys)
    assert code == 2 and err.count("\n") == 1 and "is inside run_dir" in err
    assert sorted(p.name for p in run.iterdir()) == before
    out = compare([run, other], tmp_path / "cmp")  # beside the runs is fine
    assert out["table"].is_file()
