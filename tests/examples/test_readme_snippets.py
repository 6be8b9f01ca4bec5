"""The README's Python snippets run as written, each in a fresh interpreter from the repository
root (where a reader of the README stands after ``make demo``), with only a training's budget
made tiny: the text of a snippet is replaced nowhere else."""

from __future__ import annotations

import ast
import re
import shutil
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]

SNIPPETS = {
    "ten-line recipe": ("config = MAPETSConfig(", [("episodes=5,", "episodes=1,")]),
    "a model or loss": ("class MAPETSWithMSE(MAPETS):", []),
    "any PettingZoo env": (
        "wrap_pettingzoo(HighwayParallelEnv(**c)",
        [("episodes=3,", "episodes=1,"), ("total_frames=3_000", "total_frames=200")],
    ),
}
"""Snippet -> a line that marks it, and its budget's replacements (old, new), each made once."""


def readme_snippets() -> list[str]:
    """The README's Python code blocks, in order."""
    return re.findall(r"```python\n(.*?)```", (ROOT / "README.md").read_text(), re.S)


def snippet(name: str) -> str:
    """The snippet ``name`` of :data:`SNIPPETS` with its budget replaced."""
    marker, budget = SNIPPETS[name]
    (code,) = [block for block in readme_snippets() if marker in block]
    for old, new in budget:
        assert code.count(old) == 1, f"the README's {name} snippet no longer says {old!r} once"
        code = code.replace(old, new)
    return code


def run_from_root(code: str) -> subprocess.CompletedProcess[str]:
    """``python -c code`` from the repository root; the run directories it wrote (the snippets
    name none: ``runs/...``, which it prints) are removed afterwards."""
    runs = ROOT / "runs"
    existed = runs.exists()
    proc = subprocess.run(
        [sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=300
    )
    for written in re.findall(r"writing the run to (\S+)$", proc.stderr, re.M):
        path = (ROOT / written).resolve()
        if path.parent == runs.resolve():
            shutil.rmtree(path, ignore_errors=True)
    if not existed and runs.is_dir() and not any(runs.iterdir()):
        runs.rmdir()
    return proc


def test_every_python_snippet_of_the_readme_is_run_here() -> None:
    blocks = readme_snippets()
    assert len(blocks) == len(SNIPPETS)
    for marker, _ in SNIPPETS.values():
        assert sum(marker in block for block in blocks) == 1, marker


def test_the_ten_line_recipe_trains_and_prints_its_thread_choice_once() -> None:
    proc = run_from_root(snippet("ten-line recipe"))
    assert proc.returncode == 0, proc.stderr
    last = ast.literal_eval(proc.stdout.strip().splitlines()[-1])
    assert last["frames"] == 200 and last["metrics"]["episode"] == 1.0
    assert 0.0 <= last["metrics"]["safety"] <= 1.0
    assert proc.stderr.count("torch threads: ") == 1  # the Python API's choice, printed once


def test_the_loss_snippet_defines_its_recipe() -> None:
    code = snippet("a model or loss") + "\nprint(MAPETSWithMSE.__mro__[1].__name__)\n"
    proc = run_from_root(code)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.split() == ["MAPETS"]


def test_the_pettingzoo_snippet_imports_and_trains_from_the_repository_root() -> None:
    """It failed with ModuleNotFoundError: ``highway_pettingzoo`` is in ``examples/extending``."""
    proc = run_from_root(snippet("any PettingZoo env"))
    assert proc.returncode == 0, proc.stderr
    written = re.findall(r"^(mapets|mappo): writing the run to ", proc.stderr, re.M)
    assert written == ["mapets", "mappo"]
    assert proc.stderr.count("torch threads: ") == 1  # two trainings, one line
