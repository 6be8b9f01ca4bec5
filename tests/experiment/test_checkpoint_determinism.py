"""Checkpoints hold no uninitialised memory: replay storages and MA-PETS's per-agent datasets
save only what was written, so two identical runs write identical checkpoints (and small
buffers small ones), and a restored storage is the one that was saved."""

from __future__ import annotations

import hashlib
import zipfile
from pathlib import Path
from typing import Any

import pytest
import torch
from tensordict import TensorDict
from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer
from torchrl.data.replay_buffers.samplers import SamplerWithoutReplacement

from mapets_rl.comm import NeighbourDatasets
from mapets_rl.experiment import latest_checkpoint, load_checkpoint
from mapets_rl.modules.storage import FilledTensorStorage
from mapets_rl.recipes.maddpg import MADDPG, MADDPGConfig
from mapets_rl.recipes.mapets import MAPETS, MAPETSConfig
from mapets_rl.recipes.mappo import MAPPO, MAPPOConfig
from tests.recipes.test_recipe_mapets import TINY

TINY_MAPETS = dict(TINY, episodes=2, seed=3)


def _records(path: Path) -> dict[str, bytes]:
    """The records of checkpoint ``path`` (a zip archive of torch.save) by name."""
    with zipfile.ZipFile(path) as archive:
        return {name: archive.read(name) for name in archive.namelist()}


def _assert_equal(a: Any, b: Any, where: str = "state") -> None:
    assert type(a) is type(b), where
    if isinstance(a, torch.Tensor):
        assert a.dtype == b.dtype and a.shape == b.shape and torch.equal(a, b), where
    elif isinstance(a, dict):
        assert a.keys() == b.keys(), where
        for key in a:
            _assert_equal(a[key], b[key], f"{where}.{key}")
    elif isinstance(a, (list, tuple)):
        assert len(a) == len(b), where
        for i, (x, y) in enumerate(zip(a, b, strict=True)):
            _assert_equal(x, y, f"{where}[{i}]")
    else:
        assert a == b, where


# ----------------------------------------------------------------- whole runs, twice
def test_identical_mapets_runs_write_identical_checkpoints(tmp_path: Path) -> None:
    paths = []
    for name in ("a", "b"):
        exp = MAPETS(MAPETSConfig(**TINY_MAPETS), tmp_path / name)
        exp.train()
        paths.append(latest_checkpoint(exp.run_dir))
    a, b = (_records(p) for p in paths)
    assert a.keys() == b.keys()
    # every record is byte-identical: the measured durations go to timings.json
    differing = {name.rpartition("/")[2] for name in a if a[name] != b[name]}
    assert not differing, differing
    states = [load_checkpoint(p) for p in paths]
    _assert_equal(*states)
    # the datasets saved the slots written, not the whole storage
    datasets = states[0]["components"]["datasets"]
    slots = datasets["storage"]["slots"]
    written = int((datasets["uid"] >= 0).sum())
    assert slots.numel() == written < datasets["uid"].numel() == 3 * 64
    assert all(v.shape[0] == written for v in _leaves(datasets["storage"]["data"]))


def _leaves(tree: Any) -> list[torch.Tensor]:
    if isinstance(tree, torch.Tensor):
        return [tree]
    return [leaf for value in tree.values() for leaf in _leaves(value)]


MODEL_FREE = {
    # recipe: (class, config class, fields, rows of the replay storage at the last checkpoint)
    "maddpg": (
        MADDPG,
        MADDPGConfig,
        {"buffer_size": 1000, "batch_size": 16, "init_random_frames": 20, "total_frames": 60},
        60,  # every transition collected, in a storage of 1000 rows
    ),
    "mappo": (MAPPO, MAPPOConfig, {"minibatch_size": 10, "total_frames": 40}, 20),  # one batch
}


@pytest.mark.usefixtures("toy_scenario")
@pytest.mark.parametrize("recipe", sorted(MODEL_FREE))
def test_identical_model_free_runs_write_byte_identical_checkpoints(
    recipe: str, tmp_path: Path
) -> None:
    cls, config_cls, extra, expected_rows = MODEL_FREE[recipe]
    config = config_cls(
        env="toy", frames_per_batch=20, eval_interval=0, progress=False, logger="none", **extra
    )
    paths = []
    for name in ("a", "b"):
        exp = cls(config, tmp_path / name)
        exp.train()
        paths.append(latest_checkpoint(exp.run_dir))
    digests = [hashlib.sha256(p.read_bytes()).hexdigest() for p in paths]
    assert digests[0] == digests[1]
    storage = load_checkpoint(paths[0])["components"]["buffer"]["_storage"]
    assert storage["rows"] == expected_rows
    assert all(v.shape[0] == expected_rows for v in _leaves(storage["data"]))


