"""benchmarks/yield_counterfactuals.py (issue 32): the counterfactuals are the library's
(``tests/envs/test_counterfactuals.py``); a missing run or a bad setting is refused before any
work."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import pytest


@pytest.mark.parametrize("bad", [["--roads", "0"], ["--gamma", "1.5"], []])
def test_bad_settings_and_missing_runs_are_refused_first(
    load_script: Callable, tmp_path: Path, bad: list[str]
) -> None:
    yields = load_script("benchmarks/yield_counterfactuals.py")
    with pytest.raises(SystemExit):
        yields.main(["--runs", str(tmp_path / "no_run_seed0"), *bad, "--out", str(tmp_path)])
    assert list(tmp_path.iterdir()) == []
