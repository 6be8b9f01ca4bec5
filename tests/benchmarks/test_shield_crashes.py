"""benchmarks/shield_crashes.py (issue 32): every CAV crash on the shielded freeway-merge falls
in exactly one class of what the shield saw, and runs that are missing are refused before any
work."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from types import ModuleType

import pytest
import torch
from torchrl.envs.utils import RandomPolicy

from mapets_rl.envs import make_env


@pytest.fixture
def crashes(load_script: Callable[[str], ModuleType]) -> ModuleType:
    return load_script("benchmarks/shield_crashes.py")


@pytest.mark.parametrize("passes", [1, 40])
def test_every_crash_of_random_decisions_has_one_class(crashes: ModuleType, passes: int) -> None:
    env = make_env("freeway-merge", backend="torch", num_envs=16, n_vehicles=12, cav_ratio=1.0,
                   shield=True, shield_passes=passes, velocity_weight=1.0)  # fmt: skip
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


def test_a_missing_run_is_refused_before_any_work(crashes: ModuleType, tmp_path: Path) -> None:
    out = tmp_path / "crashes"
    with pytest.raises(SystemExit):
        crashes.main(["--runs", str(tmp_path / "nothing"), "--out", str(out)])
    with pytest.raises(SystemExit):
        crashes.main(["--runs", str(tmp_path), "--shield-passes", "0", "--out", str(out)])
    assert not out.exists()
