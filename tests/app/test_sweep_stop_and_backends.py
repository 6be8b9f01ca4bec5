"""Sweeps (issues 51 and 52): the summary options of a brand-new sweep checked before any
trial, a SIGTERM to the sweep driver that stops its trials with a checkpoint (exit 143, no
process left), and the submitit backend (a 2-trial grid on submitit's local executor, skipped
and resumed by re-runs)."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest

from mapets_rl.app import sweep
from mapets_rl.app.sweep import SweepResult, SweepSpec, run_sweep, run_trial
from mapets_rl.experiment import list_checkpoints, read_results
from tests.app.test_sweep import _SWEEP_SCRIPT, _alive
from tests.sweep_helpers import SLOW_ENV

TINY = ["total_frames=20", "frames_per_batch=10", "eval_interval=10", "checkpoint_interval=10"]


@pytest.fixture
def sweep_here(toy_recipe, monkeypatch) -> Callable[..., SweepResult]:
    """``sweep_here(out, **spec fields)``: a toy sweep of seed 0 whose trials run in this
    process (the local backend's pool would spawn one per worker)."""
    monkeypatch.setattr(
        sweep, "run_local", lambda payloads, _: ((i, run_trial(p)) for i, p in enumerate(payloads))
    )

    def run(out: Path, **fields: Any) -> SweepResult:
        spec = {"recipe": "toy", "env": "toy", "seeds": [0], "out": out, "overrides": TINY}
        return run_sweep(SweepSpec(**{**spec, **fields}), echo=lambda _: None)

    return run


# ------------------------------------------------- a brand-new sweep's summary options
def test_a_brand_new_sweep_refuses_an_unknown_metric_before_any_trial(tmp_path, sweep_here):
    out = tmp_path / "sweep"
    refused = r"metrics must be metrics of an evaluation .*'return'.*got \['nosuch'\]"
    with pytest.raises(ValueError, match=refused):
        sweep_here(out, grid={"lr": [0.05, 0.2]}, metrics=["return", "nosuch"])
    assert not out.exists()  # no trial ran, nothing written
    result = sweep_here(out, grid={"lr": [0.05]}, metrics=["return"])
    assert not result.failed and result.summary


# ------------------------------------------------------------- SIGTERM to the driver
@pytest.mark.skipif(not Path("/proc").is_dir(), reason="needs /proc to find the workers")
def test_a_sigterm_to_the_sweep_stops_its_trial_with_a_checkpoint(tmp_path):
    out = tmp_path / "sweep"
    log = tmp_path / "sweep.log"
    budget = ["total_frames=40", "frames_per_batch=10", "checkpoint_interval=10"]
    one_worker = ["--cpus-per-trial", str(os.cpu_count() or 1)]  # seed 1 waits for seed 0
    argv = ["sweep", "slowtoy", "--env", "toy", "--seeds", "0", "1", *budget, *one_worker]
    argv += ["--out", str(out)]
    tests = Path(__file__).resolve().parents[1]
    script = _SWEEP_SCRIPT.format(
        tests=str(tests), extending=str(tests.parent / "examples" / "extending"), argv=argv
    )
    env = {**os.environ, "PYTHONPATH": str(tests.parent), SLOW_ENV: "1.5"}
    with open(log, "w") as fh:
        proc = subprocess.Popen(
            [sys.executable, "-c", script], cwd=tests.parent, env=env, stdout=fh, stderr=fh
        )
    trial = out / "trials" / "seed=0"
    deadline = time.monotonic() + 120
    while not list_checkpoints(trial) and time.monotonic() < deadline and proc.poll() is None:
        time.sleep(0.1)  # the first checkpoint (frame 10): the trial is in its training loop
    assert list_checkpoints(trial), log.read_text()
    worker = json.loads((trial / "trial.json").read_text())["pid"]
    os.kill(proc.pid, signal.SIGTERM)
    try:
        code = proc.wait(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
    deadline = time.monotonic() + 5
    while _alive(worker) and time.monotonic() < deadline:
        time.sleep(0.1)
    orphan = _alive(worker)
    if orphan:
        os.kill(worker, signal.SIGKILL)
    text = log.read_text()
    assert code == 128 + signal.SIGTERM, text
    assert not orphan, "the trial's worker outlived the sweep"
    assert "stopped by SIGTERM" in text and "Traceback" not in text
    record = json.loads((trial / "trial.json").read_text())
    # stopped before its budget of 40 frames, with a checkpoint of the frames it reached
    assert record["state"] == "stopped" and 10 < record["frames"] < 40
    assert list_checkpoints(trial)[-1].name.endswith(f"{record['frames']}.pt")
    manifest = json.loads((out / "sweep.json").read_text())
    assert [t["state"] for t in manifest["trials"]] == ["stopped", "pending"]
    assert not (out / "trials" / "seed=1" / "trial.json").exists()  # never started
    assert "trial seed=1: not started" in text


# ------------------------------------------------------------------ the submitit backend
def test_submitit_backend_runs_a_grid_and_a_rerun_skips_and_resumes(
    tmp_path, toy_recipe, monkeypatch
):
    pytest.importorskip("submitit", reason="the submitit backend needs submitit installed")
    tests = Path(__file__).resolve().parents[1]
    extending = tests.parent / "examples" / "extending"
    # submitit's local jobs are new interpreters: they find the toy recipe on PYTHONPATH
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join([str(extending), str(tests.parent)]))
    monkeypatch.setattr(sweep, "SUBMITIT_POLL_S", 0.2)
    out = tmp_path / "sweep"

    def run(overrides: list[str]) -> SweepResult:
        spec = SweepSpec(
            recipe="toy",
            env="toy",
            seeds=[0],
            grid={"lr": [0.05, 0.2]},
            out=out,
            overrides=overrides,
            backend="submitit",
            executor_params={"cluster": "local", "timeout_min": 5},
        )
        return run_sweep(spec, echo=lambda _: None)

    first = run(TINY)
    assert not first.failed, first.records
    assert {r["state"] for r in first.records.values()} == {"done"}
    assert (out / "submitit").is_dir()  # submitit's job files, beside the trials
    done, cut = (out / "trials" / f"lr={lr}__seed=0" for lr in ("0.05", "0.2"))
    stamp = (done / "results.json").stat().st_mtime_ns
    # `cut` as a job killed after its checkpoint at frame 10 leaves it
    list_checkpoints(cut)[-1].unlink()
    record = json.loads((cut / "trial.json").read_text())
    (cut / "trial.json").write_text(json.dumps({**record, "state": "running"}))
    again = run(TINY)  # the same command: the finished trial is skipped, the other resumed
    assert not again.failed, again.records
    assert again.records["lr=0.05__seed=0"]["ran"] is False
    assert (done / "results.json").stat().st_mtime_ns == stamp
    assert again.records["lr=0.2__seed=0"]["resumed"] is True
    assert [e["frames"] for e in read_results(cut)["evaluations"]] == [10, 20]
    assert [p.name for p in list_checkpoints(cut)] == [p.name for p in list_checkpoints(done)]


def test_submitit_options_are_parsed_and_checked_before_any_trial(tmp_path, toy_recipe):
    pytest.importorskip("submitit", reason="the submitit backend needs submitit installed")
    from mapets_rl.app.cli import build_parser
    from mapets_rl.app.sweep import spec_from_args

    out = tmp_path / "sweep"
    argv = ["sweep", "toy", "--env", "toy", "--out", str(out), "--backend", "submitit"]
    params = ["--executor-param", "cluster=local", "--executor-param", "timeout_min=5"]
    args, _ = build_parser().parse_known_args([*argv, *params])
    assert spec_from_args(args).executor_params == {"cluster": "local", "timeout_min": 5}
    base = {"recipe": "toy", "env": "toy", "seeds": [0], "out": out}
    with pytest.raises(ValueError, match="executor_params must be empty without the submitit"):
        SweepSpec(**base, executor_params={"timeout_min": 5})
    with pytest.raises(ValueError, match="cpus_per_trial must be a whole number >= 1"):
        SweepSpec(**base, backend="submitit", cpus_per_trial=0.5)
    spec = SweepSpec(**base, backend="submitit", executor_params={"cluster": "local", "bogus": 1})
    with pytest.raises(ValueError, match="executor_params .*bogus"):
        run_sweep(spec, echo=lambda _: None)
    assert not (out / "trials").exists() and not (out / "sweep.json").exists()
