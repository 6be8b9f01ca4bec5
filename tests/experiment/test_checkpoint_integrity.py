"""Checkpoints verify themselves, resume falls back to the newest good one, and a failed
command never damages a run directory (toy recipe of examples/extending, CLI and Python API)."""

from __future__ import annotations

import logging
import os
import pickle
import signal
import stat
import subprocess
import sys
import textwrap
from collections.abc import Callable
from pathlib import Path

import pytest
import torch
from toy_recipe import ToyConfig, ToyLearner

from mapets_rl.experiment import (
    CheckpointError,
    ConfigError,
    checkpoint_frames,
    checkpoint_problem,
    digest_path,
    file_sha256,
    latest_checkpoint,
    list_checkpoints,
    load_checkpoint,
    load_latest_checkpoint,
    read_results,
    remove_stale_files,
    save_checkpoint,
    verified_checkpoints,
)
from tests.cli_run import run_cli
from tests.experiment.test_experiment import _params

ROOT = Path(__file__).resolve().parents[2]

pytestmark = pytest.mark.usefixtures("toy_scenario")


def _trained(tmp_path: Path, frames: int = 40) -> Path:
    """A toy run stopped at ``frames`` with checkpoints at 20 and 40 frames."""
    run = tmp_path / "run"
    ToyLearner(ToyConfig(total_frames=frames), run).train()
    assert [p.name for p in list_checkpoints(run)] == [
        "ckpt_000000000020.pt",
        "ckpt_000000000040.pt",
    ]
    return run


def test_a_checkpoints_name_gives_the_frames_its_run_resumes_at(tmp_path: Path) -> None:
    run = _trained(tmp_path)
    assert [checkpoint_frames(p) for p in list_checkpoints(run)] == [20, 40]
    resumed = ToyLearner.from_run_dir(run)
    resumed.close()
    assert resumed.frames == checkpoint_frames(latest_checkpoint(run))
    with pytest.raises(ValueError, match="results.json.*not named like a checkpoint"):
        checkpoint_frames(run / "results.json")


# --------------------------------------------------------------------- ways to break a file
def _flip_byte(path: Path) -> None:
    data = bytearray(path.read_bytes())
    data[len(data) // 2] ^= 0xFF  # inside the tensor records of the zip archive
    path.write_bytes(bytes(data))


def _truncate(path: Path) -> None:
    path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])


def _empty(path: Path) -> None:
    path.write_bytes(b"")


def _garbage(path: Path) -> None:
    path.write_bytes(os.urandom(4096))


class _Payload:
    marker: Path

    def __reduce__(self):
        return (os.system, (f"touch {self.marker}",))


def _pickle_payload_with_digest(path: Path) -> None:
    """Replace the checkpoint by a pickle with a code payload AND a matching digest."""
    torch.save({"recipe": "toy", "x": _Payload()}, path)
    digest_path(path).write_text(f"{file_sha256(path)}  {path.name}\n")


BREAKERS: dict[str, tuple[Callable[[Path], None], str]] = {
    "flipped byte": (_flip_byte, "does not match its SHA-256 digest"),
    "truncated": (_truncate, "does not match its SHA-256 digest"),
    "empty": (_empty, "does not match its SHA-256 digest"),
    "garbage": (_garbage, "does not match its SHA-256 digest"),
    "bad digest file": (
        lambda p: digest_path(p).write_text("not a digest\n"),
        "does not hold the SHA-256 digest",
    ),
    "pickle payload": (_pickle_payload_with_digest, "not a checkpoint this library wrote"),
}


@pytest.fixture
def marker(tmp_path: Path, monkeypatch) -> Path:
    path = tmp_path / "payload-ran"
    monkeypatch.setattr(_Payload, "marker", path, raising=False)
    return path


# ------------------------------------------------------------------ load_checkpoint refuses
@pytest.mark.parametrize("kind", sorted(BREAKERS))
def test_broken_checkpoint_is_refused_with_one_line_naming_it(
    tmp_path: Path, kind: str, marker: Path
) -> None:
    path = save_checkpoint({"w": torch.arange(1000.0), "step": 7}, tmp_path, 7)
    breaker, reason = BREAKERS[kind]
    breaker(path)
    with pytest.raises(CheckpointError, match=reason) as err:
        load_checkpoint(path)
    message = str(err.value)
    assert path.name in message and "\n" not in message
    assert "weights_only" not in message
    assert not marker.exists()


