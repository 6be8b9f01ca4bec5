"""Exact and sampled Shapley values refuse non-finite coalition values with a one-line
ValueError."""

from __future__ import annotations

import pytest
import torch

from mapets_rl.shapley import exact_shapley, sampled_shapley
from tests.refusals import INF, NAN, refused


# ------------------------------------------------------------------------------- Shapley
@pytest.mark.parametrize("bad", [NAN, INF], ids=["nan", "inf"])
def test_exact_shapley_refuses_non_finite_values(bad: float) -> None:
    values = torch.zeros(3, 8)
    values[1, 5] = bad
    refused(lambda: exact_shapley(values, 3), "values must be finite")


def test_sampled_shapley_refuses_non_finite_value_fn_outputs() -> None:
    def value_fn(masks: torch.Tensor) -> torch.Tensor:
        out = masks.float().sum(-1)
        out[-1] = NAN
        return out

    refused(lambda: sampled_shapley(value_fn, 4, 8), "value_fn's values must be finite")
