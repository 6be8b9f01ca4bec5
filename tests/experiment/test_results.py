"""``results.json`` keeps training entries (e.g. MA-PETS's episodes) and deterministic
evaluations apart; files and checkpoints from before the split still read."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest

from mapets_rl.experiment import ResultsWriter, read_results

ENV_CONFIG = {"n_cavs": 4, "horizon": 20}


def fake_run(
    path: Path,
    recipe: str = "toy",
    seed: int = 0,
    env: str = "figure-eight",
    env_config: dict[str, Any] | None = None,
    evaluations=(),
    train=(),
    **config: Any,
) -> Path:
    """A run directory whose results.json holds the given entries, as the runner writes it:
    ``evaluations`` / ``train`` are ``(frames, {metric: value})`` pairs."""
    cfg = {
        "env": env,
        "env_config": dict(ENV_CONFIG if env_config is None else env_config),
        "seed": seed,
        **config,
    }
    writer = ResultsWriter(path, recipe, env, seed, cfg)
    for frames, metrics in train:
        writer.add_train(frames, metrics)
    for frames, metrics in evaluations:
        writer.add_evaluation(frames, metrics)
    writer.write()
    return path


def eval_entries(*returns: float, every: int = 100) -> list[tuple[int, dict[str, float]]]:
    return [(every * (i + 1), {"return": r, "safety": 0.5}) for i, r in enumerate(returns)]


def train_entries(*safeties: float, length: int = 20) -> list[tuple[int, dict[str, float]]]:
    """MA-PETS-like training entries: episode k, frames = the steps so far."""
    return [
        (length * (k + 1) + k, {"episode": float(k + 1), "safety": s, "return": 10 * s})
        for k, s in enumerate(safeties)
    ]


# ------------------------------------------------------------------------- results files
def test_results_keep_training_and_evaluation_entries_apart(tmp_path: Path) -> None:
    run = fake_run(tmp_path / "run", train=train_entries(0.2, 0.4), evaluations=eval_entries(1.0))
    data = json.loads((run / "results.json").read_text())
    assert [e["metrics"]["episode"] for e in data["train"]] == [1.0, 2.0]
    assert [e["frames"] for e in data["evaluations"]] == [100]
    res = read_results(run)
    assert res["train"] == data["train"] and res["evaluations"] == data["evaluations"]
    assert res["legacy"] is False


def test_results_files_from_before_the_split_still_read(tmp_path: Path) -> None:
    run = tmp_path / "old"
    run.mkdir()
    entries = [{"frames": 21, "metrics": {"episode": 1.0, "safety": 0.3}}]
    (run / "results.json").write_text(
        json.dumps(
            {
                "recipe": "mapets",
                "env": "figure-eight",
                "seed": 0,
                "config": {},
                "evaluations": entries,
            }
        )
    )
    res = read_results(run)
    assert res["legacy"] is True and res["evaluations"] == entries and res["train"] == []
    res = read_results(run, legacy_as="train")
    assert res["train"] == entries and res["evaluations"] == []
    with pytest.raises(ValueError, match="legacy_as must be one of"):
        read_results(run, legacy_as="both")


def test_malformed_train_entries_are_refused(tmp_path: Path) -> None:
    run = fake_run(tmp_path / "run", evaluations=eval_entries(1.0))
    data = json.loads((run / "results.json").read_text())
    data["train"] = [{"frames": "x"}]
    (run / "results.json").write_text(json.dumps(data))
    with pytest.raises(ValueError, match="'train' must be a list of"):
        read_results(run)


@pytest.mark.parametrize("kind", ["train", "eval"])
def test_entries_of_an_old_checkpoint_take_the_kind_of_the_next_entry(
    tmp_path: Path, kind: str
) -> None:
    """Before the split every recipe wrote one kind of entry into 'evaluations' (MA-PETS: its
    training episodes); resumed from such a checkpoint, they join the kind added next."""
    old = [{"frames": 21, "metrics": {"safety": 0.3}}]
    writer = ResultsWriter(tmp_path, "toy", "figure-eight", 0, {})
    writer.load_state_dict({"evaluations": json.dumps(old)})
    assert writer.latest_metrics() == {"safety": 0.3}
    assert writer.state_dict() == {"evaluations": json.dumps(old)}
    writer.write()  # still the old layout: nothing tells yet what the entries are
    assert read_results(tmp_path)["legacy"] is True
    add = writer.add_train if kind == "train" else writer.add_evaluation
    add(40, {"safety": 0.6})
    res = read_results(tmp_path)
    mine, other = ("train", "evaluations") if kind == "train" else ("evaluations", "train")
    assert [e["frames"] for e in res[mine]] == [21, 40] and res[other] == []
    assert res["legacy"] is False
    assert set(writer.state_dict()) == {"evaluations", "train"}


def test_mapets_records_training_episodes_as_train_entries(tmp_path: Path) -> None:
    from mapets_rl.recipes.mapets import MAPETS, MAPETSConfig

    config = MAPETSConfig(
        env_config={"n_cavs": 2, "n_hvs": 1, "horizon": 5},
        preset="cpu",
        episodes=1,
        planner={"horizon": 2, "population": 4, "elites": 1, "iterations": 1, "particles": 5},
        model={"hidden": [8], "batch_size": 8, "epochs": 1},
        num_threads=1,
        progress=False,
        logger="none",
    )
    exp = MAPETS(config, tmp_path / "run")
    history = exp.train()
    res = read_results(tmp_path / "run")
    assert res["evaluations"] == [] and res["train"] == history
    assert [e["metrics"]["episode"] for e in res["train"]] == [1.0]