def test_checkpoint_without_digest_file_loads_with_a_warning(tmp_path: Path, caplog) -> None:
    """Checkpoints written before digests existed stay loadable (weights-only)."""
    path = save_checkpoint({"w": torch.ones(2), "step": 3}, tmp_path, 3)
    digest_path(path).unlink()
    with caplog.at_level(logging.WARNING, logger="mapets_rl"):
        assert load_checkpoint(path)["step"] == 3
    assert any("has no digest file" in r.getMessage() for r in caplog.records)


def test_pickle_payload_is_refused_with_or_without_a_digest(tmp_path: Path, marker: Path) -> None:
    path = tmp_path / "checkpoints" / "ckpt_000000000001.pt"
    path.parent.mkdir()
    with open(path, "wb") as fh:
        pickle.dump({"x": _Payload()}, fh)
    for breaker in (lambda p: None, _pickle_payload_with_digest):
        breaker(path)
        with pytest.raises(CheckpointError):
            load_checkpoint(path)
    assert not marker.exists()


# ------------------------------------------------------------------- fallback on resume
@pytest.mark.parametrize("kind", sorted(BREAKERS))
def test_resume_falls_back_to_the_previous_good_checkpoint(
    tmp_path: Path, kind: str, marker: Path, caplog
) -> None:
    full = ToyLearner(ToyConfig(), tmp_path / "full")
    full_evals = full.train()
    run = _trained(tmp_path)
    newest = list_checkpoints(run)[-1]
    BREAKERS[kind][0](newest)
    with caplog.at_level(logging.WARNING, logger="mapets_rl"):
        resumed = ToyLearner.from_run_dir(run, overrides=["total_frames=60"])
    assert resumed.frames == 20  # the older checkpoint
    skipped = [r.getMessage() for r in caplog.records if "skipped" in r.getMessage()]
    assert len(skipped) == 1 and newest.name in skipped[0] and "\n" not in skipped[0]
    assert not marker.exists()
    # the resumed run finishes exactly like an uninterrupted one
    assert resumed.train() == full_evals
    assert torch.equal(_params(resumed), _params(full))


def test_cli_evaluate_skips_a_tampered_checkpoint_with_one_warning_line(
    tmp_path: Path, toy_recipe, capsys
) -> None:
    run = _trained(tmp_path)
    code, _, err = run_cli(["evaluate", str(run)], capsys)
    assert code == 0 and err == ""
    _flip_byte(list_checkpoints(run)[-1])
    code, out, err = run_cli(["evaluate", str(run)], capsys)
    assert code == 0 and '"frames": 20' in out
    assert err.count("\n") == 1 and err.startswith("mapets-rl: warning: checkpoint")
    assert "ckpt_000000000040.pt' does not match its SHA-256 digest" in err
    assert err.endswith("; skipped\n")


def test_no_checkpoint_verifies_fails_with_one_line(tmp_path: Path, toy_recipe, capsys) -> None:
    run = _trained(tmp_path)
    for path, breaker in zip(list_checkpoints(run), (_truncate, _garbage), strict=True):
        breaker(path)
    with pytest.raises(CheckpointError, match="none of the 2 checkpoints"):
        load_latest_checkpoint(run)
    capsys.readouterr()
    for command in ("resume", "evaluate"):
        code, _, err = run_cli([command, str(run)], capsys)
        lines = err.splitlines()
        assert code == 2 and lines[-1].startswith("mapets-rl: error: none of the 2 checkpoints")
        assert len(lines) == 3 and all(
            x.startswith("mapets-rl: warning: checkpoint") and x.endswith("; skipped")
            for x in lines[:2]
        )


# ---------------------------------------------------------- temp files and permissions
def test_stale_temp_files_and_orphan_digests_are_removed_on_the_next_start(tmp_path: Path) -> None:
    run = _trained(tmp_path)
    ckpt_dir = run / "checkpoints"
    stale = [
        ckpt_dir / ".ckpt_000000000060.pt.abcd1234.tmp",  # an older writer's temp file
        ckpt_dir / ".ckpt_000000000060.pt.k2j4h5g6.tmp.pt",
        ckpt_dir / "ckpt_000000000060.pt.sha256",  # digest of a checkpoint never renamed
        run / ".results.json.zz99yy88.tmp.json",
    ]
    for path in stale:
        path.write_text("x")
    keep = run / "notes.txt"
    keep.write_text("mine")
    resumed = ToyLearner.from_run_dir(run)
    assert not any(p.exists() for p in stale) and keep.read_text() == "mine"
    assert resumed.frames == 40
    assert remove_stale_files(run) == []


