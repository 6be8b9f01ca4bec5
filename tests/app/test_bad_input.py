"""Bad command lines never end in a traceback: ``mapets-rl`` exits with code 2 and one line
``mapets-rl: error: ...`` before any work starts (no run directory is made), and a run directory
that cannot be written is refused before the env is built."""

from __future__ import annotations

import os
import re
from pathlib import Path

import pytest
from toy_recipe import ToyConfig, ToyLearner

from mapets_rl.app.cli import main
from mapets_rl.experiment import runner
from tests.refusals import NO_CUDA_DEVICE, refused

pytestmark = pytest.mark.usefixtures("toy_scenario")


# -------------------------------------------------------------------------------- the CLI
@pytest.fixture
def a_file(tmp_path: Path) -> Path:
    path = tmp_path / "a_file"
    path.write_text("not a directory")
    return path


@pytest.fixture
def bad_yaml(tmp_path: Path) -> Path:
    path = tmp_path / "bad.yaml"
    path.write_text("total_frames: [40\n")
    return path


@pytest.fixture
def dup_yaml(tmp_path: Path) -> Path:
    path = tmp_path / "dup.yaml"
    path.write_text("lr: 0.1\ntotal_frames: 40\nlr: 0.2\n")
    return path


@pytest.fixture
def alias_yaml(tmp_path: Path) -> Path:
    """A "billion laughs" document: each line doubles the last (2**9 here, unbounded in
    general)."""
    lines = ["a0: &a0 [x, x]"] + [f"a{i}: &a{i} [*a{i - 1}, *a{i - 1}]" for i in range(1, 9)]
    path = tmp_path / "bomb.yaml"
    path.write_text("\n".join(lines) + "\n")
    return path


@pytest.fixture
def finished_run(tmp_path: Path) -> Path:
    run = tmp_path / "done"
    ToyLearner(ToyConfig(total_frames=20), run).train()
    return run


TRAIN = ["train", "toy", "--env", "toy"]
CLI_CASES = [
    ("lr=.inf", TRAIN + ["lr=.inf"], "lr must be a finite number"),
    ("lr=1e400", TRAIN + ["lr=1e400"], "lr must be a finite number"),
    ("lr=nan", TRAIN + ["lr=nan"], "lr must be a finite number"),
    ("device=bogus", TRAIN + ["device=bogus"], "device must be one of"),
    ("device=cuda", TRAIN + [f"device={NO_CUDA_DEVICE}"], "device must be one of"),
    (
        "env=nowhere override",
        TRAIN + ["env=nowhere"],
        r"chosen by --env \(toy\), not by 'env=nowhere'",
    ),
    ("--env and env=", TRAIN + ["env=freeway"], r"chosen by --env \(toy\), not by 'env=freeway'"),
    ("--seed and seed=", TRAIN + ["--seed", "1", "seed=2"], "--seed 1 and 'seed=2' both set"),
    ("a key twice", TRAIN + ["lr=0.1", "lr=0.2"], r"lr is set twice \('lr=0.1' and 'lr=0.2'\)"),
    ("--run-dir ''", TRAIN + ["--run-dir", ""], "--run-dir must be a non-empty path"),
    (
        "--run-dir name too long",
        TRAIN + ["--run-dir", "{tmp_path}/" + "x" * 300],
        "run_dir cannot be created: the name .* is 300 bytes, this file system allows",
    ),
    (
        "total_frames below one batch",
        TRAIN + ["total_frames=20", "frames_per_batch=200"],
        "total_frames must be >= frames_per_batch=200",
    ),
    ("seed=2**64", TRAIN + [f"seed={2**64}"], r"seed must be in \[0, 4611686018427387903\]"),
    ("--config /dev/zero", TRAIN + ["--config", "/dev/zero"], "is not a regular file"),
    (
        "--config duplicate key",
        TRAIN + ["--config", "{dup_yaml}"],
        "key 'lr' given twice at line 3",
    ),
    ("--config alias bomb", TRAIN + ["--config", "{alias_yaml}"], r"aliases \(\*name\) are not"),
    (
        "num_cells too large",
        ["train", "mappo", "--env", "figure-eight", "num_cells=[1000000, 1000000]"],
        r"num_cells must be layers whose weights fit in memory \(at least 14901.2 GiB",
    ),
    (
        "critic_cells too large",
        ["train", "coma", "--env", "freeway", "critic_cells=[1000000, 1000000]"],
        r"critic_cells must be layers whose weights fit in memory",
    ),
    (
        "mapets ts1 particles that do not split over the members",
        [
            "train",
            "mapets",
            "--env",
            "figure-eight",
            "--run-dir",
            "{tmp_path}/ts1",
            "preset=cpu",
            "planner.propagation=ts1",
            "planner.particles=3",
        ],
        r"planner.particles \* population \(24\) must be divisible by the ensemble size \(5\)",
    ),
    (
        "coma on continuous actions",
        ["train", "coma", "--env", "figure-eight", "total_frames=20"],
        "coma needs discrete actions; scenario 'figure-eight' has continuous actions",
    ),
    ("malformed --config", TRAIN + ["--config", "{bad_yaml}"], "is not valid YAML"),
    ("missing --config", TRAIN + ["--config", "/nonexistent/c.yaml"], "cannot be read"),
    (
        "--run-dir under a file",
        TRAIN + ["--run-dir", "{a_file}/run"],
        "run_dir .* cannot be created: .* is not a directory",
    ),
    (
        "--run-dir is a file",
        TRAIN + ["--run-dir", "{a_file}"],
        "run_dir .* cannot be created: .* is not a directory",
    ),
    (
        "--runs-root under a file",
        TRAIN + ["--runs-root", "{a_file}/runs"],
        "--runs-root .* cannot be created",
    ),
    (
        "env_config length=inf",
        ["train", "toy", "--env", "figure-eight", "env_config.length=.inf"],
        "length must be a finite number > 0",
    ),
    (
        "env_config n_hvs=many",
        ["train", "toy", "--env", "figure-eight", "env_config.n_hvs=many"],
        "n_hvs must be an int >= 0 or a range",
    ),
    (
        "compare --out under a file",
        ["compare", "{finished_run}", "--out", "{a_file}/cmp"],
        "out_dir .* cannot be created",
    ),
    (
        "compare --metrics ,",
        ["compare", "{finished_run}", "--out", "{tmp_path}/cmp", "--metrics", ","],
        "--metrics must name at least one metric",
    ),
    (
        "compare unknown metric",
        ["compare", "{finished_run}", "--out", "{tmp_path}/cmp", "--metrics", "nope"],
        r"metrics \['nope'\] are not in every run",
    ),
    (
        "resume env override",
        ["resume", "{finished_run}", "env=freeway"],
        "env cannot change when resuming",
    ),
    ("resume device=bogus", ["resume", "{finished_run}", "device=bogus"], "device must be one of"),
]


