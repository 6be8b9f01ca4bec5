"""One writer per run directory: an OS lock (``flock`` on ``RUN_DIR/.lock``) taken before
anything is written, held for the life of a run, refused with one line naming the holder's pid,
and never left stale (it dies with its process, kill -9 included)."""

from __future__ import annotations

import gc
import json
import os
import signal
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest
import yaml
from toy_recipe import ToyConfig, ToyLearner

from mapets_rl.experiment import list_checkpoints
from mapets_rl.experiment.files import LOCK_FILE, RunDirLock, RunDirLocked
from tests.cli_run import run_cli

ROOT = Path(__file__).resolve().parents[2]

pytestmark = pytest.mark.usefixtures("toy_scenario")


def _snapshot(run: Path) -> dict[str, bytes]:
    """Every file under ``run`` (relative path -> bytes)."""
    return {str(p.relative_to(run)): p.read_bytes() for p in sorted(run.rglob("*")) if p.is_file()}


def _holder(run: Path) -> subprocess.Popen:
    """A process that takes ``run``'s lock, says ``locked`` and then waits (until killed or
    its stdin closes)."""
    code = textwrap.dedent(
        f"""
        import sys
        from mapets_rl.experiment.files import RunDirLock
        lock = RunDirLock.acquire({str(run)!r})
        print("locked", flush=True)
        sys.stdin.read()
        """
    )
    proc = subprocess.Popen(
        [sys.executable, "-c", code],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
        cwd=ROOT,
    )
    assert proc.stdout.readline().strip() == "locked"
    return proc


# ------------------------------------------------------------------------- in one process
def test_second_experiment_on_the_same_run_dir_is_refused_and_changes_nothing(
    tmp_path: Path,
) -> None:
    run = tmp_path / "run"
    first = ToyLearner(ToyConfig(seed=0, total_frames=40), run)
    before = _snapshot(run)
    assert (run / LOCK_FILE).read_text().strip() == str(os.getpid())
    with pytest.raises(RunDirLocked) as err:
        ToyLearner(ToyConfig(seed=1, total_frames=40), run)
    message = str(err.value)
    assert "\n" not in message and f"pid {os.getpid()}" in message and str(run) in message
    assert _snapshot(run) == before  # not a byte written by the second writer
    # the first run is not mixed with the refused one: its config, run.json, results, checkpoints
    first.train()
    assert yaml.safe_load((run / "config.yaml").read_text())["seed"] == 0
    assert json.loads((run / "run.json").read_text())["seed"] == 0
    assert json.loads((run / "results.json").read_text())["seed"] == 0
    assert [p.name for p in list_checkpoints(run)] == [
        "ckpt_000000000020.pt",
        "ckpt_000000000040.pt",
    ]
    # train() released the lock: the run can be resumed in this process
    resumed = ToyLearner.from_run_dir(run, overrides=["total_frames=60"])
    assert resumed.frames == 40
    # ... and while the resumed experiment lives, nobody else may write there
    with pytest.raises(RunDirLocked, match=f"pid {os.getpid()}"):
        ToyLearner.from_run_dir(run)
    resumed.train()
    assert resumed.frames == 60 and (run / LOCK_FILE).read_text().strip() == ""


def test_close_context_manager_and_garbage_collection_release_the_lock(tmp_path: Path) -> None:
    run = tmp_path / "run"
    exp = ToyLearner(ToyConfig(), run)
    exp.close()
    exp.close()  # idempotent
    with ToyLearner.from_run_dir(run, load=False) as again:
        with pytest.raises(RunDirLocked):
            ToyLearner.from_run_dir(run, load=False)
    assert again._lock is None
    held = ToyLearner.from_run_dir(run, load=False)
    del held
    gc.collect()
    ToyLearner.from_run_dir(run, load=False).close()
    # save_checkpoint outside train() takes the lock again
    exp.save_checkpoint()
    with pytest.raises(RunDirLocked):
        ToyLearner.from_run_dir(run)
    exp.close()
    assert ToyLearner.from_run_dir(run).frames == 0


def test_a_construction_that_fails_releases_the_lock_at_once(tmp_path: Path) -> None:
    class Broken(ToyLearner):
        def __init__(self, config: ToyConfig, run_dir: Path) -> None:
            super().__init__(config, run_dir)
            raise ValueError("broken after the run directory was prepared")

    run = tmp_path / "run"
    with pytest.raises(ValueError, match="broken after") as err:
        Broken(ToyConfig(), run)
    assert err.value.__traceback__ is not None  # the frames (and the instance) are still alive
    ToyLearner(ToyConfig(), run).close()  # not refused by the failed one


