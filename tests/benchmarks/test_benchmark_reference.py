"""``--reference mbrl-lib`` of the benchmarks without mbrl-lib: install advice, non-zero exit."""

from __future__ import annotations

import importlib.util
import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]

pytestmark = pytest.mark.skipif(
    importlib.util.find_spec("mbrl") is not None,
    reason="mbrl-lib is importable here: the flag would run the reference instead",
)


@pytest.mark.parametrize(
    "script, args",
    [
        ("planner.py", ["--configs", "cpu", "--agents", "1"]),
        ("ensemble_training.py", ["--agents", "1"]),
    ],
)
def test_reference_without_mbrl_explains_install_and_exits(script: str, args: list[str]) -> None:
    env = {**os.environ, "PYTHONPATH": str(ROOT), "OMP_NUM_THREADS": "1"}
    result = subprocess.run(
        [sys.executable, str(ROOT / "benchmarks" / script), "--reference", "mbrl-lib", *args],
        cwd=ROOT,
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert result.returncode == 2, result.stderr
    assert "No module named 'mbrl'" in result.stderr
    assert "pip install --no-deps mbrl==0.2.0" in result.stderr
    assert "site.addsitedir" in result.stderr
    # It stops before any benchmark work: nothing is timed or printed on stdout.
    assert "CPU capability" not in result.stdout
    assert result.stdout == ""
