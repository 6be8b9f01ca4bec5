"""The discrete action set of the value-based baselines: the grid's known points, the map from
a one-hot choice to its continuous action on both figure-eights, bad input refused."""

from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict

from mapets_rl.envs.registry import build_env
from mapets_rl.modules import ACTION, AgentGroupSpec
from mapets_rl.modules.action_map import (
    ACTION_CHOICE,
    DiscreteActionMap,
    action_grid,
    make_action_map,
)


def test_action_grid_is_the_product_of_evenly_spaced_levels_first_dimension_slowest() -> None:
    grid = action_grid(torch.tensor([0.0, 0.0]), torch.tensor([12.0, 1.0]), [4, 2])
    expected = [[0, 0], [0, 1], [4, 0], [4, 1], [8, 0], [8, 1], [12, 0], [12, 1]]
    assert torch.equal(grid, torch.tensor(expected, dtype=torch.float32))
    assert torch.equal(
        action_grid(torch.tensor([2.0]), torch.tensor([5.0]), [1]), torch.tensor([[2.0]])
    )


@pytest.mark.parametrize(
    "env, levels, expected",
    [
        ("figure-eight", 3, [[0.0], [6.945], [13.89]]),
        (
            "figure-eight-multilane",
            2,
            [[0.0, 0.0], [0.0, 1.0], [13.89, 0.0], [13.89, 1.0]],
        ),
    ],
)
def test_the_map_sends_each_choice_to_its_action_on_the_figure_eights(
    env: str, levels: int, expected: list[list[float]]
) -> None:
    scenario = build_env(env, {"n_cavs": 2, "n_hvs": 1, "horizon": 5})
    spec = AgentGroupSpec.from_env(scenario)
    module, choice_spec, table = make_action_map(spec, levels)
    assert torch.allclose(table, torch.tensor(expected), atol=1e-5)
    assert choice_spec.shape == (2, len(expected))
    # agent 0 takes the last action, agent 1 the first, over a batch of 3 steps
    choice = torch.zeros(3, 2, len(expected))
    choice[:, 0, -1] = 1
    choice[:, 1, 0] = 1
    out = module(TensorDict({ACTION_CHOICE: choice}, batch_size=[3]))
    action = out.get(ACTION)
    assert action.shape == (3, 2, spec.action_dim)
    assert torch.allclose(action[:, 0], torch.tensor(expected[-1]), atol=1e-5)
    assert torch.allclose(action[:, 1], torch.tensor(expected[0]), atol=1e-5)
    assert spec.action_spec.is_in(action[0])  # inside the scenario's bounds
    scenario.close()


@pytest.mark.parametrize(
    "call, match",
    [
        (lambda: action_grid(torch.zeros(2), torch.ones(2), [3]), "levels must be 2 integers >= 1"),
        (lambda: action_grid(torch.zeros(1), torch.ones(1), [0]), "levels must be 1 integers >= 1"),
        (lambda: action_grid(torch.ones(1), torch.zeros(1), [2]), "low <= high"),
        (lambda: DiscreteActionMap(torch.zeros(3)), r"table must have shape \[K >= 1, A\]"),
        (
            lambda: DiscreteActionMap(torch.zeros(3, 1))(torch.zeros(2, 4)),
            "choice must be one-hot over 3 actions",
        ),
    ],
)
def test_bad_input_is_refused_naming_the_argument(call, match: str) -> None:
    with pytest.raises(ValueError, match=match):
        call()
