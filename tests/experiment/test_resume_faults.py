"""Faults where something is lost or mixed (issue 23): the logs after a kill and resume hold
each step once, a resume whose override fails leaves the run directory as it was, MAPPO's
trajectory ids continue across a resume, and a write that fails (file size limit, disk full) is
one line naming the file with the earlier checkpoints intact."""

from __future__ import annotations

import errno
import os
import subprocess
import sys
import textwrap
from pathlib import Path
from typing import Any

import pytest
import torch
import yaml

from mapets_rl.experiment import (
    list_checkpoints,
    load_checkpoint,
    read_results,
    verified_checkpoints,
)
from mapets_rl.experiment.files import WriteFailed
from mapets_rl.recipes.mapets import MAPETS, MAPETSConfig
from mapets_rl.recipes.mappo import MAPPO, MAPPOConfig
from tests.experiment.test_checkpoint_determinism import _assert_equal
from tests.recipes.test_recipe_mapets import TINY

ROOT = Path(__file__).resolve().parents[2]


class Crash(Exception):
    """Stands for kill -9: the experiment object is dropped where it was."""


def _snapshot(run: Path) -> dict[str, bytes]:
    """Every file under ``run`` (relative path -> bytes)."""
    return {str(p.relative_to(run)): p.read_bytes() for p in sorted(run.rglob("*")) if p.is_file()}


def _csv_steps(run: Path) -> dict[str, list[int]]:
    """Scalar CSV file (relative to ``logs``) -> the steps of its rows, in file order."""
    return {
        str(p.relative_to(run / "logs")): [
            int(line.split(",")[0]) for line in p.read_text().split()
        ]
        for p in sorted((run / "logs").rglob("scalars/**/*.csv"))
    }


def _assert_logs_like(run: Path, reference: Path) -> None:
    steps, expected = _csv_steps(run), _csv_steps(reference)
    assert steps and steps.keys() == expected.keys()
    for name, seen in steps.items():
        assert seen == sorted(set(seen)), f"{name}: steps repeated or out of order: {seen}"
        assert seen == expected[name], name


def _mappo_config(total: int, **extra: Any) -> MAPPOConfig:
    fields = dict(
        env="toy",
        total_frames=total,
        frames_per_batch=20,
        eval_interval=20,
        checkpoint_interval=40,
        minibatch_size=10,
        progress=False,
        logger="csv",
    )
    return MAPPOConfig(**{**fields, **extra})


# ----------------------------------------------------------------- logs after a kill + resume
@pytest.mark.usefixtures("toy_scenario")
def test_mappo_logs_hold_each_step_once_after_a_crash_and_resume(tmp_path: Path) -> None:
    MAPPO(_mappo_config(100), tmp_path / "full").train()
    run = tmp_path / "run"
    MAPPO(_mappo_config(40), run).train()  # checkpoint at 40 frames
    resumed = MAPPO.from_run_dir(run, overrides=["total_frames=100"])
    frames = []

    def crash_at_60(metrics: dict[str, float]) -> None:
        frames.append(resumed.frames)
        if frames[-1] == 60:  # logged 60 (train, timers, eval), checkpoint next at 80
            raise Crash

    with pytest.raises(Crash):
        resumed.train(crash_at_60)
    resumed = None  # dropped where it crashed
    assert [int(p.stem.split("_")[1]) for p in list_checkpoints(run)] == [40]
    MAPPO.from_run_dir(run, overrides=["total_frames=100"]).train()
    _assert_logs_like(run, tmp_path / "full")


def test_mapets_logs_hold_each_step_once_after_a_crash_and_resume(tmp_path: Path) -> None:
    def config(episodes: int) -> MAPETSConfig:
        return MAPETSConfig(**{**TINY, "episodes": episodes, "seed": 5, "logger": "csv"})

    MAPETS(config(2), tmp_path / "full").train()
    run = tmp_path / "run"
    MAPETS(config(1), run).train()
    resumed = MAPETS.from_run_dir(run, overrides=["episodes=2"])

    def crash_before_the_checkpoint() -> None:
        raise Crash  # episode 2 is logged (train, timers, model/nll) and in results.json

    resumed.save_checkpoint = crash_before_the_checkpoint
    with pytest.raises(Crash):
        resumed.train()
    del resumed
    assert [e["metrics"]["episode"] for e in read_results(run)["train"]] == [1.0, 2.0]
    again = MAPETS.from_run_dir(run, overrides=["episodes=2"])
    assert again.episode == 1
    again.train()
    _assert_logs_like(run, tmp_path / "full")
    assert [e["metrics"]["episode"] for e in read_results(run)["train"]] == [1.0, 2.0]