def test_checkpoints_have_the_permissions_of_every_other_file(tmp_path: Path) -> None:
    run = _trained(tmp_path)
    mode = stat.S_IMODE((run / "config.yaml").stat().st_mode)
    for path in [
        *list_checkpoints(run),
        *map(digest_path, list_checkpoints(run)),
        run / "results.json",
        run / "run.json",
    ]:
        assert stat.S_IMODE(path.stat().st_mode) == mode, path.name
    umask = os.umask(0)
    os.umask(umask)
    assert mode == 0o666 & ~umask


# -------------------------------------------------- a failed resume leaves the run usable
@pytest.mark.parametrize(
    "override, needle",
    [
        ("env_config.n_agents=2", "cannot resume with env_config.n_agents changed"),
        ("env=freeway", "env cannot change when resuming"),
        ("device=bogus", "device must be one of"),
        ("lr=.inf", "lr must be a finite number"),
        ("nope=1", "unknown config key 'nope'"),
    ],
)
def test_failed_resume_leaves_the_run_directory_usable(
    tmp_path: Path, toy_recipe, capsys, override: str, needle: str
) -> None:
    run = _trained(tmp_path)
    before = {
        p.relative_to(run): p.read_bytes()
        for p in run.rglob("*")
        if p.is_file() and "logs" not in p.parts
    }
    code, _, err = run_cli(["resume", str(run), override, "total_frames=60"], capsys)
    assert code == 2 and err.count("\n") == 1 and needle in err, err
    after = {
        p.relative_to(run): p.read_bytes()
        for p in run.rglob("*")
        if p.is_file() and "logs" not in p.parts
    }
    assert after == before  # nothing was rewritten
    code, out, _ = run_cli(["resume", str(run), "total_frames=60"], capsys)
    assert code == 0 and '"frames": 60' in out
    code, out, _ = run_cli(["evaluate", str(run)], capsys)
    assert code == 0
    assert [e["frames"] for e in read_results(run)["evaluations"]] == [20, 40, 60]


def test_override_that_keeps_shapes_is_saved_after_the_restore(tmp_path: Path) -> None:
    # (a resume may change only the budget, the intervals and keep_last, device, logger,
    # progress, video: issue 51)
    run = _trained(tmp_path)
    resumed = ToyLearner.from_run_dir(run, overrides=["total_frames=60", "keep_last=3"])
    assert resumed.frames == 40 and resumed.config.keep_last == 3
    # the old config stays until the resumed run has started (issue 23: a resume that fails
    # in its first iteration leaves the run directory as it was)
    assert "keep_last: 2" in (run / "config.yaml").read_text()
    resumed.train()
    assert "keep_last: 3" in (run / "config.yaml").read_text()


@pytest.mark.parametrize(
    "content, needle",
    [
        ("lr: [1, 2\n", "is not valid YAML"),
        ("- a\n- b\n", "must hold a mapping"),
        ("lr: 0.05\n", "is incomplete"),
        ("episodes: 3\ncomm_range: 100\n", "is not a 'toy' config"),
    ],
)
def test_malformed_config_yaml_gives_one_line_naming_it(
    tmp_path: Path, toy_recipe, capsys, content: str, needle: str
) -> None:
    run = _trained(tmp_path)
    (run / "config.yaml").write_text(content)
    code, _, err = run_cli(["resume", str(run)], capsys)
    assert code == 2 and err.count("\n") == 1 and needle in err and "config.yaml" in err
    with pytest.raises(ConfigError, match=needle):
        ToyLearner.from_run_dir(run)


@pytest.mark.parametrize(
    "content, needle",
    [
        ('{"recipe": "toy"', "is not valid JSON"),
        ('{"env": "toy"}', "does not name the run's recipe"),
        ("[1, 2]", "must hold a JSON object"),
        ("", "is not valid JSON"),
    ],
)
def test_malformed_run_json_gives_one_line_naming_it(
    tmp_path: Path, toy_recipe, capsys, content: str, needle: str
) -> None:
    run = _trained(tmp_path)
    (run / "run.json").write_text(content)
    for command in ("resume", "evaluate"):
        code, _, err = run_cli([command, str(run)], capsys)
        assert code == 2 and err.count("\n") == 1 and needle in err and "run.json" in err


