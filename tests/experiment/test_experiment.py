"""mapets_rl.experiment: config, checkpoints, the run loop (with the small real learner of
``examples/extending/toy_recipe.py`` on its toy multi-agent env), exact resume, results and
compare."""

from __future__ import annotations

import json
import os
from pathlib import Path

import pytest
import torch
from toy_recipe import ToyConfig, ToyLearner

from mapets_rl.app.comparison import compare
from mapets_rl.experiment import (
    CheckpointError,
    ConfigError,
    digest_path,
    file_sha256,
    latest_checkpoint,
    list_checkpoints,
    load_checkpoint,
    read_results,
    save_checkpoint,
)
from mapets_rl.statistics import mean_ci95

pytestmark = pytest.mark.usefixtures("toy_scenario")


# ------------------------------------------------------------------------------- config
def test_config_overrides_and_yaml_roundtrip(tmp_path: Path) -> None:
    cfg = ToyConfig().with_overrides(
        ["lr=3e-4", "seed=7", "env_config.n_agents=2", "video=true", "total_frames=100.0"]
    )
    assert cfg.lr == pytest.approx(3e-4) and isinstance(cfg.lr, float)
    assert cfg.seed == 7 and cfg.env_config == {"n_agents": 2} and cfg.video is True
    assert cfg.total_frames == 100 and isinstance(cfg.total_frames, int)
    cfg.to_yaml(tmp_path / "c.yaml")
    assert ToyConfig.from_yaml(tmp_path / "c.yaml") == cfg


@pytest.mark.parametrize(
    "override, field",
    [
        ("nope=1", "nope"),
        ("lr=-1", "lr"),
        ("seed=abc", "seed"),
        ("logger=xml", "logger"),
        ("frames_per_batch=0", "frames_per_batch"),
        ("video=maybe", "video"),
        ("lr", "lr"),
    ],
)
def test_config_errors_name_the_field(override: str, field: str) -> None:
    with pytest.raises(ConfigError, match=field):
        ToyConfig().with_overrides([override])


# -------------------------------------------------------------------------- checkpoints
def test_checkpoint_keep_last_and_safe_load(tmp_path: Path) -> None:
    for step in (10, 20, 30):
        save_checkpoint(
            {"w": torch.full((2,), float(step)), "step": step}, tmp_path, step, keep_last=2
        )
    names = [p.name for p in list_checkpoints(tmp_path)]
    assert names == ["ckpt_000000000020.pt", "ckpt_000000000030.pt"]
    assert load_checkpoint(latest_checkpoint(tmp_path))["step"] == 30

    marker = tmp_path / "pwned"

    class Evil:
        def __reduce__(self):
            return (os.system, (f"touch {marker}",))

    evil = tmp_path / "checkpoints" / "ckpt_000000000099.pt"
    torch.save({"x": Evil()}, evil)
    # even with a matching digest beside it, a pickle with a payload is refused, not run
    digest_path(evil).write_text(f"{file_sha256(evil)}  {evil.name}\n")
    with pytest.raises(CheckpointError, match="not a checkpoint this library wrote") as err:
        load_checkpoint(evil)
    assert "weights_only" not in str(err.value) and not marker.exists()


def test_truncated_write_never_replaces_good_checkpoint(tmp_path: Path, monkeypatch) -> None:
    good = save_checkpoint({"w": torch.ones(3)}, tmp_path, 5)
    real_save = torch.save

    def crash_mid_write(obj, fh, *a, **k):
        real_save(obj, fh, *a, **k)
        fh.truncate(7)  # half a file on disk, then the process dies
        raise KeyboardInterrupt

    monkeypatch.setattr(torch, "save", crash_mid_write)
    with pytest.raises(KeyboardInterrupt):
        save_checkpoint({"w": torch.zeros(3)}, tmp_path, 5)
    monkeypatch.undo()
    assert list_checkpoints(tmp_path) == [good]
    # temp file cleaned, the good checkpoint's digest untouched
    assert sorted(p.name for p in good.parent.iterdir()) == [good.name, digest_path(good).name]
    assert torch.equal(load_checkpoint(good)["w"], torch.ones(3))


# --------------------------------------------------------------------- run loop + resume
def _params(exp: ToyLearner) -> torch.Tensor:
    return torch.cat([p.detach().flatten() for p in exp.actor.parameters()])


def test_toy_learner_trains_and_writes_run_dir(tmp_path: Path) -> None:
    exp = ToyLearner(ToyConfig(total_frames=200, logger="csv"), tmp_path / "run")
    before = exp.evaluate()["return"]
    p0 = _params(exp).clone()
    evals = exp.train()
    assert not torch.equal(p0, _params(exp))
    assert [e["frames"] for e in evals] == list(range(20, 201, 20))
    assert evals[-1]["metrics"]["return"] > before  # it learns to drive x to 0
    run = tmp_path / "run"
    assert (run / "config.yaml").is_file() and (run / "logs").is_dir()
    assert read_results(run)["evaluations"] == evals
    assert len(list_checkpoints(run)) == 2
    with pytest.raises(ValueError, match="already holds a run"):
        ToyLearner(ToyConfig(), run)  # a fresh run must not mix with the old checkpoints


