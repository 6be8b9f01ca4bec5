"""mapets_rl.modules: the building blocks recipes share (recipes never import each other),
and the one Gumbel-softmax / one-hot implementation."""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import pytest
import torch
from torchrl.envs.utils import ExplorationType, set_exploration_type

from mapets_rl.modules import GumbelSoftmaxHead, gumbel_one_hot, one_hot_argmax
from mapets_rl.modules.arguments import hidden_sizes, require_positive_ints
from mapets_rl.objectives.coma import COMACritic
from mapets_rl.shapley import CoalitionCritic, RandomCoalition
from tests.test_architecture import project_imports

ROOT = Path(__file__).resolve().parents[2]


def test_recipes_do_not_import_each_other() -> None:
    offenders = [
        f"{path.name}: {name}"
        for path in sorted((ROOT / "recipes").glob("*.py"))
        for _line, name in project_imports(path)
        if name == "recipes" or name.startswith("recipes.")
    ]
    assert offenders == []


def test_one_gumbel_softmax_implementation() -> None:
    logits = torch.tensor([[0.1, 2.0, -1.0, 0.5], [3.0, 0.0, 0.2, 0.1]], requires_grad=True)
    head = GumbelSoftmaxHead(tau=0.7)
    torch.manual_seed(0)
    with set_exploration_type(ExplorationType.RANDOM):
        sampled = head(logits)
    torch.manual_seed(0)
    assert torch.equal(sampled, gumbel_one_hot(logits, 0.7))
    torch.manual_seed(0)
    assert torch.equal(sampled, torch.nn.functional.gumbel_softmax(logits, tau=0.7, hard=True))
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        greedy = head(logits)
    assert torch.equal(greedy.detach(), one_hot_argmax(logits.detach()))
    assert torch.equal(
        one_hot_argmax(logits.detach()), torch.tensor([[0.0, 1, 0, 0], [1, 0, 0, 0]])
    )
    # straight-through: the gradient of the greedy action is the softmax's
    (greedy * torch.arange(4.0)).sum().backward()
    soft_grad = torch.autograd.grad((logits.softmax(-1) * torch.arange(4.0)).sum(), logits)[0]
    torch.testing.assert_close(logits.grad, soft_grad)


@pytest.mark.parametrize(
    ("build", "message"),
    [
        (lambda: CoalitionCritic(True, 3, 4), "n_agents must be an int >= 1, got True"),
        (lambda: CoalitionCritic(3, 0, 4), "observation_dim must be an int >= 1, got 0"),
        (lambda: COMACritic(3, 2, 2.0), "n_actions must be an int >= 1, got 2.0"),
        (lambda: COMACritic(3, 2, 4, num_cells=[]), "num_cells must be a non-empty list"),
        (lambda: COMACritic(3, 2, 4, num_cells=[64, 0]), "num_cells must be a non-empty list"),
        (lambda: RandomCoalition(-1), "n_agents must be an int >= 1, got -1"),
    ],
)
def test_network_arguments_are_checked_by_name(build: Any, message: str) -> None:
    with pytest.raises(ValueError, match=re.escape(message)):
        build()


def test_hidden_sizes_returns_a_list() -> None:
    assert hidden_sizes((64, 32)) == [64, 32]
    require_positive_ints(a=1, b=7)