def test_failed_train_leaves_no_half_made_run_dir(tmp_path: Path, toy_recipe, capsys) -> None:
    run = tmp_path / "new"
    for env, override in (("toy", "logger=wandb"), ("figure-eight", "env_config.max_speed=-5")):
        code, _, err = run_cli(
            ["train", "toy", "--env", env, "--run-dir", str(run), override], capsys
        )
        assert code == 2 and err.count("\n") == 1
        assert not run.exists()


def test_resume_of_a_real_scenario_refuses_another_agent_count(tmp_path: Path, capsys) -> None:
    run = str(tmp_path / "mappo")
    tiny = [
        "total_frames=20",
        "frames_per_batch=10",
        "minibatch_size=10",
        "eval_interval=0",
        "checkpoint_interval=10",
        "env_config.horizon=10",
        "env_config.n_hvs=2",
        "progress=false",
        "logger=none",
    ]
    code, _, _ = run_cli(
        ["train", "mappo", "--env", "figure-eight", "--run-dir", run, *tiny], capsys
    )
    assert code == 0
    config = (tmp_path / "mappo" / "config.yaml").read_bytes()
    for override, needle in (
        ("env_config.n_cavs=4", "env_config.n_cavs changed"),
        ("num_cells=[32]", "num_cells changed"),
    ):
        code, _, err = run_cli(["resume", run, override, "total_frames=30"], capsys)
        assert code == 2 and err.count("\n") == 1 and needle in err, err
        assert (tmp_path / "mappo" / "config.yaml").read_bytes() == config
    code, out, _ = run_cli(["resume", run, "total_frames=30"], capsys)
    assert code == 0 and '"frames": 30' in out


def test_keys_missing_from_config_yaml_can_be_given_as_overrides(tmp_path: Path) -> None:
    run = _trained(tmp_path)
    path = run / "config.yaml"
    path.write_text(
        "".join(
            line
            for line in path.read_text().splitlines(keepends=True)
            if not line.startswith("lr:")
        )
    )
    with pytest.raises(ConfigError, match=r"lacks the keys \['lr'\]"):
        ToyLearner.from_run_dir(run)
    resumed = ToyLearner.from_run_dir(run, overrides=["lr=0.05"])
    assert resumed.frames == 40 and "lr: 0.05" in path.read_text()


# ------------------------------------------------------------ kill -9 while writing a checkpoint
KILLERS = {
    # the process dies inside torch.save of the second checkpoint (a half-written temp file)
    "inside torch.save": """
        real_save = torch.save
        calls = []
        def dying_save(obj, fh, *args, **kwargs):
            calls.append(1)
            if len(calls) == 2:
                fh.write(b"half a checkpoint")
                fh.flush()
                os.kill(os.getpid(), signal.SIGKILL)
            real_save(obj, fh, *args, **kwargs)
        torch.save = dying_save
    """,
    # the process dies after the second checkpoint's digest, before its rename
    "before the rename": """
        real_replace = os.replace
        def dying_replace(src, dst):
            if str(dst).endswith("ckpt_000000000040.pt"):
                os.kill(os.getpid(), signal.SIGKILL)
            real_replace(src, dst)
        os.replace = dying_replace
    """,
}


@pytest.mark.parametrize("moment", sorted(KILLERS))
def test_kill_9_during_a_checkpoint_write_resumes_bit_exactly(tmp_path: Path, moment: str) -> None:
    full = ToyLearner(ToyConfig(), tmp_path / "full")
    full_evals = full.train()
    run = tmp_path / "killed"
    script = "\n".join(
        [
            "import os, signal, sys",
            f"sys.path.insert(0, {str(ROOT / 'examples' / 'extending')!r})",
            "import torch",
            "from mapets_rl.experiment import register_env",
            "from toy_recipe import ToyConfig, ToyLearner",
            "from toy_scenario import ToyAgentsEnv",
            "register_env('toy', ToyAgentsEnv)",
            textwrap.dedent(KILLERS[moment]),
            f"ToyLearner(ToyConfig(), {str(run)!r}).train()",
        ]
    )
    proc = subprocess.run(
        [sys.executable, "-c", script], cwd=ROOT, capture_output=True, text=True, timeout=300
    )
    assert proc.returncode == -signal.SIGKILL, proc.stderr
    assert [p.name for p in list_checkpoints(run)] == ["ckpt_000000000020.pt"]
    leftovers = sorted(
        p.name
        for p in (run / "checkpoints").iterdir()
        if p.name not in ("ckpt_000000000020.pt", "ckpt_000000000020.pt.sha256")
    )
    assert leftovers  # a temp file (and, before the rename, the new digest) left behind
    resumed = ToyLearner.from_run_dir(run, overrides=["total_frames=60"])
    assert resumed.frames == 20
    assert all(not (run / "checkpoints" / name).exists() for name in leftovers)
    assert resumed.train() == full_evals
    assert torch.equal(_params(resumed), _params(full))


