"""Issue 51 (reliability, round four): each case a test that failed before its fix.

No write through a link: the logs a run appends to (the CSV scalars, ``train_episodes.jsonl``)
are never opened through a symbolic or hard link, so a resume never writes outside its run
directory.
"""

from __future__ import annotations

import os
from pathlib import Path

import pytest
from toy_recipe import ToyConfig, ToyLearner

from mapets_rl.experiment.episodes import TRAIN_EPISODES_FILE
from mapets_rl.experiment.files import open_append
from tests.cli_run import run_cli


# ------------------------------------------------------------- no append through a link
@pytest.fixture
def csv_toy_run(tmp_path, toy_scenario) -> Path:
    """A finished 20-frame toy run logging CSV scalars."""
    run_dir = tmp_path / "run"
    ToyLearner(ToyConfig(total_frames=20, logger="csv"), run_dir).train()
    return run_dir


def _reward_csv(run_dir: Path) -> Path:
    return run_dir / "logs" / "toy_toy" / "scalars" / "eval" / "reward.csv"


@pytest.mark.parametrize("target", ["victim", "empty victim", "dangling"])
def test_a_resume_never_appends_through_a_symlinked_csv_log(tmp_path, csv_toy_run, target):
    victim = tmp_path / "victim.csv"
    if target != "dangling":
        victim.write_text("" if target == "empty victim" else "0,1.0\n")
    log = _reward_csv(csv_toy_run)
    log.unlink()
    log.symlink_to(victim)
    resumed = ToyLearner.from_run_dir(csv_toy_run, ["total_frames=40"])
    resumed.train()
    assert resumed.frames == 40
    if target == "dangling":
        assert not victim.exists()
    else:
        assert victim.read_text() == ("" if target == "empty victim" else "0,1.0\n")
    assert not log.is_symlink() and log.read_text().splitlines()[-1].startswith("40,")


def test_a_resume_never_appends_through_a_hard_linked_csv_log(tmp_path, csv_toy_run):
    log = _reward_csv(csv_toy_run)
    victim = tmp_path / "victim.csv"
    victim.write_text(log.read_text())
    log.unlink()
    os.link(victim, log)
    before = victim.read_text()
    ToyLearner.from_run_dir(csv_toy_run, ["total_frames=40"]).train()
    assert victim.read_text() == before
    assert os.stat(log).st_nlink == 1 and log.read_text().startswith(before)


@pytest.mark.parametrize("dangling", [False, True])
def test_a_resume_never_appends_through_a_symlinked_episode_log(tmp_path, csv_toy_run, dangling):
    victim = tmp_path / "victim.jsonl"
    if not dangling:
        victim.write_text('{"frames": 0}\n')
    episodes = csv_toy_run / TRAIN_EPISODES_FILE
    episodes.unlink()
    episodes.symlink_to(victim)
    ToyLearner.from_run_dir(csv_toy_run, ["total_frames=40"]).train()
    assert not victim.exists() if dangling else victim.read_text() == '{"frames": 0}\n'
    assert not episodes.is_symlink() and episodes.is_file()


@pytest.mark.parametrize("kind", ["symlink", "hard link", "fifo"])
def test_open_append_refuses_a_file_that_is_not_a_plain_one_of_ours(tmp_path, kind):
    victim = tmp_path / "victim"
    victim.write_text("precious\n")
    path = tmp_path / "log.csv"
    {"symlink": path.symlink_to, "hard link": lambda v: os.link(v, path)}.get(
        kind, lambda _: os.mkfifo(path)
    )(victim)
    with pytest.raises(ValueError, match="cannot append to .*log.csv.* it ") as err:
        open_append(path)
    assert "\n" not in str(err.value)
    assert victim.read_text() == "precious\n"


# ------------------------------------------------- --out of compare and sweep is no run dir
def _files(folder: Path) -> dict[Path, bytes]:
    return {p: p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


@pytest.mark.parametrize("inside", [False, True])
def test_compare_refuses_an_out_in_a_run_directory(tmp_path, csv_toy_run, capsys, inside):
    other = tmp_path / "other"
    ToyLearner(ToyConfig(total_frames=20), other).train()
    before = _files(other)
    out = other / "figures" if inside else other
    code, _, err = run_cli(["compare", str(csv_toy_run), "--out", str(out)], capsys)
    assert code == 2 and err.count("\n") == 1, err
    assert "is a run directory (it holds run.json)" in err
    assert _files(other) == before


def test_sweep_refuses_an_out_that_is_a_run_directory(tmp_path, csv_toy_run, toy_recipe, capsys):
    before = _files(csv_toy_run)
    argv = ["sweep", "toy", "--env", "toy", "--seeds", "0", "--out", str(csv_toy_run)]
    code, _, err = run_cli([*argv, "total_frames=20"], capsys)
    assert code == 2 and err.count("\n") == 1, err
    assert "out" in err and "is a run directory (it holds run.json)" in err
    assert _files(csv_toy_run) == before
