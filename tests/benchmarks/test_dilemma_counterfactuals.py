"""benchmarks/dilemma_counterfactuals.py (issue 50): on the dilemma variant no ramp CAV's
Change Left on the acceleration lane runs and forcing scores exactly keep lane; with
``ramp_forcing`` back on the same question finds forced merges that run; bad settings are
refused before any work."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
SMALL = ["--roads", "3", "--score-roads", "3", "--seeds", "0"]


@pytest.fixture(autouse=True)
def _benchmarks_on_path(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.syspath_prepend(str(ROOT / "benchmarks"))  # the script imports _common


def _row(table: str, label: str) -> list[str]:
    line = next(line for line in table.splitlines() if line.startswith(f"| {label} |"))
    return [cell.strip() for cell in line.strip("|").split("|")]


@pytest.mark.parametrize("forcing", [False, True])
def test_forcing_runs_only_where_the_scenario_allows_it(load_script: Callable,
                                                       forcing: bool) -> None:  # fmt: skip
    study = load_script("benchmarks/dilemma_counterfactuals.py")
    setting = ["--set", "n_vehicles=12", f"ramp_forcing={str(forcing).lower()}"]
    table = study.main([*SMALL, *setting])
    attempts, ran = _row(table, "forcing")[1:3]
    assert float(attempts) > 0
    assert (float(ran) > 0) == forcing
    gain = _row(table, "every ramp CAV forcing")[2]
    assert (gain != "+0.0%") == forcing
    assert _row(table, "rule's yields")[1] != "0.00"


@pytest.mark.parametrize("bad", [["--roads", "0"], ["--gamma", "1.5"], ["--score-roads", "0"]])
def test_bad_settings_are_refused_first(load_script: Callable, bad: list[str]) -> None:
    study = load_script("benchmarks/dilemma_counterfactuals.py")
    with pytest.raises(SystemExit):
        study.main(bad)