def test_failed_resume_releases_the_lock(tmp_path: Path) -> None:
    run = tmp_path / "run"
    ToyLearner(ToyConfig(total_frames=20), run).train()
    with pytest.raises(ValueError, match="unknown config key"):
        ToyLearner.from_run_dir(run, overrides=["nope=1"])
    ToyLearner.from_run_dir(run).close()


def test_a_directory_that_is_not_a_run_gets_no_lock_file(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="has no config.yaml"):
        ToyLearner.from_run_dir(tmp_path)
    assert list(tmp_path.iterdir()) == []


# -------------------------------------------------------------------- another process
def test_a_lock_held_by_another_process_refuses_every_writer_naming_its_pid(
    tmp_path: Path, toy_recipe, capsys
) -> None:
    run = tmp_path / "run"
    ToyLearner(ToyConfig(total_frames=20), run).train()
    before = _snapshot(run)
    holder = _holder(run)
    try:
        with pytest.raises(RunDirLocked) as err:
            ToyLearner.from_run_dir(run, overrides=["total_frames=40"])
        assert f"pid {holder.pid} holds" in str(err.value) and "\n" not in str(err.value)
        for argv in (
            ["resume", str(run), "total_frames=40"],
            ["evaluate", str(run)],
            ["train", "toy", "--env", "toy", "--run-dir", str(run)],
        ):
            code, out, err_text = run_cli(argv, capsys)
            assert code == 2 and out == "", argv
            assert err_text.count("\n") == 1 and err_text.startswith("mapets-rl: error: ")
            if argv[0] != "train":  # train first refuses a directory that holds checkpoints
                assert f"pid {holder.pid}" in err_text, err_text
        after = _snapshot(run)
        assert after.pop(LOCK_FILE).split() == [str(holder.pid).encode()]
        assert after == {k: v for k, v in before.items() if k != LOCK_FILE}
    finally:
        holder.stdin.close()
        holder.wait(timeout=60)
    # the holder exited: the lock went with it
    code, out, _ = run_cli(["resume", str(run), "total_frames=40"], capsys)
    assert code == 0 and '"frames": 40' in out


def test_a_new_run_into_a_locked_directory_writes_nothing(
    tmp_path: Path, toy_recipe, capsys
) -> None:
    """Two ``train`` into one new directory: the second is refused before writing."""
    run = tmp_path / "run"
    run.mkdir()
    holder = _holder(run)
    try:
        code, _, err = run_cli(["train", "toy", "--env", "toy", "--run-dir", str(run)], capsys)
        assert code == 2 and err.count("\n") == 1 and f"pid {holder.pid}" in err
        assert [p.name for p in run.iterdir()] == [LOCK_FILE]
    finally:
        holder.stdin.close()
        holder.wait(timeout=60)


def test_kill_9_of_the_holder_leaves_no_stale_lock(tmp_path: Path) -> None:
    run = tmp_path / "run"
    ToyLearner(ToyConfig(total_frames=20), run).train()
    holder = _holder(run)
    with pytest.raises(RunDirLocked, match=f"pid {holder.pid}"):
        ToyLearner.from_run_dir(run)
    holder.send_signal(signal.SIGKILL)
    assert holder.wait(timeout=60) == -signal.SIGKILL
    assert (run / LOCK_FILE).read_text().strip() == str(holder.pid)  # its pid is left, not lock
    resumed = ToyLearner.from_run_dir(run, overrides=["total_frames=40"])
    assert (run / LOCK_FILE).read_text().strip() == str(os.getpid())
    resumed.train()
    assert resumed.frames == 40


def test_run_dir_lock_protocol(tmp_path: Path) -> None:
    with RunDirLock.acquire(tmp_path) as lock:
        assert lock.held and (tmp_path / LOCK_FILE).read_text().strip() == str(os.getpid())
        with pytest.raises(RunDirLocked, match="this process"):
            RunDirLock.acquire(tmp_path)
    assert not lock.held and (tmp_path / LOCK_FILE).read_text().strip() == ""
    RunDirLock.acquire(tmp_path).release()
    with pytest.raises(ValueError, match="cannot be locked"):
        RunDirLock.acquire(tmp_path / "missing")


def test_a_run_without_a_run_dir_names_the_one_it_writes(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """The Python API without ``run_dir`` writes ``./runs/...`` and says so in one line on
    stderr; with a ``run_dir`` the caller chose, it says nothing."""
    monkeypatch.chdir(tmp_path)
    with ToyLearner(ToyConfig(env="toy")) as exp:
        pass
    out, err = capsys.readouterr()
    assert exp.run_dir.parent == Path("runs") and (tmp_path / exp.run_dir).is_dir()
    assert err == f"toy: writing the run to {exp.run_dir}\n" and out == ""
    with ToyLearner(ToyConfig(env="toy"), tmp_path / "chosen"):
        pass
    assert capsys.readouterr() == ("", "")