@pytest.mark.usefixtures("toy_scenario")
def test_a_fresh_run_in_a_directory_without_checkpoints_starts_from_empty_logs(
    tmp_path: Path,
) -> None:
    run = tmp_path / "run"
    first = MAPPO(_mappo_config(40, checkpoint_interval=0), run)
    first.save_checkpoint = lambda: (_ for _ in ()).throw(Crash())  # killed before checkpoint

    with pytest.raises(Crash):
        first.train()
    del first
    assert list_checkpoints(run) == [] and _csv_steps(run)
    MAPPO(_mappo_config(40), run).train()
    MAPPO(_mappo_config(40), tmp_path / "clean").train()
    _assert_logs_like(run, tmp_path / "clean")


# ------------------------------------------------------------ a resume override that fails
@pytest.mark.usefixtures("toy_scenario")
def test_a_resume_override_that_fails_in_the_first_iteration_changes_nothing(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    full = MAPPO(_mappo_config(80), tmp_path / "full")
    full.train()
    run = tmp_path / "run"
    MAPPO(_mappo_config(40), run).train()
    before = _snapshot(run)
    train_step = MAPPO.train_step

    def out_of_memory(self: MAPPO, batch: Any) -> dict[str, float]:
        if self.config.keep_last == 5:  # (a resume changes only budget, intervals, ...)
            raise torch.OutOfMemoryError("CUDA out of memory (simulated)")
        return train_step(self, batch)

    monkeypatch.setattr(MAPPO, "train_step", out_of_memory)
    failing = MAPPO.from_run_dir(run, overrides=["total_frames=80", "keep_last=5"])
    with pytest.raises(torch.OutOfMemoryError):
        failing.train()
    del failing
    assert _snapshot(run) == before  # every file, byte for byte
    # a plain resume continues the run as it was configured
    resumed = MAPPO.from_run_dir(run, overrides=["total_frames=80"])
    assert resumed.config.keep_last == 2
    assert resumed.train() == full.results.evaluations
    assert yaml.safe_load((run / "config.yaml").read_text())["total_frames"] == 80
    _assert_equal(
        load_checkpoint(list_checkpoints(run)[-1])["components"],
        load_checkpoint(list_checkpoints(tmp_path / "full")[-1])["components"],
    )


def test_a_mapets_resume_override_that_fails_changes_nothing(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    run = tmp_path / "run"
    MAPETS(MAPETSConfig(**{**TINY, "episodes": 1, "seed": 2}), run).train()
    before = _snapshot(run)
    run_episode = MAPETS.run_episode

    def out_of_memory(self: MAPETS, random_actions: bool) -> Any:
        if self.config.keep_last == 5:  # (a resume changes only budget, intervals, ...)
            raise torch.OutOfMemoryError("CUDA out of memory (simulated)")
        return run_episode(self, random_actions)

    monkeypatch.setattr(MAPETS, "run_episode", out_of_memory)
    failing = MAPETS.from_run_dir(run, overrides=["episodes=2", "keep_last=5"])
    with pytest.raises(torch.OutOfMemoryError):
        failing.train()
    del failing
    assert _snapshot(run) == before
    resumed = MAPETS.from_run_dir(run, overrides=["episodes=2"])
    assert resumed.config.keep_last == 2
    assert [e["metrics"]["episode"] for e in resumed.train()] == [1.0, 2.0]


# ------------------------------------------------------------- MAPPO's trajectory ids continue
@pytest.mark.usefixtures("toy_scenario")
def test_mappo_checkpoint_after_a_resume_equals_the_uninterrupted_one(tmp_path: Path) -> None:
    MAPPO(_mappo_config(80, logger="none"), tmp_path / "full").train()
    run = tmp_path / "run"
    MAPPO(_mappo_config(40, logger="none"), run).train()
    MAPPO.from_run_dir(run, overrides=["total_frames=80"]).train()
    name = "ckpt_000000000080.pt"
    resumed = load_checkpoint(run / "checkpoints" / name)
    full = load_checkpoint(tmp_path / "full" / "checkpoints" / name)
    traj_ids = resumed["components"]["buffer"]["_storage"]["data"]["collector"]["traj_ids"]
    assert int(traj_ids.max()) > 3  # numbered on from the first run's trajectories
    _assert_equal(resumed, full)


# ------------------------------------------------------------------------- a write that fails
_ENTRY_POINT = """
from importlib import metadata
_installed = metadata.entry_points
def _entry_points(**params):
    found = _installed(**params)
    if params.get("group") == "mapets_rl.recipes":
        toy = metadata.EntryPoint("toy", "toy_recipe:ToyLearner", "mapets_rl.recipes")
        return metadata.EntryPoints([*found, toy])
    return found
metadata.entry_points = _entry_points
"""


def _cli_with_file_size_limit(argv: list[str], limit: int) -> subprocess.CompletedProcess:
    """``mapets-rl argv`` in a process whose files may not grow beyond ``limit`` bytes
    (``RLIMIT_FSIZE``; SIGXFSZ ignored, so a write past it fails with EFBIG)."""
    script = "\n".join(
        [
            "import resource, signal, sys",
            f"sys.path.insert(0, {str(ROOT / 'examples' / 'extending')!r})",
            textwrap.dedent(_ENTRY_POINT),
            "from mapets_rl.experiment import register_env",
            "from toy_scenario import ToyAgentsEnv",
            "register_env('toy', ToyAgentsEnv)",
            "signal.signal(signal.SIGXFSZ, signal.SIG_IGN)",
            f"resource.setrlimit(resource.RLIMIT_FSIZE, ({limit}, {limit}))",
            "from mapets_rl.app.cli import main",
            f"sys.exit(main({argv!r}))",
        ]
    )
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    return subprocess.run(
        [sys.executable, "-c", script],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=300,
        env=env,
    )


@pytest.mark.parametrize("recipe", ["toy", "mapets"])
def test_a_write_past_the_file_size_limit_is_one_line_and_keeps_the_checkpoints(
    recipe: str, tmp_path: Path, toy_recipe: None
) -> None:
    run = tmp_path / "run"
    if recipe == "toy":
        from toy_recipe import ToyConfig, ToyLearner

        ToyLearner(ToyConfig(total_frames=40, logger="csv"), run).train()
        resume = ["resume", str(run), "total_frames=80"]
    else:
        # The file-size limit would also stop inductor writing its compiled code (the planner
        # then plans eagerly, with a warning: tests/planning/test_compiled_planner.py): plan
        # eagerly.
        planner = {**TINY["planner"], "compile": False}
        MAPETS(MAPETSConfig(**{**TINY, "episodes": 1, "seed": 4, "planner": planner}), run).train()
        resume = ["resume", str(run), "episodes=2"]
    checkpoints = list_checkpoints(run)
    newest = checkpoints[-1]
    limit = newest.stat().st_size // 2  # the next checkpoint cannot be written
    assert all(
        p.stat().st_size < limit
        for p in run.rglob("*")
        if p.is_file() and p.parent.name != "checkpoints"
    )
    proc = _cli_with_file_size_limit(resume, limit)
    assert proc.returncode == 2, proc.stderr
    assert proc.stderr.count("\n") == 1, proc.stderr
    assert proc.stderr.startswith("mapets-rl: error: cannot write ")
    assert "ckpt_" in proc.stderr and "File too large" in proc.stderr
    assert "Traceback" not in proc.stderr and "unexpected pos" not in proc.stderr
    # the checkpoints written before are there and verify; no partial file is left
    assert verified_checkpoints(run) == list_checkpoints(run)
    assert newest in list_checkpoints(run)
    assert not [p for p in (run / "checkpoints").iterdir() if ".tmp" in p.name]
    cls = MAPETS if recipe == "mapets" else ToyLearner
    resumed = cls.from_run_dir(run, overrides=resume[2:])
    resumed.train()
    assert verified_checkpoints(run) == list_checkpoints(run)


@pytest.mark.usefixtures("toy_scenario")
def test_a_full_disk_is_a_write_failed_naming_the_file(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    run = tmp_path / "run"
    exp = MAPPO(_mappo_config(40, logger="none"), run)
    exp.train()
    kept = _snapshot(run / "checkpoints")
    real_fsync = os.fsync

    def disk_full(fd: int) -> None:
        if os.readlink(f"/proc/self/fd/{fd}").endswith(".pt"):
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        real_fsync(fd)

    monkeypatch.setattr(os, "fsync", disk_full)
    exp.frames = 60
    with pytest.raises(WriteFailed) as err:
        exp.save_checkpoint()
    message = str(err.value)
    assert "\n" not in message and "ckpt_000000000060.pt" in message
    assert "No space left on device" in message and err.value.errno == errno.ENOSPC
    assert _snapshot(run / "checkpoints") == kept
