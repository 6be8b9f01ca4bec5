"""examples/mixed_traffic.py (paper Table I) at the smoke scale: both methods, two seeds, the
all-human row, intervals and units in the table."""

import json
import math
from collections.abc import Callable
from pathlib import Path
from types import ModuleType

import pytest


def test_table_smoke(tmp_path: Path, load_script: Callable[[str], ModuleType]) -> None:
    mixed = load_script("examples/mixed_traffic.py")
    tiny = ["env_config.horizon=5", "eval_episodes=1", "num_cells=[8]", "critic_cells=[8]"]
    argv = [
        "--scale", "smoke", "--n-vehicles", "4", "--frames", "40", "--ratios", "0", "0.5",
        "--seeds", "0", "1", "--out", str(tmp_path),
        "--shapley-override", *tiny, "init_random_frames=0", "batch_size=8",
        "--coma-override", *tiny, "minibatch_size=20",
    ]  # fmt: skip
    results = mixed.main(argv)
    assert set(results) == {"shapley_ac", "coma", "scripted"}
    for method in results:
        assert set(results[method]) == {"0.00", "0.50"}
        assert all(len(runs) == 2 for runs in results[method].values())
        assert all(r["average_velocity"] > 0 for r in results[method]["0.50"])
    table = (tmp_path / "table.md").read_text()
    assert "velocity (mph)" in table and "velocity (m/s)" in table and "±" in table
    assert "| coma | 0.50 | 2 |" in table and "| shapley_ac | 1.00" not in table
    # the scripted keep-lane CAVs train nothing and have no paper column
    assert "| scripted | 0.50 | 2 |" in table and table.rstrip().endswith("| - | - |")
    assert not (tmp_path / "runs" / "scripted").exists()
    assert json.loads((tmp_path / "results.json").read_text()).keys() == results.keys()
    assert (tmp_path / "velocity_comfort.png").stat().st_size > 0
    assert (tmp_path / "runs" / "coma" / "ratio0.50" / "seed1" / "results.json").is_file()
    # finished runs are reused: a second call trains nothing and gives the same table
    assert mixed.main(argv) == results


def test_the_plot_keeps_every_band_in_its_metric_range(
    tmp_path: Path, load_script: Callable[[str], ModuleType], monkeypatch
) -> None:
    """Seeds at the ends of comfort's [0, 3] and velocity's [0, inf) (Student-t error bars of
    n = 3 left both): the drawn bands, read from the matplotlib artists, stay inside."""
    mixed = load_script("examples/mixed_traffic.py")
    figures: list = []
    monkeypatch.setattr(mixed, "atomic_savefig", lambda fig, path, **kw: figures.append(fig))
    seeds = [(0.1, 3.0), (0.2, 3.0), (25.0, 1.0)]  # (m/s, comfort) of 3 seeds
    results = {
        "coma": {
            f"{ratio:.2f}": [{"average_velocity": v, "average_comfort": c} for v, c in seeds]
            for ratio in (0.5, 1.0)
        }
    }
    mixed.plot_table(results, tmp_path / "plot.png")
    (fig,) = figures
    velocity, comfort = fig.axes[:2]
    for ax, (low, high) in ((velocity, (0.0, math.inf)), (comfort, (0.0, 3.0))):
        ys = [
            y for coll in ax.collections for path in coll.get_paths() for y in path.vertices[:, 1]
        ]
        assert ys and low <= min(ys) and max(ys) <= high
    assert max(y for coll in comfort.collections for y in coll.get_paths()[0].vertices[:, 1]) == 3.0


def test_bad_arguments(load_script: Callable[[str], ModuleType]) -> None:
    mixed = load_script("examples/mixed_traffic.py")
    with pytest.raises(SystemExit):
        mixed.parse_args(["--ratios", "1.5"])
    with pytest.raises(SystemExit):
        mixed.parse_args(["--frames", "10"])
    args = mixed.parse_args(["--scale", "paper"])
    assert (args.n_vehicles, args.frames) == (30, 400_000)
    cpu = mixed.parse_args(["--scale", "cpu", "--shapley-override", "batch_size=32"])
    assert cpu.override["shapley_ac"][-2:] == ["exact_max_agents=5", "batch_size=32"]


def test_table_on_freeway_merge(tmp_path: Path, load_script: Callable[[str], ModuleType]) -> None:
    """``--env freeway-merge``: the runs, the scripted rows and ratio 0 (humans only) are all
    on the on-ramp scenario."""
    mixed = load_script("examples/mixed_traffic.py")
    tiny = ["env_config.horizon=5", "eval_episodes=1", "num_cells=[8]", "critic_cells=[8]"]
    argv = [
        "--env", "freeway-merge", "--scale", "smoke", "--n-vehicles", "4", "--frames", "40",
        "--ratios", "0", "1", "--seeds", "0", "--out", str(tmp_path),
        "--shapley-override", *tiny, "init_random_frames=0", "batch_size=8",
        "--coma-override", *tiny, "minibatch_size=20",
    ]  # fmt: skip
    results = mixed.main(argv)
    assert all(r["average_velocity"] > 0 for r in results["scripted"]["1.00"])
    config = (tmp_path / "runs" / "shapley_ac" / "ratio1.00" / "seed0" / "config.yaml").read_text()
    assert "env: freeway-merge" in config


def test_table_on_the_torch_backend_with_training_columns(
    tmp_path: Path, load_script: Callable[[str], ModuleType]
) -> None:
    """``--backend torch --num-envs 2``: both methods train on two batched roads; the table
    adds the training episodes' velocity, comfort and system reward (the last ``--window``)."""
    mixed = load_script("examples/mixed_traffic.py")
    tiny = ["eval_episodes=1", "num_cells=[8]", "critic_cells=[8]"]
    argv = [
        "--backend", "torch", "--num-envs", "2", "--scale", "smoke", "--n-vehicles", "4",
        "--frames", "160", "--ratios", "0.5", "--seeds", "0", "--window", "2",
        "--schedule", "openai", "--out", str(tmp_path),
        "--shapley-override", *tiny, "init_random_frames=0", "batch_size=8",
        "--coma-override", *tiny, "minibatch_size=20",
    ]  # fmt: skip
    results = mixed.main(argv)
    for method in ("shapley_ac", "coma"):
        (run,) = results[method]["0.50"]
        assert run["train_episodes"] >= 4  # 80 steps of each of 2 roads: 2 episodes each
        assert run["train_average_velocity"] > 0 and "train_system_return" in run
        run_dir = tmp_path / "runs" / method / "ratio0.50" / "seed0"
        config = (run_dir / "config.yaml").read_text()
        assert "backend: torch" in config and "num_envs: 2" in config
        assert "gamma: 0.95" in config  # --schedule openai
    shapley = (tmp_path / "runs" / "shapley_ac" / "ratio0.50" / "seed0" / "config.yaml").read_text()
    assert "batch_size: 8" in shapley and "update_interval: 100" in shapley  # override last
    table = (tmp_path / "table.md").read_text()
    assert "training system reward" in table and "| scripted | 0.50 | 2 |" in table
    assert mixed.main(argv) == results  # finished runs are reused
