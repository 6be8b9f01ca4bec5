"""Start-up: the CLI imports only what a command needs (fresh interpreters)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
HEAVY = ("torch", "tensordict", "torchrl", "highway_env", "matplotlib", "pygame", "pandas")


def _imported_after(code: str) -> list[str]:
    report = f"import json, sys; print(json.dumps([m for m in {HEAVY!r} if m in sys.modules]))"
    proc = subprocess.run(
        [sys.executable, "-c", f"{code}\n{report}"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 0, proc.stderr
    return json.loads(proc.stdout.splitlines()[-1])


@pytest.mark.parametrize(
    "code",
    [
        "import mapets_rl.app.cli",
        "from mapets_rl.app.cli import main\ntry:\n    main(['--help'])\n"
        "except SystemExit:\n    pass",
        "import mapets_rl.threads",
    ],
)
def test_cli_and_help_import_no_heavy_module(code: str) -> None:
    assert _imported_after(code) == []


def test_the_check_sees_heavy_imports() -> None:
    """The same check reports them when a module does import them (the test can fail)."""
    assert _imported_after("import pandas") == ["pandas"]


def test_importing_the_package_changes_no_global_logging_or_warning_state() -> None:
    """``import mapets_rl`` (and its recipes) installs no warning filter and no logging filter;
    the CLI quiets its dependencies itself."""
    code = (
        "import logging, warnings\n"
        "import mapets_rl, mapets_rl.experiment, mapets_rl.recipes.mapets\n"
        "def ours():\n"
        "    mine = [f for f in warnings.filters if f[1] and 'PettingZoo' in f[1].pattern]\n"
        "    return mine, list(logging.getLogger('torchrl').filters)\n"
        "assert ours() == ([], []), ours()\n"
        "mapets_rl.quiet_dependencies()\n"
        "assert all(ours()), ours()\n"
    )
    subprocess.run([sys.executable, "-c", code], check=True, cwd=ROOT)