# ------------------------------------------------------------ a bogus "newest" checkpoint
BOGUS = "ckpt_999999999999.pt"


def _bogus_garbage(run: Path) -> None:
    (run / "checkpoints" / BOGUS).write_bytes(os.urandom(4096))


def _bogus_garbage_with_wrong_digest(run: Path) -> None:
    path = run / "checkpoints" / BOGUS
    path.write_bytes(os.urandom(4096))
    digest_path(path).write_text(f"{'0' * 64}  {BOGUS}\n")


def _bogus_copy_of_a_real_one(run: Path) -> None:
    """A real checkpoint and its digest copied under the bogus name (the digest names the
    original file)."""
    real = list_checkpoints(run)[0]
    (run / "checkpoints" / BOGUS).write_bytes(real.read_bytes())
    digest_path(run / "checkpoints" / BOGUS).write_text(digest_path(real).read_text())


BOGUS_KINDS: dict[str, tuple[Callable[[Path], None], str]] = {
    "garbage": (_bogus_garbage, "has no digest file ckpt_999999999999.pt.sha256 and is not an "),
    "wrong digest": (_bogus_garbage_with_wrong_digest, "does not match its SHA-256 digest"),
    "copy": (_bogus_copy_of_a_real_one, "does not hold the SHA-256 digest of " + BOGUS),
}


@pytest.mark.parametrize("kind", sorted(BOGUS_KINDS))
def test_a_bogus_newest_checkpoint_is_ranked_by_what_verifies(
    tmp_path: Path, kind: str, caplog
) -> None:
    """A stray ``ckpt_999999999999.pt`` is neither "newest" nor counted by pruning; what is
    wrong with it is reported in one line (and it is never unpickled)."""
    run = _trained(tmp_path)
    make, reason = BOGUS_KINDS[kind]
    make(run)
    bogus = run / "checkpoints" / BOGUS
    ckpt_40 = run / "checkpoints" / "ckpt_000000000040.pt"
    assert list_checkpoints(run)[-1] == bogus  # newest by name ...
    assert latest_checkpoint(run) == ckpt_40  # ... but not by what verifies
    assert verified_checkpoints(run) == list_checkpoints(run)[:2]
    problem = checkpoint_problem(bogus)
    assert problem is not None and reason in problem and "\n" not in problem
    assert "pickled Python objects" not in problem
    assert checkpoint_problem(ckpt_40) is None
    with caplog.at_level(logging.WARNING, logger="mapets_rl"):
        path, state = load_latest_checkpoint(run)
    assert path == ckpt_40 and state["frames"] == 40
    warnings = [r.getMessage() for r in caplog.records]
    assert len(warnings) == 1 and BOGUS in warnings[0] and reason in warnings[0], warnings
    assert "pickled Python objects" not in warnings[0]
    # resuming writes two more checkpoints: pruning keeps the two newest real ones (the bogus
    # file is not one of them), reports the bogus file once and leaves it in place
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="mapets_rl"):
        resumed = ToyLearner.from_run_dir(run, overrides=["total_frames=80"])
        assert resumed.frames == 40
        resumed.train()
    assert [p.name for p in list_checkpoints(run)] == [
        "ckpt_000000000060.pt",
        "ckpt_000000000080.pt",
        BOGUS,
    ]
    assert latest_checkpoint(run).name == "ckpt_000000000080.pt"
    pruning = [r.getMessage() for r in caplog.records if "not counted" in r.getMessage()]
    assert len(pruning) == 1 and BOGUS in pruning[0] and reason in pruning[0], pruning
    assert ToyLearner.from_run_dir(run).frames == 80


def test_cli_evaluate_names_what_is_wrong_with_a_bogus_checkpoint(
    tmp_path: Path, toy_recipe, capsys
) -> None:
    run = _trained(tmp_path)
    _bogus_garbage(run)
    code, out, err = run_cli(["evaluate", str(run)], capsys)
    assert code == 0 and '"frames": 40' in out
    assert err.count("\n") == 1 and BOGUS in err and "is not an archive torch.save writes" in err
