"""MA-PETS with ``comm.share_plans``: the CAVs plan with each other's broadcast plans, the
messages are counted per step, and d = 0 sends none."""

from __future__ import annotations

from mapets_rl.recipes.mapets import MAPETS
from tests.recipes.test_recipe_mapets import tiny


def test_two_lane_run_shares_plans_and_counts_messages(tmp_path) -> None:
    config = tiny(
        env="figure-eight-multilane",
        env_config={"n_cavs": 6, "n_hvs": 2, "horizon": 20},
        episodes=2,
        comm={"share_plans": True},
    )
    exp = MAPETS(config, tmp_path / "run")
    assert exp.plan_sharing is not None
    entries = exp.train()
    random_episode, planned = (e["metrics"] for e in entries)
    assert random_episode["plan_messages"] == 0.0
    assert planned["plan_messages"] > 0 and planned["plans_used"] > 0
    assert planned["plan_bytes"] == planned["plan_messages"] * 4 * config.planner.horizon


def test_without_range_no_plan_is_sent(tmp_path) -> None:
    config = tiny(episodes=2, comm={"share_plans": True, "comm_range": 0.0})
    entries = MAPETS(config, tmp_path / "run").train()
    assert entries[-1]["metrics"]["plan_messages"] == 0.0
    assert entries[-1]["metrics"]["plans_used"] == 0.0


def test_paper_configuration_has_no_plan_sharing(tmp_path) -> None:
    exp = MAPETS(tiny(episodes=1), tmp_path / "run")
    assert exp.plan_sharing is None and exp.policy is not None


def test_an_evaluation_episode_starts_without_plans(tmp_path) -> None:
    """The broadcasts of the last training step must not reach the first step of an
    evaluation episode (nor of the next training episode)."""
    exp = MAPETS(tiny(episodes=2, comm={"share_plans": True}), tmp_path / "run")
    exp.train()
    assert exp.plan_sharing._plans is not None
    seen = []
    original = exp.plan_sharing.forward

    def spy(td):
        seen.append(exp.plan_sharing._plans)
        return original(td)

    exp.plan_sharing.forward = spy
    exp.evaluate(episodes=1)
    assert seen[0] is None
