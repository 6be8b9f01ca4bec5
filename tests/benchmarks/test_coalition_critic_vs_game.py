"""benchmarks/coalition_critic_vs_game.py (issue 32): the summary's known answers on constructed
games, and a tiny trained run compared end to end (efficiency of every Shapley value, the
member game's empty coalition, resume without recomputation)."""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path
from types import ModuleType

import pytest

from mapets_rl.recipes.shapley_ac import ShapleyAC, ShapleyACConfig
from mapets_rl.shapley import exact_shapley

N = 3


@pytest.fixture
def bench(load_script: Callable[[str], ModuleType]) -> ModuleType:
    return load_script("benchmarks/coalition_critic_vs_game.py")


def _row(v_critic: list[float], v_member: list[float], v_credit: list[float]) -> dict:
    import torch

    phi = {
        name: exact_shapley(torch.tensor(v, dtype=torch.float64), N).tolist()
        for name, v in (("critic", v_critic), ("member", v_member), ("credit", v_credit))
    }
    singles = sum(v_credit[1 << i] - v_credit[0] for i in range(N))
    return {
        "run": "r",
        "v_critic": v_critic,
        "v_member": v_member,
        "v_credit": v_credit,
        "phi": phi,
        "credit_gain": v_credit[-1] - v_credit[0],
        "credit_additive": singles,
        "view_disagreement": 0.25,
    }


def test_a_critic_that_is_the_member_game_scores_one_and_scale_is_measured(
    bench: ModuleType,
) -> None:
    additive = [0.0, 1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0]  # v(C) = sum of 1, 2, 4 over members
    half = [v / 2 for v in additive]
    superadditive = [*additive[:-1], 14.0]  # the grand coalition gains 7 more together
    rows = [_row(additive, additive, superadditive), _row(half, additive, superadditive)]
    summary = bench.summarise(rows)
    assert summary["v_corr"] == pytest.approx(1.0)
    assert summary["grand_ratio"] == pytest.approx(0.75)  # median of 1 and 0.5
    assert summary["phi_member_corr"] == pytest.approx(1.0)
    assert summary["credit_gain"] == pytest.approx(14.0)
    assert summary["credit_ratio"] == pytest.approx(2.0)  # twice the sum of its parts
    assert summary["view_disagreement"] == pytest.approx(0.25)
    assert bench.pearson(bench.np.ones(3), bench.np.arange(3.0)) is None


def test_a_tiny_run_is_compared_and_resumed(bench: ModuleType, tmp_path: Path) -> None:
    config = ShapleyACConfig(
        env="freeway-merge",
        env_config={"backend": "torch", "num_envs": 2, "n_vehicles": 8, "cav_ratio": 0.375},
        frames_per_batch=8,
        total_frames=16,
        eval_interval=0,
        checkpoint_interval=16,
        num_cells=[8],
        critic_cells=[8],
        batch_size=8,
        init_random_frames=0,
        progress=False,
        logger="none",
    )
    run = tmp_path / "run"
    ShapleyAC(config, run).train()
    out = tmp_path / "out"
    argv = ["--runs", str(run), "--roads", "2", "--steps", "0", "3", "--out", str(out)]
    table = bench.main(argv)
    rows = [json.loads(line) for line in (out / "states.jsonl").read_text().splitlines()]
    assert 1 <= len(rows) <= 4 and {r["step"] for r in rows} <= {0, 3}
    for row in rows:
        assert len(row["v_critic"]) == 2**N and row["v_member"][0] == 0.0
        for name, values in (("critic", "v_critic"), ("member", "v_member")):
            assert sum(row["phi"][name]) == pytest.approx(row[values][-1], abs=1e-6)
        assert sum(row["phi"]["credit"]) == pytest.approx(row["credit_gain"], abs=1e-6)
    assert "| run |" in table and (out / "critic_vs_game.png").stat().st_size > 0
    stamp = (out / "states.jsonl").stat().st_mtime_ns
    assert bench.main(argv) == table
    assert (out / "states.jsonl").stat().st_mtime_ns == stamp
