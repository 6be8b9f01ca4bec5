"""benchmarks/critic_resolution.py (issue 50): critics fitted offline to exact returns, each
scored on held-out roads and probed on every decision near the merge; bad settings refused
before any work."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
TINY = ["--set", "n_vehicles=12", "--roads", "4", "--episodes", "2", "--probe-roads", "3",
        "--steps", "5", "--batch", "8"]  # fmt: skip


@pytest.fixture(autouse=True)
def _benchmarks_on_path(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.syspath_prepend(str(ROOT / "benchmarks"))  # the script imports _common


def test_every_critic_and_target_is_fitted_and_probed(load_script: Callable) -> None:
    study = load_script("benchmarks/critic_resolution.py")
    table = study.main([*TINY, "--critics", "own", "advantage-own"])
    fits = [line.split("|")[1:4] for line in table.splitlines() if line.count("|") == 5]
    assert {(name.strip(), target.strip()) for name, target, _ in fits[2:]} == {
        ("own", "own"),
        ("own", "team"),
        ("advantage-own", "own"),
        ("advantage-own", "team"),
    }
    for _, _, r2 in fits[2:]:
        assert float(r2) <= 1.0
    probed = [line for line in table.splitlines() if "every mainline move near the merge" in line]
    assert len(probed) == 4
    exact = {line.split("|")[4] for line in probed if ", own |" in line}
    assert len(exact) == 1  # both critics are probed on the same decisions


def test_stored_proposals_keep_the_moves_the_shield_replaced(
    load_script: Callable, capsys: pytest.CaptureFixture
) -> None:
    """With every CAV moving at random, some moves are replaced by the shield: stored as Keep
    Lane by default (as the learners store them), as proposed with ``--store proposed``."""
    study = load_script("benchmarks/critic_resolution.py")
    moves = {}
    for store in ("executed", "proposed"):
        study.main([*TINY, "--critics", "own", "--targets", "own", "--epsilon", "1",
                    "--store", store])  # fmt: skip
        line = next(x for x in capsys.readouterr().out.splitlines() if "moves that" in x)
        moves[store] = int(line.split("), ")[1].split(" moves")[0])
    assert moves["proposed"] > moves["executed"] > 0


@pytest.mark.parametrize(
    "bad",
    [
        ["--roads", "0"],
        ["--episodes", "1"],
        ["--epsilon", "1.5"],
        ["--gamma", "-0.1"],
        ["--store", "both"],
    ],
)
def test_bad_settings_are_refused_first(load_script: Callable, bad: list[str]) -> None:
    study = load_script("benchmarks/critic_resolution.py")
    with pytest.raises(SystemExit):
        study.main(bad)
