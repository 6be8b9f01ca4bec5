"""benchmarks/gpu.sh, the one command for the GPU measurements: it parses, every file it runs
exists, and a step not asked for is not run (the steps themselves need a CUDA device)."""

import re
import shutil
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
SCRIPT = ROOT / "benchmarks" / "gpu.sh"


@pytest.mark.skipif(shutil.which("bash") is None, reason="needs bash")
def test_gpu_script_parses_and_names_existing_files(tmp_path: Path) -> None:
    subprocess.run(["bash", "-n", str(SCRIPT)], check=True)
    text = SCRIPT.read_text()
    paths = set(re.findall(r"\b((?:benchmarks|tests)/[\w/]+\.py)\b", text))
    assert {"benchmarks/planner.py", "benchmarks/decision_time.py"} <= paths
    assert all((ROOT / p).is_file() for p in paths), paths
    # only the named step runs: "machine" with a python that prints its arguments
    fake = tmp_path / "python"
    fake.write_text('#!/bin/sh\necho "fake python $*"\n')
    fake.chmod(0o755)
    out = subprocess.run(
        ["bash", str(SCRIPT), str(tmp_path / "out"), str(fake), "machine"],
        capture_output=True,
        text=True,
        cwd=ROOT,
        check=True,
    ).stdout
    assert "=== machine" in out and "=== planner" not in out and "=== tests" not in out
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == ["machine.log"]
