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


def test_torch_backend_trains_every_algorithm_and_reports_the_training_metric(
    tmp_path: Path, load_script: Callable[[str], ModuleType]
) -> None:
    """``--backend torch --num-envs 2``: every algorithm trains on two batched roads for the
    same frames; the paper's metric (mean training system reward per window of training
    episodes) is tabulated and drawn beside the greedy evaluations, read from each run's
    training episodes; ``--schedule openai`` gives each recipe the fields it has."""
    example = load_script("examples/shapley_freeway.py")
    argv = [
        "--backend", "torch", "--num-envs", "2", "--frames", "240", "--eval-interval", "160",
        "--eval-episodes", "1", "--seeds", "0", "--n-vehicles", "4", "--cav-ratio", "0.5",
        "--window", "2", "--schedule", "openai", "--out", str(tmp_path),
    ]  # fmt: skip
    summary = example.main(argv)
    assert set(summary) == {"shapley_ac", "maddpg", "m3ddpg", "coma", "mappo", "keep_lane"}
    keep = summary.pop("keep_lane")
    assert np.isfinite(keep["final_mean"])
    for algo, row in summary.items():
        run = tmp_path / "runs" / f"{algo}_seed0"
        config = (run / "config.yaml").read_text()
        assert "backend: torch" in config and "num_envs: 2" in config
        assert "total_frames: 240" in config
        returns = [
            json.loads(line)["system_return"]
            for line in (run / "train_episodes.jsonl").read_text().splitlines()
        ]
        # 120 steps of each of the 2 roads: 3 episodes each, unless CAVs crashed early
        assert len(returns) >= 6
        assert row["train_episodes_per_seed"] == [len(returns)]
        windows = len(returns) // 2
        assert row["train_windows"] == windows
        assert row["train_last_mean"] == pytest.approx(np.mean(returns[2 * windows - 2 :]))
        assert row["train_first_mean"] == pytest.approx(np.mean(returns[:2]))
        assert json.loads((run / "results.json").read_text())["evaluations"][-1]["frames"] == 240
    maddpg = (tmp_path / "runs" / "maddpg_seed0" / "config.yaml").read_text()
    assert "update_interval: 100" in maddpg and "batch_size: 1024" in maddpg
    coma = (tmp_path / "runs" / "coma_seed0" / "config.yaml").read_text()
    assert "lr_critic: 0.01" in coma and "lr: 0.0005" in coma  # its policy lr stays
    table = (tmp_path / "system_reward.md").read_text()
    assert "Mean *training* episode system reward" in table and "| MAPPO | " in table
    assert (tmp_path / "train_system_reward.png").stat().st_size > 0
    # finished runs are not retrained
    stamp = (tmp_path / "runs" / "maddpg_seed0" / "train_episodes.jsonl").stat().st_mtime_ns
    assert example.main(argv) == {**summary, "keep_lane": keep}
    path = tmp_path / "runs" / "maddpg_seed0" / "train_episodes.jsonl"
    assert path.stat().st_mtime_ns == stamp


def test_torch_backend_run_extended_later_records_the_same_episodes(
    tmp_path: Path, load_script: Callable[[str], ModuleType]
) -> None:
    """A run trained to 160 frames, then resumed to 240, records the training episodes an
    uninterrupted 240-frame run records."""
    example = load_script("examples/shapley_freeway.py")

    def argv(frames: int, out: Path) -> list[str]:
        return [
            "--backend", "torch", "--num-envs", "2", "--frames", str(frames),
            "--eval-interval", "80", "--eval-episodes", "1", "--seeds", "0",
            "--n-vehicles", "4", "--algorithms", "maddpg", "--window", "2", "--out", str(out),
        ]  # fmt: skip

    example.main(argv(160, tmp_path / "a"))
    resumed = example.main(argv(240, tmp_path / "a"))
    whole = example.main(argv(240, tmp_path / "b"))
    episodes = [
        (tmp_path / out / "runs" / "maddpg_seed0" / "train_episodes.jsonl").read_text()
        for out in ("a", "b")
    ]
    assert episodes[0] == episodes[1] and episodes[0]
    assert resumed["maddpg"]["train_last_mean"] == whole["maddpg"]["train_last_mean"]
