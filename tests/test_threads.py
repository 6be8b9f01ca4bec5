"""Thread-count and OpenMP wait-policy choice (mapets_rl.threads)."""

from __future__ import annotations

import json
import multiprocessing
import os
import subprocess
import sys
from pathlib import Path

import pytest

from mapets_rl import threads
from mapets_rl.threads import (
    SUBMITIT_ENV,
    THREADS_ENV,
    choose_threads,
    config_threads,
    configure_threads,
    launched_worker,
    prepare_process,
)

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.parametrize(
    "cpus,load,default,expected",
    [
        (2, 0.2, 2, 2),  # quiet: every core
        (2, 0.9, 2, 1),  # one core busy
        (2, 4.0, 2, 1),  # overloaded: never below one
        (16, 4.2, 16, 12),
        (16, 0.0, 8, 8),  # never above torch's default
    ],
)
def test_thread_count_follows_the_load(cpus, load, default, expected) -> None:
    choice = choose_threads(environ={}, cpus=cpus, load=load, default=default)
    assert choice.threads == expected
    assert f"load average {load:.2f} on {cpus} CPUs" in choice.reason
    assert ("busy" in choice.reason) == (expected < default)


def test_explicit_requests_win_in_order() -> None:
    env = {THREADS_ENV: "3", "OMP_NUM_THREADS": "5"}
    assert choose_threads(2, environ=env, cpus=8, load=0.0).threads == 2
    assert choose_threads(None, environ=env, cpus=8, load=0.0).threads == 3
    omp = choose_threads(None, environ={"OMP_NUM_THREADS": "5"}, cpus=8, load=7.5)
    assert omp.threads is None and "OMP_NUM_THREADS=5" in omp.reason
    assert choose_threads(0, environ={}, cpus=4, load=0.0, default=4).threads == 4  # 0: unset
    # a launcher's worker keeps the count it was given unless it requests one
    worker = choose_threads(None, environ={}, cpus=2, load=5.0, default=2, automatic=False)
    assert worker.threads is None and "launcher's worker" in worker.reason
    assert choose_threads(3, environ={}, automatic=False).threads == 3


@pytest.mark.parametrize("value", ["0", "-1", "two", "1.5"])
def test_bad_thread_counts_are_refused(value) -> None:
    with pytest.raises(ValueError, match=f"{THREADS_ENV} must be an integer >= 1"):
        choose_threads(environ={THREADS_ENV: value})
    with pytest.raises(ValueError, match="threads must be an integer >= 1"):
        choose_threads(-2, environ={})


def test_config_field_names() -> None:
    class Config:
        threads = 0
        num_threads = 3

    assert config_threads(Config()) == 3
    Config.threads = 2
    assert config_threads(Config()) == 2
    assert config_threads(object()) is None


def test_prepare_process_sets_passive_wait_only_when_unset() -> None:
    env: dict[str, str] = {}
    # torch is already imported in the test process: the policy can no longer change, and
    # the thread count stays torch's default
    assert prepare_process(env) == "runtime default" and "OMP_WAIT_POLICY" not in env
    env = {"OMP_WAIT_POLICY": "active", THREADS_ENV: "2"}
    assert prepare_process(env) == "active" and env["OMP_NUM_THREADS"] == "2"


def test_configure_threads_applies_and_logs(monkeypatch, caplog) -> None:
    import torch

    before = torch.get_num_threads()
    monkeypatch.setenv(THREADS_ENV, "1")
    try:
        with caplog.at_level("INFO", logger="mapets_rl.threads"):
            choice = configure_threads()
        assert choice.threads == 1 and torch.get_num_threads() == 1
        assert f"torch threads: 1 ({THREADS_ENV}=1)" in caplog.text
    finally:
        torch.set_num_threads(before)


