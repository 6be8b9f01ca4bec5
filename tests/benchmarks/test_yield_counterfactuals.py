"""benchmarks/yield_counterfactuals.py (issue 32): a lane-change command that moves nothing
differs from Keep Lane by its comfort only, a trained policy's decisions are replayed from its
run, and a missing run is refused before any work."""

from __future__ import annotations

import argparse
from collections.abc import Callable
from pathlib import Path
from types import ModuleType

import numpy as np
import pytest
import torch

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture
def yields(load_script: Callable[[str], ModuleType], monkeypatch) -> ModuleType:
    monkeypatch.syspath_prepend(str(ROOT / "benchmarks"))  # cooperation_control & co.
    return load_script("benchmarks/yield_counterfactuals.py")


def test_a_command_that_moves_nothing_costs_its_comfort_only(yields: ModuleType) -> None:
    def change_left(observation: torch.Tensor) -> torch.Tensor:
        return torch.full(observation.shape[:-1], yields.CL, dtype=torch.long)

    args = argparse.Namespace(roads=2, n_vehicles=8, gamma=0.95, deviation="step")
    out = {k: np.asarray(v) for k, v in yields.counterfactuals(change_left, {}, 0, args).items()}
    assert len({len(v) for v in out.values()}) == 1
    still, moved = ~out["moved"], out["moved"]
    assert still.any() and moved.any()  # the leftmost lane is reached, and left before that
    # the same road afterwards: Change Left's comfort (1) against Keep Lane's (3, or 2 when
    # braking or accelerating hard), paid by the CAV and so by the system
    assert set(out["own"][still].round(5)) <= {-1.0, -2.0}  # float32 rewards
    assert np.allclose(out["own"][still], out["system"][still])
    assert not np.allclose(out["own"][moved], out["system"][moved])


def test_opting_out_keeps_the_lane_to_the_end(yields: ModuleType) -> None:
    def change_left(observation: torch.Tensor) -> torch.Tensor:
        return torch.full(observation.shape[:-1], yields.CL, dtype=torch.long)

    common = dict(roads=2, n_vehicles=8, gamma=1.0)
    once, rest = (
        {k: np.asarray(v) for k, v in yields.counterfactuals(change_left, {}, 0, args).items()}
        for args in (
            argparse.Namespace(**common, deviation="step"),
            argparse.Namespace(**common, deviation="rest"),
        )
    )
    assert np.array_equal(once["step"], rest["step"])  # the same decisions of the same episodes
    # in the leftmost lane Change Left moves nothing: opting out there only forgoes the comfort
    # cost (1 against Keep Lane's 2 or 3) of every later Change Left, one step's when once
    still = ~rest["moved"]
    assert still.any()
    assert (rest["own"][still] <= once["own"][still] + 1e-9).all()
    assert (rest["own"][still] < once["own"][still] - 0.5).any()


def test_a_trained_run_is_replayed_and_a_missing_one_refused(
    yields: ModuleType, load_script: Callable[[str], ModuleType], tmp_path: Path
) -> None:
    control = load_script("benchmarks/cooperation_control.py")
    tiny = ["--seeds", "0", "--frames", "20", "--train-roads", "4", "--eval-roads", "2"]
    control.main(
        ["--variants", "maddpg_shield_w1", *tiny, "--n-vehicles", "8", "--out", str(tmp_path)]
    )
    argv = ["--seeds", "0", "--roads", "2", "--n-vehicles", "8", "--out", str(tmp_path)]
    with pytest.raises(ValueError, match="no trained run .*maddpg_shield_seed0"):
        yields.main(["--variants", "maddpg_shield_w1", "maddpg_shield", *argv])
    assert not list((tmp_path / "evals").glob("yields_*"))  # refused before any work
    table = yields.main(["--variants", "maddpg_shield_w1", "rule", *argv])
    assert "| maddpg_shield_w1, near the merge |" in table and "| rule, elsewhere |" in table
    assert (tmp_path / "yields_gamma0.95_rest.md").read_text() == table + "\n"
