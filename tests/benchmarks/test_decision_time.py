"""benchmarks/decision_time.py times real eval policies and rejects bad input before work."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
SCRIPT = ROOT / "benchmarks" / "decision_time.py"


def _run(*argv: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, str(SCRIPT), *argv],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=300,
    )


def test_decision_time_table_for_two_baselines() -> None:
    proc = _run("--methods", "maddpg", "shapley_ac", "--agents", "2", "--decisions", "3")
    assert proc.returncode == 0, proc.stderr
    machine = r"CPU capability \w+, torch \S+, 1 thread\(s\); device cpu \(cpu\), I = 2"
    assert re.search(machine, proc.stdout)
    table = proc.stdout.split("|---|---|---|---|---|---|---|\n")[1]
    rows = [[c.strip() for c in line.strip("|").split("|")] for line in table.splitlines()]
    assert [r[:3] for r in rows] == [
        ["maddpg", "figure-eight", "3"],
        ["shapley_ac", "freeway", "3"],
    ]
    for row in rows:
        median = float(row[3].split(" [")[0])
        low, high = map(float, row[3].split("[")[1].rstrip("]").split("-"))
        assert 0 < low <= median <= high
        # per agent-step = joint / I (both printed to 3 significant digits)
        assert float(row[5]) == pytest.approx(median / 2, rel=0.01)
        assert row[6] == "—"  # the paper's Table IV has neither


def test_bad_arguments_fail_before_any_work() -> None:
    proc = _run("--agents", "0")
    assert proc.returncode == 2 and "--agents must be >= 1, got 0" in proc.stderr
    assert proc.stdout == ""


def test_dqn_and_firl_rows_with_the_papers_firl_cell() -> None:
    proc = _run("--methods", "dqn", "firl", "--agents", "2", "--decisions", "3")
    assert proc.returncode == 0, proc.stderr
    table = proc.stdout.split("|---|---|---|---|---|---|---|\n")[1]
    rows = [[c.strip() for c in line.strip("|").split("|")] for line in table.splitlines()]
    assert [r[:3] for r in rows] == [["dqn", "figure-eight", "3"], ["firl", "figure-eight", "3"]]
    assert [r[6] for r in rows] == ["—", "76.04 ± 3.03"]  # the paper's Table IV has FIRL


def test_svmix_row_with_the_papers_svmix_cells_on_both_loops() -> None:
    for loop, cell in (
        ("figure-eight", "102.80 ± 2.67"),
        ("figure-eight-multilane", "110.60 ± 3.02"),
    ):
        proc = _run("--methods", "svmix", "--loop", loop, "--agents", "2", "--decisions", "3")
        assert proc.returncode == 0, proc.stderr
        table = proc.stdout.split("|---|---|---|---|---|---|---|\n")[1]
        rows = [[c.strip() for c in line.strip("|").split("|")] for line in table.splitlines()]
        assert [r[:3] for r in rows] == [["svmix", loop, "3"]]
        assert rows[0][6] == cell  # the paper's Table IV, single- and multi-lane loop
