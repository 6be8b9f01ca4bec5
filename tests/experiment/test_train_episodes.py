"""Training episodes of the model-free loop (:mod:`mapets_rl.experiment.episodes`): every
episode that ended in a collected batch is recorded with its system return (reward summed over
CAVs and steps, the Shapley paper's Fig. 2 quantity) and the scenario's episode metrics; the
per-iteration count and means are training metrics; the run's ``train_episodes.jsonl`` is cut
back on resume like the logs, so a resumed run records what an uninterrupted one does."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch
from tensordict import TensorDict, TensorDictBase

from mapets_rl.experiment import TRAIN_EPISODES_FILE, read_train_episodes, window_means
from mapets_rl.experiment.episodes import EpisodeLog, EpisodeTracker, summarize_episodes
from mapets_rl.recipes.maddpg import MADDPG, MADDPGConfig

ROADS = 4


def _config(env: str = "freeway", **kw: Any) -> MADDPGConfig:
    base: dict[str, Any] = {
        "env": env,
        "env_config": {"backend": "torch", "num_envs": ROADS, "n_vehicles": 4, "cav_ratio": 0.5},
        "frames_per_batch": 40,  # 10 steps of each road
        "total_frames": 400,  # 100 steps of each road: 2 whole episodes and a half
        "eval_interval": 0,
        "checkpoint_interval": 0,
        "eval_episodes": 1,
        "num_cells": [16],
        "batch_size": 16,
        "updates_per_batch": 1,
        "init_random_frames": 0,
        "progress": False,
        "logger": "none",
    }
    base.update(kw)
    return MADDPGConfig(**base)


def _by_hand(batches: list[TensorDictBase]) -> list[float]:
    """System return of every episode that ended, from the rewards of the collected batches
    [B, T]: each road's steps in time order, cut after each step whose root ``done`` is set;
    episodes ordered by the step they ended at, then by road."""
    reward = torch.cat([b.get(("next", "agents", "reward")).double() for b in batches], 1)
    done = torch.cat([b.get(("next", "done")) for b in batches], 1).squeeze(-1)
    ended = []
    for road in range(reward.shape[0]):
        total = 0.0
        for t in range(reward.shape[1]):
            total += reward[road, t].sum().item()
            if done[road, t]:
                ended.append((t, road, total))
                total = 0.0
    return [value for _, _, value in sorted(ended)]


def _recording(exp: MADDPG) -> list[TensorDictBase]:
    """The batches ``exp`` trains on, recorded as it trains."""
    batches: list[TensorDictBase] = []
    step = exp.train_step

    def record(batch: TensorDictBase) -> dict[str, float]:
        batches.append(batch.clone())
        return step(batch)

    exp.train_step = record
    return batches


@pytest.mark.parametrize("env", ["freeway", "freeway-merge"])
def test_batched_run_records_every_finished_episode(env: str, tmp_path: Path) -> None:
    exp = MADDPG(_config(env), tmp_path)
    batches = _recording(exp)
    metrics: list[dict[str, float]] = []
    exp.train(on_iteration_end=metrics.append)
    expected = _by_hand(batches)
    ends = int(sum(b.get(("next", "done")).sum().item() for b in batches))
    assert len(expected) == ends >= ROADS * 2  # two whole episodes of every road at least
    episodes = read_train_episodes(tmp_path)
    np.testing.assert_allclose(episodes["system_return"], expected, rtol=1e-6)
    # the per-iteration metrics count them and average them
    assert [m["episodes"] for m in metrics] == [
        float(b.get(("next", "done")).sum()) for b in batches
    ]
    assert sum(m["episodes"] for m in metrics) == ends
    with_episodes = [m for m in metrics if m["episodes"] > 0]
    assert with_episodes and all("system_return" in m for m in with_episodes)
    assert all("system_return" not in m for m in metrics if m["episodes"] == 0)
    weighted = sum(m["system_return"] * m["episodes"] for m in with_episodes) / ends
    assert weighted == pytest.approx(float(np.mean(expected)), rel=1e-6)
    # each episode's frame count is that of the batch it ended in
    frames = np.repeat(
        [40 * (i + 1) for i in range(len(batches))],
        [int(b.get(("next", "done")).sum()) for b in batches],
    )
    np.testing.assert_array_equal(episodes["frames"], frames)
    # the scenario's episode metrics, from the env the collector steps
    keys = {"average_velocity", "average_comfort", "collisions"}
    keys |= {"ramp_stuck"} if env == "freeway-merge" else set()
    assert keys <= set(episodes)
    assert np.all(episodes["average_velocity"] > 0) and np.all(episodes["length"] <= 40)
    assert np.all((episodes["collisions"] >= 0) & (episodes["collisions"] <= 2))


def test_resumed_run_records_what_an_uninterrupted_one_does(tmp_path: Path) -> None:
    whole = tmp_path / "whole"
    MADDPG(_config(total_frames=480, checkpoint_interval=160), whole).train()
    expected = (whole / TRAIN_EPISODES_FILE).read_text()
    assert expected
    # a run killed after its checkpoint at 320 frames had recorded more episodes
    part = tmp_path / "part"
    MADDPG(_config(total_frames=320, checkpoint_interval=160), part).train()
    with open(part / TRAIN_EPISODES_FILE, "a") as f:
        f.write(json.dumps({"frames": 360, "system_return": 1.0, "length": 40.0}) + "\n")
        f.write('{"frames": 400, "system_ret')  # half written
    exp = MADDPG.from_run_dir(part, overrides=["total_frames=480"])
    # nothing is written until the resumed run has started
    assert (part / TRAIN_EPISODES_FILE).read_text().endswith('"system_ret')
    exp.train()
    assert (part / TRAIN_EPISODES_FILE).read_text() == expected


def test_tracker_carries_episodes_over_batches_and_orders_by_end() -> None:
    """Two roads, two batches of 3 steps: road 0 ends at steps 1 and 4, road 1 at step 2
    (global step numbering); each batch's rows continue the previous batch's."""
    reward = torch.tensor([[1.0, 2.0, 3.0, 4.0, 5.0, 6.0], [10.0, 20.0, 30.0, 40.0, 50.0, 60.0]])
    done = torch.zeros(2, 6, dtype=torch.bool)
    done[0, 1] = done[0, 4] = done[1, 2] = True

    def batch(cols: slice) -> TensorDict:
        r = reward[:, cols]
        return TensorDict(
            {
                "next": {
                    "agents": {"reward": r[..., None, None].expand(*r.shape, 2, 1).clone()},
                    "done": done[:, cols, None],
                }
            },
            batch_size=r.shape,
        )

    tracker = EpisodeTracker()
    first = tracker.update(batch(slice(0, 3)))
    assert first == [
        {"system_return": 2 * (1.0 + 2.0), "length": 2.0},
        {"system_return": 2 * (10.0 + 20.0 + 30.0), "length": 3.0},
    ]
    second = tracker.update(batch(slice(3, 6)))
    assert second == [{"system_return": 2 * (3.0 + 4.0 + 5.0), "length": 3.0}]
    tracker.reset()  # the envs were reset: the episodes under way are dropped
    assert tracker.update(batch(slice(3, 6))) == [{"system_return": 2 * (4.0 + 5.0), "length": 2.0}]


def test_summary_window_means_and_the_log(tmp_path: Path) -> None:
    assert summarize_episodes([]) == {"episodes": 0.0}
    summary = summarize_episodes([{"system_return": 1.0, "x": 4.0}, {"system_return": 3.0}])
    assert summary == {"episodes": 2.0, "system_return": 2.0, "x": 4.0}
    np.testing.assert_allclose(window_means([1, 2, 3, 4, 5], 2), [1.5, 3.5])
    assert window_means([1, 2], 3).shape == (0,)
    with pytest.raises(ValueError, match="window"):
        window_means([1.0], 0)
    assert read_train_episodes(tmp_path)["system_return"].shape == (0,)
    (tmp_path / TRAIN_EPISODES_FILE).write_text('{"frames": 1, "system_return": 2}\n')
    log = EpisodeLog(tmp_path)  # a fresh run: an earlier attempt's file is removed
    assert not (tmp_path / TRAIN_EPISODES_FILE).exists()
    log.append(40, [{"system_return": 5.0, "length": 40.0}])
    log.append(80, [])
    got = read_train_episodes(tmp_path)
    assert got["frames"].tolist() == [40] and got["system_return"].tolist() == [5.0]
    (tmp_path / TRAIN_EPISODES_FILE).write_text("not json\n{}\n")
    with pytest.raises(ValueError, match="line 1"):
        read_train_episodes(tmp_path)


def test_highway_env_backend_records_its_episodes(tmp_path: Path) -> None:
    """One in-process highway-env road: system returns from the batches, the scenario's
    metrics from the env's ``last_episode_metrics`` (one episode per batch of 40 frames)."""
    config = _config(
        env_config={"n_vehicles": 4, "cav_ratio": 0.5}, total_frames=80, eval_episodes=1
    )
    exp = MADDPG(config, tmp_path)
    batches = _recording(exp)
    exp.train()
    episodes = read_train_episodes(tmp_path)
    reward = torch.cat([b.get(("next", "agents", "reward")).double() for b in batches])
    done = torch.cat([b.get(("next", "done")) for b in batches]).reshape(-1)
    assert len(episodes["system_return"]) == int(done.sum()) >= 1
    first_end = int(done.nonzero()[0])
    assert episodes["system_return"][0] == pytest.approx(reward[: first_end + 1].sum().item())
    # the scenario's metrics of the episodes that ended alone in their batch
    assert np.isfinite(episodes["average_velocity"]).any()
