"""The svmix recipe: ``mapets-rl train svmix`` on both figure-eights and the freeway (tiny
runs), exact resume with link failures drawn, the critic's graph within range ``d``, bad input
refused."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch

from mapets_rl.comm import communication_graph
from mapets_rl.recipes.svmix import NEIGHBOURS, SVMIX, SVMIXConfig
from tests.cli_run import run_cli

TINY = [
    "total_frames=40",
    "frames_per_batch=20",
    "minibatch_size=10",
    "epochs=2",
    "eval_interval=20",
    "checkpoint_interval=0",
    "logger=none",
    "progress=false",
]
LOOP = ["env_config.n_cavs=3", "env_config.n_hvs=2", "env_config.horizon=20"]
SCENARIOS = {
    "figure-eight": (LOOP, ("agility", "safety")),
    "figure-eight-multilane": (LOOP, ("agility", "safety")),
    "freeway": (["env_config.n_vehicles=4", "env_config.cav_ratio=0.5"], ("average_velocity",)),
}
"""Scenario -> (its tiny env_config, its metrics): the figure-eights' continuous target speeds
and the freeway's one-hot lane moves (the categorical policy)."""


@pytest.mark.parametrize("scenario", sorted(SCENARIOS))
def test_mapets_rl_train_svmix(scenario: str, tmp_path: Path, capsys) -> None:
    env_config, metrics = SCENARIOS[scenario]
    run_dir = tmp_path / "run"
    argv = ["train", "svmix", "--env", scenario, "--run-dir", str(run_dir), *env_config, *TINY]
    code, out, err = run_cli(argv, capsys)
    assert code == 0, err
    final = json.loads(out.splitlines()[-1])
    assert final["frames"] == 40
    for name in (*metrics, "reward"):
        assert torch.isfinite(torch.tensor(final["metrics"][name]))
    assert (run_dir / "results.json").is_file()


def _config(total: int, **kwargs) -> SVMIXConfig:
    return SVMIXConfig(
        env="figure-eight",
        env_config={"n_cavs": 3, "n_hvs": 2, "horizon": 20},
        total_frames=total,
        frames_per_batch=20,
        minibatch_size=10,
        epochs=2,
        eval_interval=20,
        checkpoint_interval=20,
        progress=False,
        logger="none",
        **kwargs,
    )


def _params(exp: SVMIX) -> torch.Tensor:
    return torch.cat([p.detach().flatten().clone() for p in exp.loss.parameters()])


def test_training_moves_the_policy_and_the_mixer(tmp_path: Path) -> None:
    exp = SVMIX(_config(40), tmp_path)
    before = {name: p.detach().clone() for name, p in exp.loss.named_parameters()}
    logs: list[dict[str, float]] = []
    step = exp.train_step
    exp.train_step = lambda batch: logs.append(step(batch)) or logs[-1]
    exp.train()
    losses = [v for log in logs for k, v in log.items() if k.startswith("loss_")]
    assert len(logs) == 2 and all(torch.isfinite(torch.tensor(losses)))
    moved = {name for name, p in exp.loss.named_parameters() if not torch.equal(p, before[name])}
    assert any("actor" in name for name in moved)
    assert any(name.endswith("hyper.weight") for name in moved)  # the mixer's hypernetwork


def test_resume_matches_uninterrupted(tmp_path: Path) -> None:
    """Half the links fail, so the critic's draws are part of what a checkpoint must replay."""
    comm = {"comm_range": 100.0, "p_fail": 0.5}
    full = SVMIX(_config(60, comm=comm), tmp_path / "full")
    expected = full.train()
    SVMIX(_config(20, comm=comm), tmp_path / "part").train()
    resumed = SVMIX.from_run_dir(tmp_path / "part", overrides=["total_frames=60"])
    assert resumed.train() == expected
    assert torch.equal(_params(resumed), _params(full))


@pytest.mark.parametrize("p_fail", [0.0, 1.0])
def test_the_critic_links_the_cavs_within_range_and_drops_failed_links(
    p_fail: float, tmp_path: Path
) -> None:
    """``d`` is the median distance between two CAVs of a short rollout: the critic's graph is
    the range-``d`` graph (some pairs linked, some not), or empty when every link fails."""
    rollout = SVMIX(_config(20), tmp_path / "probe").env.rollout(5)
    position, mask = rollout["agents", "position"], rollout["agents", "mask"]
    distance = torch.cdist(position, position)
    d = distance[distance > 0].median().item()
    exp = SVMIX(_config(20, comm={"comm_range": d, "p_fail": p_fail}), tmp_path / "run")
    with torch.no_grad():
        out = exp.critic(rollout.copy())
    expected = communication_graph(position, d, mask=mask)
    assert expected.any() and not (expected | torch.eye(3, dtype=torch.bool)).all()
    assert torch.equal(out[NEIGHBOURS], expected if p_fail == 0.0 else torch.zeros_like(expected))
    assert out["joint_value"].shape == (5, 1)


@pytest.mark.parametrize(
    "override, needle",
    [
        ("comm.p_fail=2", "comm.p_fail must be in [0, 1]"),
        ("comm.comm_range=-1", "comm.comm_range must be >= 0"),
        ("comm.share_plans=true", "comm.share_plans must be false"),
        ("gnn_hidden=0", "gnn_hidden must be >= 1"),
        ("gnn_layers=0", "gnn_layers must be >= 1"),
        ("mixing_embed=0", "mixing_embed must be >= 1"),
        ("clip_epsilon=0", "clip_epsilon must be > 0"),
        ("reward_scale=0", "reward_scale must be > 0"),
    ],
)
def test_bad_config_is_refused_in_one_line(override: str, needle: str, capsys) -> None:
    code, _, err = run_cli(["train", "svmix", "--env", "figure-eight", override], capsys)
    assert code != 0
    assert needle in err
    assert "Traceback" not in err