def test_public_training_steps_reseed_and_count(tmp_path: Path) -> None:
    """``reset_collector`` re-seeds the collector from (seed, boundary), so two resets give the
    same first observations; ``train_on_batch`` is one iteration of ``train``: it counts the
    batch's frames and returns its training metrics."""
    exp = ToyLearner(ToyConfig(), tmp_path / "run")
    exp.reset_collector()
    first = exp.collector.next()
    exp.reset_collector()
    again = exp.collector.next()
    # the episodes restart from the same states (the policy's noise is not re-seeded)
    assert torch.equal(first["agents", "observation"][0], again["agents", "observation"][0])
    exp.reset_collector()
    metrics = exp.train_on_batch()
    assert (exp.frames, exp.batches) == (first.numel(), 1)
    assert metrics and all(isinstance(value, float) for value in metrics.values())
    exp.close()


def test_resume_reproduces_uninterrupted_run(tmp_path: Path) -> None:
    full = ToyLearner(ToyConfig(), tmp_path / "full")
    full_evals = full.train()

    part = ToyLearner(ToyConfig(total_frames=40), tmp_path / "part")
    part.train()
    # continue the stopped run with the full budget (as `mapets-rl resume` would)
    resumed = ToyLearner.from_run_dir(tmp_path / "part", overrides=["total_frames=60"])
    assert resumed.frames == 40
    evals = resumed.train()
    assert evals == full_evals
    assert torch.equal(_params(resumed), _params(full))


@pytest.mark.parametrize("progress", [True, False])
def test_evaluate_counts_its_episodes_on_stderr_unless_quiet(
    progress: bool, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    exp = ToyLearner(ToyConfig(progress=progress), tmp_path / "run")
    capsys.readouterr()
    exp.evaluate(episodes=3)
    out, err = capsys.readouterr()
    assert out == ""
    if progress:
        assert "evaluate toy toy seed 0" in err and "0/3 " in err and "episode/s" in err
    else:
        assert err == ""


def test_training_entries_and_checkpoints_of_a_recipe_loop(tmp_path: Path) -> None:
    """A loop written in the recipe (as MA-PETS's): ``end_iteration`` alone keeps each
    iteration's metrics as a training entry, checkpoints when due and calls back."""
    exp = ToyLearner(ToyConfig(), tmp_path / "run")
    seen = []
    with exp.training_loop(
        seen.append, eval_interval=None, checkpoint_interval=20, train_entries=True
    ) as loop:
        exp.collector.reset()
        while not loop.finished:
            metrics = exp.train_on_batch()
            loop.end_iteration(metrics)
    assert [entry["frames"] for entry in exp.results.train] == list(range(10, 61, 10))
    assert [entry["metrics"] for entry in exp.results.train] == seen
    assert exp.results.evaluations == []
    assert [path.name for path in list_checkpoints(tmp_path / "run")][-2:] == [
        "ckpt_000000000040.pt",
        "ckpt_000000000060.pt",
    ]
    assert exp.latest_metrics == seen[-1]


@pytest.mark.parametrize(
    "intervals, name",
    [
        ({"eval_interval": -1, "checkpoint_interval": 1}, "eval_interval"),
        ({"eval_interval": None, "checkpoint_interval": -5}, "checkpoint_interval"),
    ],
)
def test_training_loop_refuses_a_negative_interval(intervals, name, tmp_path: Path) -> None:
    exp = ToyLearner(ToyConfig(), tmp_path / "run")
    with pytest.raises(ValueError, match=f"{name} must be >= 0"):
        with exp.training_loop(**intervals):
            pass


# -------------------------------------------------------------------------------- compare
def test_mean_ci95() -> None:
    mean, half = mean_ci95([1.0, 2.0, 3.0])
    assert mean == pytest.approx(2.0)
    assert half == pytest.approx(4.3027 * 1.0 / 3**0.5, abs=1e-3)
    assert mean_ci95([5.0]) == (5.0, 0.0)


def test_compare_writes_plot_and_table(tmp_path: Path) -> None:
    runs = []
    for seed in (0, 1):
        exp = ToyLearner(ToyConfig(seed=seed), tmp_path / f"toy{seed}")
        exp.train()
        runs.append(exp.run_dir)
    out = compare(runs, tmp_path / "cmp")
    assert out["plot"].is_file() and out["plot"].stat().st_size > 1000
    table = out["table"].read_text()
    assert "| toy |" in table and "return" in table and "n=2" in table
    data = json.loads(out["summary"].read_text())
    assert data["toy"]["return"]["n"] == 2
