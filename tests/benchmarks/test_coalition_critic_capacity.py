"""benchmarks/coalition_critic_capacity.py (issue 32): the synthetic game's payoffs are the
known ones, a small coalition critic learns a CAV's state-dependent move effect, and bad
arguments are refused before any fitting."""

from __future__ import annotations

from collections.abc import Callable
from types import ModuleType

import pytest
import torch


@pytest.fixture
def capacity(load_script: Callable[[str], ModuleType]) -> ModuleType:
    return load_script("benchmarks/coalition_critic_capacity.py")


def test_the_game_pays_column_one_plus_column_zero_for_a_lane_change(capacity) -> None:
    obs, action, payoff = capacity.sample(3, 4, 64, torch.Generator().manual_seed(0), 5.0)
    moving = action[..., 1] + action[..., 2]
    torch.testing.assert_close(payoff, 5.0 * obs[..., 1] + moving * obs[..., 0])
    assert set(action.sum(-1).unique().tolist()) == {1.0}
    uniform = capacity.draw_coalitions("uniform", 5, 4000)
    assert uniform.any(-1).all() and set(uniform.sum(-1).unique().tolist()) == {1, 2, 3, 4, 5}


def test_two_agents_critic_learns_the_move_effect(capacity) -> None:
    rows = capacity.main(
        ["--agents", "2", "--cells", "32", "--embed", "0", "8", "--heads", "sum", "member",
         "--steps", "400", "--batch", "256", "--eval-states", "512", "--permutations", "4"]
    )  # fmt: skip
    assert [(row["embed"], row["heads"]) for row in rows] == [
        (0, "sum"),
        (0, "member"),
        (8, "sum"),
        (8, "member"),
    ]
    for row in rows:
        assert row["r2"] > 0.9
        assert min(row["corr_single"], row["corr_phi"], row["corr_grand"]) > 0.8


def test_target_noise_costs_fit_but_is_scored_against_the_noiseless_game(capacity) -> None:
    argv = ["--agents", "2", "--cells", "16", "--steps", "200", "--batch", "128",
            "--eval-states", "256", "--permutations", "4", "--noise", "0", "3"]  # fmt: skip
    clean, noisy = capacity.main(argv)
    assert (clean["noise"], noisy["noise"]) == (0.0, 3.0)
    assert clean["r2"] > 0.9 and noisy["r2"] < clean["r2"]


@pytest.mark.parametrize(
    "argv",
    [
        ["--obs-dim", "1"],
        ["--permutations", "3"],
        ["--steps", "0"],
        ["--lr", "0"],
        ["--embed", "-1"],
        ["--heads", "mean"],
        ["--noise", "-1"],
    ],
)
def test_bad_arguments_are_refused(capacity, argv, capsys) -> None:
    with pytest.raises(SystemExit):
        capacity.main(argv)
    assert "synthetic" not in capsys.readouterr().out  # nothing fitted
