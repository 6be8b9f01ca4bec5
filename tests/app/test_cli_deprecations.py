"""A renamed config key still works from the command line and says so in one line."""

from __future__ import annotations

from pathlib import Path

import yaml

from tests.cli_run import run_cli


def test_the_collectors_old_name_warns_in_one_line(tmp_path: Path, capsys) -> None:
    run = tmp_path / "run"
    code, _, err = run_cli(
        ["train", "maddpg", "--env", "freeway", "total_frames=200", "num_envs=1",
         "progress=false", "logger=none", "eval_interval=0", "--run-dir", str(run)],
        capsys,
    )  # fmt: skip
    assert code == 0, err
    assert (
        "mapets-rl: warning: config key 'num_envs' of MADDPGConfig is deprecated: it is now "
        "'collector_workers'"
    ) in err.splitlines()
    assert yaml.safe_load((run / "config.yaml").read_text())["collector_workers"] == 1