# ------------------------------------------------------------------ the storages alone
def _batch(start: int, n: int) -> TensorDict:
    x = torch.arange(start, start + n, dtype=torch.float32)
    return TensorDict({"x": x[:, None].expand(n, 3).clone(), "n": {"i": x.long()}}, [n])


def test_filled_storage_saves_the_filled_rows_and_restores_the_same_buffer() -> None:
    def buffer(storage_cls: type = FilledTensorStorage) -> TensorDictReplayBuffer:
        return TensorDictReplayBuffer(
            storage=storage_cls(100), sampler=SamplerWithoutReplacement(), batch_size=7
        )

    full = buffer()
    full.extend(_batch(0, 30))
    state = full.state_dict()
    storage_state = state["_storage"]
    assert storage_state["rows"] == 30 and storage_state["data"]["x"].shape == (30, 3)
    # the saved rows are a copy, not a view of the 100-row storage (which torch.save would save)
    assert storage_state["data"]["x"].untyped_storage().nbytes() == 30 * 3 * 4
    restored = buffer()
    restored.load_state_dict(state)
    assert len(restored) == 30
    stored = restored.storage._storage
    assert torch.equal(stored[:30]["x"], full.storage._storage[:30]["x"])
    assert not stored[30:]["x"].any() and not stored[30:]["n", "i"].any()
    _assert_equal(restored.state_dict(), state)
    # both go on alike: writes land at the same cursor, sampling continues the same way
    for buf in (full, restored):
        buf.extend(_batch(30, 90))  # wraps around
    assert torch.equal(full.storage._storage["x"], restored.storage._storage["x"])
    assert full.state_dict()["_storage"]["rows"] == 100
    # a plain LazyTensorStorage state (checkpoints written before) still loads
    old = buffer(LazyTensorStorage)
    old.extend(_batch(0, 30))
    from_old = buffer()
    from_old.load_state_dict(old.state_dict())
    assert torch.equal(from_old.storage._storage[:30]["x"], old.storage._storage[:30]["x"])
    assert len(from_old) == 30


def test_filled_storage_of_plain_tensors() -> None:
    storage = FilledTensorStorage(10)
    storage.set(torch.arange(4), torch.ones(4, 2))
    state = storage.state_dict()
    assert state["rows"] == 4 and state["data"].shape == (4, 2)
    restored = FilledTensorStorage(10)
    restored.load_state_dict(state)
    assert len(restored) == 4 and torch.equal(restored.get(torch.arange(4)), torch.ones(4, 2))
    assert restored._storage.shape == (10, 2) and not restored._storage[4:].any()


def _transitions(steps: int, agents: int, offset: float = 0.0) -> TensorDict:
    obs = torch.arange(steps * agents, dtype=torch.float32).reshape(steps, agents, 1) + offset
    return TensorDict({"observation": obs, "action": obs * 2}, [steps, agents])


def test_neighbour_datasets_save_only_the_written_slots_and_restore_alike() -> None:
    data = NeighbourDatasets(3, capacity_per_agent=50, seed=1)
    assert data.state_dict()["storage"] == {}
    data.add(_transitions(4, 3))
    data.exchange(torch.ones(3, 3, dtype=torch.bool))
    state = data.state_dict()
    assert state["storage"]["slots"].tolist() == list(range(12))
    assert state["storage"]["data"]["observation"].shape == (12, 1)
    restored = NeighbourDatasets(3, capacity_per_agent=50, seed=7)
    restored.load_state_dict(state)
    _assert_equal(restored.state_dict(), state)
    for agent in range(3):
        assert torch.equal(
            restored.dataset(agent)["observation"], data.dataset(agent)["observation"]
        )
    assert torch.equal(restored.sample(5)["observation"], data.sample(5)["observation"])
    # the whole-storage state of a checkpoint written before still loads
    from_old = NeighbourDatasets(3, capacity_per_agent=50)
    from_old.load_state_dict({**state, "storage": data.storage.state_dict()})
    assert torch.equal(from_old.dataset(1)["observation"], data.dataset(1)["observation"])
    for d in (data, restored):
        d.add(_transitions(2, 3, offset=100.0))
    _assert_equal(restored.state_dict(), data.state_dict())