def test_cli_entry_point_sets_passive_wait_before_torch() -> None:
    """In a fresh process the CLI sets OMP_WAIT_POLICY before torch starts its runtime."""
    env = {k: v for k, v in os.environ.items() if k not in ("OMP_WAIT_POLICY", THREADS_ENV)}
    code = (
        "import os, sys, json\n"
        "from mapets_rl.app import cli\n"
        "try:\n    cli.main(['--help'])\nexcept SystemExit:\n    pass\n"
        "print(json.dumps([os.environ.get('OMP_WAIT_POLICY'), 'torch' in sys.modules]))\n"
    )
    proc = subprocess.run(
        [sys.executable, "-c", code], cwd=ROOT, env=env, capture_output=True, text=True, timeout=60
    )
    assert proc.returncode == 0, proc.stderr
    assert json.loads(proc.stdout.splitlines()[-1]) == ["PASSIVE", False]


@pytest.fixture
def fresh_process(monkeypatch):
    """This process as a fresh one for the thread choice (no choice made or printed yet, no
    request in the environment); torch's thread count is restored afterwards."""
    import torch

    before = torch.get_num_threads()
    monkeypatch.setattr(threads, "_load_choice", None)
    monkeypatch.setattr(threads, "_announced", False)
    for name in (THREADS_ENV, "OMP_NUM_THREADS", SUBMITIT_ENV):
        monkeypatch.delenv(name, raising=False)
    yield
    torch.set_num_threads(before)


def test_the_python_api_chooses_by_the_load_once_and_prints_it_once(
    fresh_process, monkeypatch, toy_recipe, tmp_path, capsys
) -> None:
    """An experiment built through the Python API takes the load's choice as the command does
    (it kept torch's default: 2 spinning threads on 2 busy cores, issue 52); a later one in
    the same process keeps that choice, and the first training showing progress prints it."""
    import torch
    from toy_recipe import ToyConfig, ToyLearner

    monkeypatch.setattr(threads, "available_cpus", lambda: 2)
    monkeypatch.setattr(threads, "load_average", lambda: 1.8)
    torch.set_num_threads(2)
    first = ToyLearner(ToyConfig(progress=True), tmp_path / "a")
    assert first.threads.threads == 1 and first.threads.by_load
    assert torch.get_num_threads() == 1
    monkeypatch.setattr(threads, "load_average", lambda: 0.0)  # this process's own load gone
    torch.set_num_threads(2)
    second = ToyLearner(ToyConfig(progress=True), tmp_path / "b")
    assert second.threads == first.threads and torch.get_num_threads() == 1
    capsys.readouterr()
    first.train()
    second.train()
    err = capsys.readouterr().err
    line = "torch threads: 1 (load average 1.80 on 2 CPUs: busy; MAPETS_RL_THREADS=N"
    assert err.count("torch threads:") == 1 and line in err
    third = ToyLearner(ToyConfig(), tmp_path / "c")
    assert third.threads == first.threads and torch.get_num_threads() == 1
    # an explicit request still wins
    monkeypatch.setenv(THREADS_ENV, "2")
    assert ToyLearner(ToyConfig(), tmp_path / "d").threads.threads == 2
    assert torch.get_num_threads() == 2


def test_a_run_without_progress_prints_no_thread_line(
    fresh_process, toy_recipe, tmp_path, capsys
) -> None:
    from toy_recipe import ToyConfig, ToyLearner

    ToyLearner(ToyConfig(progress=False), tmp_path / "run").train()
    assert "torch threads" not in capsys.readouterr().err
    assert not threads._announced


def _worker_sees() -> tuple[bool, bool]:
    """In a spawned child: whether it counts as a launcher's worker, with and without
    submitit's variable."""
    return launched_worker({}), launched_worker({SUBMITIT_ENV: "local"})


def test_a_launchers_worker_keeps_the_count_it_was_given() -> None:
    """The local sweep's spawned workers and submitit's jobs set their own count (the
    sweep's ``cpus_per_trial``): the load's rule leaves it alone there."""
    assert launched_worker({}) is False  # pytest's own process
    assert launched_worker({SUBMITIT_ENV: "slurm"}) is True
    with multiprocessing.get_context("spawn").Pool(1) as pool:
        assert pool.apply(_worker_sees) == (True, True)
