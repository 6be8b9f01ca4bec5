"""mapets-rl CLI: train / resume / evaluate / compare on a toy recipe, and the error paths
(one line on stderr, exit code 2, no traceback)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from mapets_rl.experiment import read_results
from tests.cli_run import run_cli

ROOT = Path(__file__).resolve().parents[2]


def test_train_resume_evaluate_compare(tmp_path: Path, toy_recipe, capsys) -> None:
    runs = []
    for seed in (0, 1):
        run = tmp_path / f"toy{seed}"
        code, out, _ = run_cli(
            [
                "train",
                "toy",
                "--env",
                "toy",
                "--seed",
                str(seed),
                "--run-dir",
                str(run),
                "total_frames=40",
            ],
            capsys,
        )
        assert code == 0 and json.loads(out.splitlines()[-1])["frames"] == 40
        runs.append(run)
    code, out, _ = run_cli(["resume", str(runs[0]), "total_frames=60"], capsys)
    assert code == 0 and json.loads(out.splitlines()[-1])["frames"] == 60
    assert [e["frames"] for e in read_results(runs[0])["evaluations"]] == [20, 40, 60]

    code, out, _ = run_cli(["evaluate", str(runs[0]), "--episodes", "2"], capsys)
    assert code == 0 and "return" in json.loads(out.splitlines()[-1])["metrics"]
    assert (runs[0] / "evaluation.json").is_file()

    code, out, _ = run_cli(["compare", *map(str, runs), "--out", str(tmp_path / "cmp")], capsys)
    assert code == 0 and "| toy |" in out
    assert (tmp_path / "cmp" / "learning_curves.png").is_file()
    assert (tmp_path / "cmp" / "final_metrics.md").is_file()


@pytest.mark.parametrize(
    "argv, needle",
    [
        (["train", "nosuchalgo", "--env", "toy"], "unknown recipe 'nosuchalgo'"),
        (["train", "toy", "--env", "nowhere"], "unknown scenario 'nowhere'"),
        (["train", "toy", "--env", "toy", "nokey=3"], "unknown config key 'nokey'"),
        (["train", "toy", "--env", "toy", "lr=-2"], "lr must be > 0"),
        (["train", "toy", "--env", "toy", "total_frames=lots"], "total_frames must be an integer"),
        (["train", "toy", "--env", "toy", "--seed", "x"], "--seed"),
        (["train", "toy"], "--env"),
        (["resume", "/nonexistent/run"], "not a run directory"),
        (["evaluate", "/nonexistent/run", "--episodes", "0"], "--episodes must be >= 1"),
        (["compare", "/nonexistent/run", "--out", "/tmp/x"], "has no results.json"),
        (["fly"], "invalid choice"),
    ],
)
def test_error_paths_exit_2_with_one_line(argv, needle, toy_recipe, capsys) -> None:
    code, _, err = run_cli(argv, capsys)
    assert code == 2
    assert err.count("\n") == 1 and err.startswith("mapets-rl: error:") and needle in err


def test_module_entry_point_errors_without_traceback() -> None:
    proc = subprocess.run(
        [
            sys.executable,
            "-m",
            "mapets_rl.app.cli",
            "train",
            "nope",
            "--env",
            "figure-eight",
        ],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 2
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(
        "mapets-rl: error: unknown recipe 'nope' (choose from: "
    )
    assert all(name in lines[0] for name in ("maddpg", "mappo", "sac"))


def test_help_explains_every_subcommand(capsys) -> None:
    for sub in ("train", "resume", "evaluate", "compare"):
        code, out, _ = run_cli([sub, "--help"], capsys)
        assert code == 0 and "usage: mapets-rl " + sub in out
    code, out, _ = run_cli(["train", "--help"], capsys)
    for option in ("--env", "--seed", "--config", "--run-dir", "key=value"):
        assert option in out


def test_evaluate_video_prints_only_our_output(tmp_path: Path) -> None:
    """No dependency chatter (torchrl INFO lines, PettingZoo version warning, SDL's
    XDG_RUNTIME_DIR error) on a console without a desktop session, and the GIF is drawn."""
    import imageio.v2 as imageio

    from mapets_rl.recipes.mappo import MAPPO, MAPPOConfig

    run = tmp_path / "run"
    MAPPO(
        MAPPOConfig(
            env="figure-eight",
            env_config={"n_cavs": 2, "n_hvs": 1, "horizon": 5},
            total_frames=10,
            frames_per_batch=10,
            minibatch_size=10,
            progress=False,
            logger="none",
        ),
        run,
    ).train()
    env = {
        k: v
        for k, v in os.environ.items()
        if k not in ("XDG_RUNTIME_DIR", "SDL_VIDEODRIVER", "RL_LOGGING_LEVEL")
    }
    proc = subprocess.run(
        [sys.executable, "-m", "mapets_rl.app.cli", "evaluate", str(run), "--video"],
        cwd=ROOT,
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert proc.returncode == 0 and proc.stderr == "", proc.stderr
    assert len(proc.stdout.splitlines()) == 1 and json.loads(proc.stdout)["frames"] == 10
    frames = imageio.mimread(run / "videos" / "eval_000000000010.gif")
    assert len(frames) == 5 and all(frame.mean() > 10 for frame in frames)