@pytest.mark.parametrize("argv, match", [c[1:] for c in CLI_CASES], ids=[c[0] for c in CLI_CASES])
def test_cli_exits_2_with_one_line(
    argv: list[str], match: str, toy_recipe, tmp_path: Path, request, capsys
) -> None:
    names = {"a_file", "bad_yaml", "dup_yaml", "alias_yaml", "finished_run", "tmp_path"}
    values = {n: request.getfixturevalue(n) for n in names if any(f"{{{n}}}" in a for a in argv)}
    argv = [a.format(**values) for a in argv]
    capsys.readouterr()
    try:
        code = main(argv)
    except SystemExit as exc:
        code = exc.code
    _, err = capsys.readouterr()
    assert code == 2, err
    assert err.count("\n") == 1 and err.startswith("mapets-rl: error: "), err
    assert re.search(match, err), err
    assert not (tmp_path / "cmp").exists()
    assert not (tmp_path / "ts1").exists()  # refused before the run directory exists


def test_read_only_run_dir_is_refused_before_anything_starts(tmp_path: Path, monkeypatch) -> None:
    read_only = tmp_path / "ro"
    read_only.mkdir()
    real_access = os.access
    monkeypatch.setattr(
        os, "access", lambda p, mode, **kw: Path(p) != read_only and real_access(p, mode, **kw)
    )
    built = []
    monkeypatch.setattr(runner, "build_env", lambda *args, **kwargs: built.append(1))
    refused(
        lambda: ToyLearner(ToyConfig(), read_only / "run"),
        "run_dir .* cannot be written: .* is not writable",
    )
    assert built == [] and list(read_only.iterdir()) == []


def test_the_action_check_builds_the_scenario_with_a_published_files_env_config():
    """highway-multi has discrete actions by default; its published MA-PETS config chooses
    highway-env's continuous ones, so `train --config highway-multi/mapets` passes the action
    check (it was refused as 'mapets needs continuous actions')."""
    from mapets_rl.app.cli import _check_action_kind
    from mapets_rl.app.plugins import load_recipe
    from mapets_rl.experiment.published import load_published

    mapets = load_recipe("mapets")
    published = load_published("highway-multi/mapets")
    _check_action_kind(mapets, "highway-multi", published.fields["env_config"])
    with pytest.raises(SystemExit):
        _check_action_kind(mapets, "highway-multi", {})
