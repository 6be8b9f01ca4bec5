"""benchmarks/shield_crashes.py (issue 32): every crash of a shielded episode falls in exactly one
class of what the shield saw, none unexplained; trained runs are read from their run
directories, refused before any work when they are not shielded freeway runs, and a second call
reuses the cached counts."""

from __future__ import annotations

import shutil
from collections.abc import Callable
from pathlib import Path
from types import ModuleType

import pytest
import torch
from torchrl.envs.utils import RandomPolicy

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture
def crashes(load_script: Callable[[str], ModuleType], monkeypatch) -> ModuleType:
    monkeypatch.syspath_prepend(str(ROOT / "benchmarks"))  # it imports cooperation_control
    return load_script("benchmarks/shield_crashes.py")


@pytest.mark.parametrize("passes", [1, 40])
def test_every_crash_of_random_decisions_has_one_class(crashes: ModuleType, passes: int) -> None:
    settings = {"shield": True, "shield_passes": passes, "velocity_weight": 1.0}
    env = crashes.evaluation_env(16, 12, settings)
    torch.manual_seed(3)  # decisions under which one road's replaced CAVs crash
    counts = crashes.classify(RandomPolicy(env.full_action_spec), env, 0)
    env.close()
    total = sum(counts[k] for k in crashes.CLASSES)
    assert total == counts["collisions"] > 0
    assert counts["replaced"] > 0 and counts["vehicle"] > 0
    assert counts["unexplained"] == 0  # the check's first step is the real step
    assert counts["shielded"] > 0
    assert counts["obstacle"] + counts["vehicle"] == total
    assert counts["ramp"] + counts["mainline near merge"] + counts["mainline elsewhere"] == total
    assert counts["mid change"] <= counts["kept, predicted"]
    assert counts["episodes"] == 16


def tiny_shielded_run(load_script: Callable[[str], ModuleType], out: Path) -> Path:
    """A 20-frame shielded MADDPG run of ``cooperation_control`` (8 vehicles) under ``out``."""
    control = load_script("benchmarks/cooperation_control.py")
    tiny = ["--seeds", "0", "--frames", "20", "--train-roads", "4", "--eval-roads", "2"]
    control.main(["--variants", "maddpg_shield", *tiny, "--n-vehicles", "8", "--out", str(out)])
    return out / "runs" / "maddpg_shield_seed0"


def test_a_trained_run_is_classified_and_cached(
    crashes: ModuleType, load_script: Callable[[str], ModuleType], tmp_path: Path
) -> None:
    run = tiny_shielded_run(load_script, tmp_path)
    control = load_script("benchmarks/cooperation_control.py")
    out = tmp_path / "crashes"
    argv = ["--runs", str(run), "--seeds", "0", "--eval-roads", "3", "--out", str(out)]
    rows = crashes.main(argv)
    assert list(rows) == ["maddpg_shield@0k", "keep lane", "cooperative merge"]
    counts = rows["maddpg_shield@0k"][0]
    assert counts["episodes"] == 3 and counts["n_vehicles"] == 8
    assert sum(counts[k] for k in crashes.CLASSES) == counts["collisions"]
    # the system reward is cooperation_control's on the same roads (keep lane, 3 roads)
    args = control.argparse.Namespace(eval_roads=3, n_vehicles=8)
    keep = control.score(control.ScriptedCAVPolicy, counts["settings"], 0, args)
    assert rows["keep lane"][0]["system_reward"] == pytest.approx(keep["system_reward"].sum())
    stamps = {f: f.stat().st_mtime_ns for f in out.iterdir()}
    assert len(stamps) == 3
    assert crashes.main(argv) == rows
    assert {f: f.stat().st_mtime_ns for f in out.iterdir()} == stamps  # nothing scored again


def test_runs_that_are_not_shielded_freeway_runs_are_refused_first(
    crashes: ModuleType, load_script: Callable[[str], ModuleType], tmp_path: Path
) -> None:
    run = tiny_shielded_run(load_script, tmp_path)
    unshielded = tmp_path / "unshielded"
    shutil.copytree(run, unshielded)
    config = unshielded / "config.yaml"
    config.write_text(config.read_text().replace("shield: true", "shield: false"))
    out = tmp_path / "crashes"
    for bad, match in [(tmp_path / "nothing", "not a run directory"), (unshielded, "shield")]:
        with pytest.raises(ValueError, match="--runs: .*" + match):
            crashes.main(["--runs", str(run), str(bad), "--out", str(out)])
    with pytest.raises(SystemExit):
        crashes.main(["--runs", str(run), "--shield-passes", "0", "--out", str(out)])
    assert not out.exists()
