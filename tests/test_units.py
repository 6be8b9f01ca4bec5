"""Metrics carry units: in ``results.json``, in ``compare``'s table and plot labels (speeds in
m/s and mph), and config fields declare theirs where they are declared."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import pytest

from mapets_rl.app.comparison import compare
from mapets_rl.comm import CommConfig
from mapets_rl.metrics import MPH_PER_MPS, format_metric, metric_label, metric_unit
from tests.experiment.test_results import fake_run


def test_metric_units_and_labels() -> None:
    assert MPH_PER_MPS == pytest.approx(2.23694, abs=1e-5)  # 1 m/s in mph
    assert metric_unit("agility") == "m/step" and metric_unit("eval/agility") == "m/step"
    assert metric_label("agility") == "agility [m/step]"
    assert metric_label("average_velocity") == "average_velocity [m/s]"
    assert metric_label("loss_actor") == "loss_actor"  # no unit, name alone
    assert format_metric("average_velocity", 31.3) == "31.3 m/s (70.02 mph)"  # freeway limit
    assert format_metric("agility", 0.9712) == "0.9712 m/step"
    assert format_metric("loss_actor", 1.5) == "1.5"


def test_results_json_names_the_units_of_its_metrics(tmp_path: Path) -> None:
    run = fake_run(
        tmp_path / "run",
        evaluations=[(100, {"agility": 1.0, "average_velocity": 25.0, "loss_x": 0.1})],
    )
    units = json.loads((run / "results.json").read_text())["units"]
    assert units == {"agility": "m/step", "average_velocity": "m/s", "frames": "env steps"}


def test_compare_table_and_plot_labels_carry_units(tmp_path: Path, monkeypatch) -> None:
    runs = [
        fake_run(
            tmp_path / f"r{s}",
            seed=s,
            evaluations=[(100, {"agility": 1.0 + s, "average_velocity": 20.0 + 2 * s})],
        )
        for s in (0, 1)
    ]
    titles: list[str] = []
    import matplotlib.axes

    original = matplotlib.axes.Axes.set_title

    def set_title(ax, label, *args, **kwargs):
        titles.append(label)
        return original(ax, label, *args, **kwargs)

    monkeypatch.setattr(matplotlib.axes.Axes, "set_title", set_title)
    out = compare(runs, tmp_path / "cmp", ["agility", "average_velocity"])
    table = out["table"].read_text()
    assert "| agility [m/step] | average_velocity [m/s] |" in table
    # mean 21 m/s = 46.98 mph; two runs get no interval, their values instead: 20 and 22 m/s
    assert "| 21 {20, 22} (46.98 {44.74, 49.21} mph) (n=2) |" in table
    assert titles == ["agility [m/step]", "average_velocity [m/s]"]


def test_config_fields_declare_their_units() -> None:
    units = {f.name: f.metadata.get("unit") for f in dataclasses.fields(CommConfig)}
    assert units == {"comm_range": "m", "p_fail": None, "share_plans": None}


def test_logs_name_the_units_of_the_logged_scalars(tmp_path: Path) -> None:
    from mapets_rl.experiment.results import make_logger

    logger = make_logger("csv", tmp_path, "run")
    logger.log_scalar("eval/agility", 1.0, step=1)
    units = json.loads((tmp_path / "logs" / "units.json").read_text())
    assert units["agility"] == "m/step" and units["average_velocity"] == "m/s"
    assert make_logger("none", tmp_path / "quiet", "run") is None
    assert not (tmp_path / "quiet").exists()
