"""``protocol.md`` gives a group's gain an interval from three seeds on and, below that, each
seed's gain instead (the bootstrap interval of two seeds is their range)."""

from __future__ import annotations

from pathlib import Path

import pytest

from mapets_rl.app.protocol_report import protocol_summary, protocol_table
from mapets_rl.statistics import bootstrap_interval


def _result(seed: int, gain: float) -> dict:
    """A run's protocol result with one reference, ``keep-lane``, and ``gain`` percent over it."""
    return {
        "seed": seed,
        "frames": 100,
        "roads": 4,
        "references": {"keep-lane": {"system_reward_mean": 10.0, "metrics": {"safety": 1.0}}},
        "gain_percent": {"keep-lane": gain},
        "policy": {"system_reward_mean": 10.0 + gain / 10, "metrics": {"safety": 0.9}},
    }


@pytest.mark.parametrize(
    ("gains", "cell"),
    [
        ([2.0], "+2.0% (+2.0)"),
        ([1.0, 4.0], "+2.5% (+1.0, +4.0)"),
        ([1.0, 4.0, 7.0], "+4.0% [{low:+.1f}, {high:+.1f}] / +4.0% / +1.0, +4.0, +7.0"),
    ],
)
def test_a_gain_has_an_interval_from_three_seeds_and_each_seeds_value_below(
    tmp_path: Path, gains: list[float], cell: str
) -> None:
    runs = [str(tmp_path / f"s{seed}") for seed in range(len(gains))]
    results = {run: _result(seed, g) for seed, (run, g) in enumerate(zip(runs, gains, strict=True))}
    summary = protocol_summary({"mappo": runs}, results)
    gain = summary["groups"]["mappo"]["gain_percent"]["keep-lane"]
    assert gain["per_seed"] == gains
    assert gain["mean"] == pytest.approx(sum(gains) / len(gains))
    assert (gain["mean_ci95"] is None) == (gain["iqm_ci95"] is None) == (len(gains) < 3)
    _, low, high = bootstrap_interval(gains)
    table = protocol_table(summary, 4)
    row = next(line for line in table.splitlines() if line.startswith("| mappo |"))
    assert row.split(" | ")[4] == cell.format(low=low, high=high)
    assert "A group of fewer than 3 seeds has no interval" in table
