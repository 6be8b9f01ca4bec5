"""examples/shapley_freeway.py (paper Fig. 2) at a tiny scale: all four algorithms on one
plot, per-seed finals, their spread and collisions in the table, resumed runs not retrained."""

import json
from collections.abc import Callable
from pathlib import Path
from types import ModuleType

import numpy as np
import pytest


def test_four_algorithms_tiny(tmp_path: Path, load_script: Callable[[str], ModuleType]) -> None:
    example = load_script("examples/shapley_freeway.py")
    argv = [
        "--frames", "80", "--eval-interval", "40", "--eval-episodes", "1", "--seeds", "0", "1",
        "--n-vehicles", "4", "--cav-ratio", "0.5", "--out", str(tmp_path),
        "--env-override", "velocity_weight=0.5",
    ]  # fmt: skip
    summary = example.main(argv)
    assert set(summary) == {"shapley_ac", "maddpg", "m3ddpg", "coma", "mappo", "keep_lane"}
    # the scripted reference is scored on each seed's evaluation episodes, trained on nothing
    keep = summary.pop("keep_lane")
    assert keep["frames"] == 0 and len(keep["final_per_seed"]) == 2
    assert all(np.isfinite(keep["final_per_seed"]))
    for algo, row in summary.items():
        assert row["seeds"] == 2 and len(row["final_per_seed"]) == 2
        assert row["final_spread"] == max(row["final_per_seed"]) - min(row["final_per_seed"])
        assert all(c >= 0 for c in row["final_collisions_per_seed"])
        # system reward = per-CAV return x 2 CAVs, read from the run's own results
        results = json.loads((tmp_path / "runs" / f"{algo}_seed1" / "results.json").read_text())
        last = results["evaluations"][-1]["metrics"]["return"] * 2
        assert abs(row["final_per_seed"][1] - last) < 1e-6
        assert (
            "velocity_weight: 0.5"
            in (tmp_path / "runs" / f"{algo}_seed0" / "config.yaml").read_text()
        )
    table = (tmp_path / "system_reward.md").read_text()
    assert "spread (max - min)" in table and "| MAPPO |" in table
    assert "| keep lane (scripted, untrained) | - |" in table
    assert (tmp_path / "system_reward.png").stat().st_size > 0
    stamp = (tmp_path / "runs" / "coma_seed0" / "results.json").stat().st_mtime_ns
    assert example.main(argv) == {**summary, "keep_lane": keep}
    assert (tmp_path / "runs" / "coma_seed0" / "results.json").stat().st_mtime_ns == stamp
    # a finished run without its results.json is restored from its checkpoint, not retrained
    (tmp_path / "runs" / "coma_seed0" / "results.json").unlink()
    assert example.main(argv) == {**summary, "keep_lane": keep}
    # --report-only trains nothing: the untrained seed 2 is skipped, the others reported
    seeds = argv.index("--seeds")
    report = [*argv[: seeds + 1], "0", "1", "2", *argv[seeds + 3 :], "--report-only"]
    reported = example.main(report)
    assert not (tmp_path / "runs" / "coma_seed2").exists()
    assert {k: v for k, v in reported.items() if k != "keep_lane"} == summary
    assert len(reported["keep_lane"]["final_per_seed"]) == 3


def test_bad_env_override_fails_before_training(
    tmp_path: Path, load_script: Callable[[str], ModuleType]
) -> None:
    example = load_script("examples/shapley_freeway.py")
    argv = ["--n-vehicles", "4", "--frames", "40", "--seeds", "0", "--out", str(tmp_path / "out")]
    with pytest.raises(ValueError, match="velocty_weight"):
        example.main([*argv, "--env-override", "velocty_weight=1.0"])
    assert not (tmp_path / "out").exists()


def test_freeway_merge_runs_and_reference_are_on_the_ramp(
    tmp_path: Path, load_script: Callable[[str], ModuleType]
) -> None:
    example = load_script("examples/shapley_freeway.py")
    argv = [
        "--env", "freeway-merge", "--algorithms", "maddpg", "--frames", "40",
        "--eval-interval", "40", "--eval-episodes", "1", "--seeds", "0",
        "--n-vehicles", "4", "--cav-ratio", "1.0", "--out", str(tmp_path),
    ]  # fmt: skip
    summary = example.main(argv)
    assert set(summary) == {"maddpg", "keep_lane"}
    config = (tmp_path / "runs" / "maddpg_seed0" / "config.yaml").read_text()
    assert "env: freeway-merge" in config
