"""evaluate_scripted: the scripted CAV policy scored on exactly the evaluation episodes a
recipe run with the same config is scored on."""

from __future__ import annotations

from pathlib import Path

import pytest

from mapets_rl.app.plugins import load_recipe
from mapets_rl.envs import ScriptedCAVPolicy
from mapets_rl.experiment import ExperimentConfig, evaluate_scripted

FREEWAY = {"n_vehicles": 6, "cav_ratio": 0.5, "horizon": 8}


def test_same_episodes_as_a_recipe_run(tmp_path: Path) -> None:
    cls = load_recipe("coma")
    config = cls.Config(env="freeway", env_config=FREEWAY, seed=3, eval_episodes=2, logger="csv")
    exp = cls(config, tmp_path / "run")
    exp.eval_policy = ScriptedCAVPolicy(exp.env)
    expected = exp.evaluate()
    exp.collector.shutdown()
    # any recipe's config (here COMA's) or the shared ExperimentConfig gives the same episodes
    assert evaluate_scripted(config) == expected
    plain = ExperimentConfig(env="freeway", env_config=FREEWAY, seed=3, eval_episodes=2)
    assert evaluate_scripted(plain) == expected


def test_keep_lane_on_the_freeway(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.chdir(tmp_path)
    metrics = evaluate_scripted(
        ExperimentConfig(env="freeway", env_config=FREEWAY, seed=0, eval_episodes=1)
    )
    assert metrics["length"] == 8
    # 3 CAVs, each step's reward is 0.1 * speed + comfort with comfort 2 or 3 (keep lane)
    assert metrics["system_return"] == pytest.approx(3 * metrics["return"], rel=1e-5)
    assert 8 * (0.1 * 15 + 2) < metrics["return"] < 8 * (0.1 * 31.3 + 3)
    assert list(tmp_path.iterdir()) == []  # nothing written where it ran


def test_seed_changes_the_episodes() -> None:
    runs = [
        evaluate_scripted(ExperimentConfig(env="freeway", env_config=FREEWAY, seed=s))
        for s in (0, 1)
    ]
    assert runs[0]["average_velocity"] != runs[1]["average_velocity"]
