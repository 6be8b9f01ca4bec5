"""Loggers and evaluation videos (issue 52): ``logger=mlflow`` through torchrl's
``MLFlowLogger`` writes a run that MLflow reads back, and an evaluation video reaches the
active logger through torchrl's ``VideoRecorder`` (TensorBoard's event file, MLflow's
artifacts) as well as ``videos/``."""

from __future__ import annotations

import io
from pathlib import Path

import pytest
from PIL import Image
from toy_recipe import ToyConfig, ToyLearner

from mapets_rl.experiment import ConfigError
from mapets_rl.experiment.config import LOGGER_PACKAGES
from mapets_rl.experiment.results import MLFLOW_RUN_TAG, MLFLOW_STORE
from mapets_rl.experiment.runner import VIDEO_TAG
from mapets_rl.recipes.mappo import MAPPO, MAPPOConfig

FIGURE_EIGHT = {"env": "figure-eight", "env_config": {"n_cavs": 2, "n_hvs": 1, "horizon": 5}}


def _needs(package: str) -> None:
    pytest.importorskip(package, reason=f"logger test: the {package} package is not installed")


def test_an_mlflow_run_is_read_back_by_mlflow(tmp_path, toy_scenario, monkeypatch, capfd):
    _needs("mlflow")
    from mlflow import MlflowClient

    monkeypatch.delenv("MLFLOW_TRACKING_URI", raising=False)
    run_dir = tmp_path / "run"
    config = ToyConfig(total_frames=20, frames_per_batch=10, eval_interval=10, logger="mlflow")
    ToyLearner(config, run_dir).train()
    assert "INFO mlflow" not in capfd.readouterr().err  # no word of MLflow's new store
    store = run_dir / "logs" / MLFLOW_STORE
    assert store.is_file()
    client = MlflowClient(tracking_uri=f"sqlite:///{store}")
    experiment = client.get_experiment_by_name("toy_toy")
    [run] = client.search_runs([experiment.experiment_id])
    assert run.data.tags[MLFLOW_RUN_TAG] == str(run_dir.resolve())
    history = client.get_metric_history(run.info.run_id, "eval/return")
    assert [m.step for m in history] == [10, 20]
    assert "train/reward" in run.data.metrics
    assert run.info.status == "FINISHED"  # the run trained its whole budget
    # a resume logs to the same MLflow run
    ToyLearner.from_run_dir(run_dir, ["total_frames=30"]).train()
    [resumed] = client.search_runs([experiment.experiment_id])
    assert resumed.info.run_id == run.info.run_id and resumed.info.status == "FINISHED"
    history = client.get_metric_history(run.info.run_id, "eval/return")
    assert [m.step for m in history] == [10, 20, 30]


def test_the_mlflow_logger_is_refused_without_mlflow(toy_scenario, monkeypatch):
    monkeypatch.setitem(LOGGER_PACKAGES, "mlflow", ("no_such_mlflow", "no_such_alembic"))
    with pytest.raises(
        ConfigError, match="logger='mlflow' needs the no_such_mlflow and no_such_alembic packages"
    ):
        ToyConfig(logger="mlflow")


def test_an_evaluation_video_is_in_the_tensorboard_event_file(tmp_path):
    _needs("tensorboard")
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    config = MAPPOConfig(**FIGURE_EIGHT, progress=False, logger="tensorboard")
    exp = MAPPO(config, tmp_path)
    metrics = exp.evaluate(episodes=1, video=True)
    exp.logger.logger.experiment.flush()
    assert (tmp_path / "videos" / "eval_000000000000.gif").is_file()  # as before
    events = EventAccumulator(str(tmp_path / "logs" / "mappo_figure-eight"), size_guidance={})
    events.Reload()
    assert VIDEO_TAG in events.Tags()["images"]
    [video] = events.Images(VIDEO_TAG)
    assert video.step == 0
    with Image.open(io.BytesIO(video.encoded_image_string)) as gif:
        assert gif.format == "GIF" and gif.n_frames == metrics["length"] == 5
        assert gif.info["duration"] == 100  # the figure-eight's 10 Hz policy, in real time
        assert gif.size == (video.width, video.height)


def test_an_evaluation_video_is_an_mlflow_artifact(tmp_path, monkeypatch):
    _needs("mlflow")
    from mlflow import MlflowClient

    monkeypatch.delenv("MLFLOW_TRACKING_URI", raising=False)
    exp = MAPPO(MAPPOConfig(**FIGURE_EIGHT, progress=False, logger="mlflow"), tmp_path)
    exp.evaluate(episodes=1, video=True)
    client = MlflowClient(tracking_uri=f"sqlite:///{tmp_path / 'logs' / MLFLOW_STORE}")
    run_id = exp.logger.logger.run_id
    [artifact] = client.list_artifacts(run_id, "videos")
    assert artifact.path == "videos/eval_video_000000000000.gif"
    local = Path(client.download_artifacts(run_id, artifact.path, str(tmp_path / "download")))
    assert (tmp_path / "logs" / "mlflow-artifacts").is_dir()  # inside the run directory
    with Image.open(local) as gif:
        assert gif.n_frames == 5
