"""The Python API keeps the console for the user's output: building an env and training (a
model-free recipe with a replay buffer and exploration noise, and MA-PETS's datasets) print
nothing on stdout and warn nothing, in a fresh interpreter that installed no filter itself."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

TRAIN = """
import sys, tempfile
from mapets_rl.envs import make_env
from mapets_rl.recipes.maddpg import MADDPG, MADDPGConfig
from mapets_rl.recipes.mapets import MAPETS, MAPETSConfig

make_env("freeway", n_vehicles=4, cav_ratio=0.5, horizon=3)
scenario = {"env": "figure-eight", "env_config": {"n_cavs": 2, "n_hvs": 1, "horizon": 5}}
quiet = {"progress": False, "logger": "none"}
MADDPG(
    MADDPGConfig(
        **scenario, **quiet, total_frames=40, frames_per_batch=20, eval_episodes=1, batch_size=8
    ),
    tempfile.mkdtemp(),
).train()
MAPETS(
    MAPETSConfig(
        **scenario, **quiet, preset="cpu", episodes=1, num_threads=1,
        planner={"horizon": 3, "population": 8, "elites": 2, "compile": False},
        model={"hidden": [16], "buffer_size": 64, "batch_size": 16, "epochs": 1},
    ),
    tempfile.mkdtemp(),
).train()
print("trained", file=sys.stderr)
"""


def test_building_and_training_print_nothing_on_stdout_and_warn_nothing() -> None:
    proc = subprocess.run(
        [sys.executable, "-c", TRAIN], cwd=ROOT, capture_output=True, text=True, timeout=600
    )
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout == ""
    assert proc.stderr == "trained\n"
