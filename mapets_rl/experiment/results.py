"""Loggers (torchrl.record.loggers), the per-run results JSON, and metric aggregation."""

from __future__ import annotations

import json
import logging
import math
import os
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

import torch
from torchrl.record.loggers import (
    CSVLogger,
    Logger,
    MLFlowLogger,
    TensorboardLogger,
    WandbLogger,
)
from torchrl.record.loggers.csv import CSVExperiment

from mapets_rl.experiment.config import LOGGERS, check_logger_package
from mapets_rl.experiment.files import (
    atomic_write_text,
    open_append,
    read_own_file,
    write_failed,
)
from mapets_rl.metrics import METRIC_UNITS, is_timing_metric, metric_unit

log = logging.getLogger(__name__)

RESULTS_FILE = "results.json"
TIMINGS_FILE = "timings.json"
"""Beside ``results.json``: the wall-clock metrics (:data:`mapets_rl.metrics.TIMING_METRICS`)
of its entries, which ``results.json`` and the checkpoints leave out."""
EVALUATION_FILE = "evaluation.json"
"""Beside ``results.json``: the standalone evaluation of the run's policy that ``mapets-rl
evaluate`` writes, ``{"frames": int, "episodes": int, "metrics": {name: float}}``."""
UNITS_FILE = "units.json"
"""Written beside the logger's files (``RUN_DIR/logs/units.json``): metric name -> unit."""
MLFLOW_STORE = "mlflow.db"
"""``logger=mlflow`` without ``MLFLOW_TRACKING_URI``: the run's MLflow store, a SQLite file in
``RUN_DIR/logs`` (MLflow >= 3.10 refuses a plain file store), its artifacts (the evaluation
videos) in ``RUN_DIR/logs/mlflow-artifacts``."""
MLFLOW_RUN_TAG = "mapets_rl.run_dir"
"""The tag of an MLflow run that names its run directory (a resumed run logs to the same one)."""
VIDEO_LOGGERS = ("tensorboard", "mlflow", "wandb")
"""The loggers that receive the evaluation videos (``log_video``); the CSV run's video is the
GIF in ``videos/``."""


def make_logger(
    kind: str, run_dir: str | os.PathLike, exp_name: str, purge_step: int | None = None
) -> Logger | None:
    """A torchrl logger writing under ``run_dir/logs``.

    Args:
        kind: ``"csv"`` (always available), ``"tensorboard"`` (needs the tensorboard package),
            ``"wandb"`` (needs wandb; runs offline unless WANDB_MODE says otherwise),
            ``"mlflow"`` (needs mlflow: torchrl's ``MLFlowLogger`` on the server or store of
            ``MLFLOW_TRACKING_URI``, else on :data:`MLFLOW_STORE` in ``run_dir/logs``; one
            MLflow run per run directory, tagged :data:`MLFLOW_RUN_TAG`) or ``"none"``
            (returns None). ``run_dir/logs/units.json`` names the unit of every metric
            (:data:`mapets_rl.metrics.METRIC_UNITS`).
        run_dir: the run directory.
        exp_name: experiment name (a sub-directory of ``logs``).
        purge_step: TensorBoard only: the new event file starts with a restart marker at this
            step, so that TensorBoard hides the events of earlier event files at this step and
            later (see :class:`RunLogger`).
    """
    if kind not in LOGGERS:
        raise ValueError(f"logger must be one of {list(LOGGERS)}, got {kind!r}")
    check_logger_package(kind)
    log_dir = str(Path(run_dir) / "logs")
    if kind == "none":
        return None
    # the logged scalars are named prefix/metric (train/agility); their units, once per run
    atomic_write_text(Path(log_dir) / UNITS_FILE, json.dumps(METRIC_UNITS, indent=1))
    if kind == "csv":
        return _NoFollowCSVLogger(exp_name=exp_name, log_dir=log_dir)
    if kind == "tensorboard":
        return _TensorboardLogger(exp_name, log_dir, purge_step)
    if kind == "mlflow":
        return _RunMLFlowLogger(exp_name, Path(run_dir))
    return WandbLogger(
        exp_name=exp_name,
        save_dir=log_dir,
        offline=os.environ.get("WANDB_MODE", "offline") == "offline",
    )


class _NoFollowCSVExperiment(CSVExperiment):
    """torchrl's CSV experiment whose scalar files are opened by
    :func:`~mapets_rl.experiment.files.open_append`: never through a symbolic link (torchrl
    opens them in append mode, following one out of the run directory)."""

    def add_scalar(self, name: str, value: float, global_step: int | None = None) -> None:
        path = os.path.join(self.log_dir, "scalars", f"{name}.csv")
        if path not in self.files:
            os.makedirs(os.path.dirname(path), exist_ok=True)
            self.files[path] = open_append(path)
        super().add_scalar(name, value, global_step)


class _NoFollowCSVLogger(CSVLogger):
    """torchrl's CSV logger on :class:`_NoFollowCSVExperiment`."""

    def _create_experiment(self) -> CSVExperiment:
        return _NoFollowCSVExperiment(
            os.path.join(self.log_dir, self.exp_name),
            video_format=self.video_format,
            video_fps=self.video_fps,
        )


def gif_bytes(video: torch.Tensor, fps: float) -> bytes:
    """An animated GIF of ``video`` (``[T, C, H, W]`` or ``[1, T, C, H, W]`` uint8, what
    torchrl's ``VideoRecorder`` passes to ``log_video``) at ``fps`` frames per second, looping
    (imageio's GIF writer, which reads ``duration`` in milliseconds per frame)."""
    import imageio.v2 as imageio

    frames = video[-1] if video.ndim == 5 else video
    frames = frames.permute(0, 2, 3, 1).to("cpu", dtype=torch.uint8).numpy()
    return imageio.mimwrite("<bytes>", list(frames), format="GIF", duration=1000.0 / fps, loop=0)


class _TensorboardLogger(TensorboardLogger):
    """torchrl's TensorBoard logger whose ``SummaryWriter`` gets ``purge_step`` (``None``:
    none) and whose videos are GIFs encoded by imageio (torch's ``add_video`` needs moviepy 1):
    TensorBoard's own video summary, an image summary holding the GIF."""

    def __init__(self, exp_name: str, log_dir: str, purge_step: int | None) -> None:
        self._purge_step = purge_step
        super().__init__(exp_name=exp_name, log_dir=log_dir)

    def _create_experiment(self) -> Any:
        from torch.utils.tensorboard import SummaryWriter

        log_dir = str(Path(self.log_dir) / self.exp_name)
        return SummaryWriter(log_dir=log_dir, purge_step=self._purge_step)

    def log_video(
        self, name: str, video: torch.Tensor, step: int | None = None, fps: float = 4, **kwargs: Any
    ) -> None:
        """Log ``video`` (``[1, T, C, H, W]`` uint8) at ``step`` as a GIF of ``fps`` frames per
        second under ``name``."""
        from tensorboard.compat.proto.summary_pb2 import Summary

        _, _, channels, height, width = video.shape
        image = Summary.Image(
            height=height,
            width=width,
            colorspace=channels,
            encoded_image_string=gif_bytes(video, fps),
        )
        summary = Summary(value=[Summary.Value(tag=name, image=image)])
        self.experiment.file_writer.add_summary(summary, step)


class _RunMLFlowLogger(MLFlowLogger):
    """torchrl's MLflow logger bound to the MLflow run of one run directory: scalars and videos
    go to that run by its id (an ``MlflowClient`` of the logger's tracking URI), not to the
    process's active run, so that a process may train several runs one after the other (a
    sweep's worker) or two at once; a resumed run logs to the run it logged to before (found
    by its :data:`MLFLOW_RUN_TAG`). Its videos are GIF artifacts (``videos/``), encoded by
    imageio (torchrl's MP4 encoding needs torchcodec)."""

    def __init__(self, exp_name: str, run_dir: Path) -> None:
        self._run_dir = run_dir.resolve()
        logs = self._run_dir / "logs"
        tracking_uri = os.environ.get("MLFLOW_TRACKING_URI") or f"sqlite:///{logs / MLFLOW_STORE}"
        artifacts = None
        if not os.environ.get("MLFLOW_TRACKING_URI"):
            artifacts = (logs / "mlflow-artifacts").as_uri()
        self._tracking_uri = tracking_uri
        super().__init__(exp_name, tracking_uri, artifact_location=artifacts)

    def _create_experiment(self) -> Any:
        from mlflow import MlflowClient

        store = logging.getLogger("mlflow.store.db.utils")
        level = store.level
        store.setLevel(logging.WARNING)  # not the INFO lines of a new store's tables
        try:
            self._client = MlflowClient(tracking_uri=self._tracking_uri)
            name = self._mlflow_kwargs["name"]
            experiment = self._client.get_experiment_by_name(name)
        finally:
            store.setLevel(level)
        if experiment is None:
            self.id = self._client.create_experiment(
                name, artifact_location=self._mlflow_kwargs["artifact_location"]
            )
        else:
            self.id = experiment.experiment_id
        run_dir = str(self._run_dir)
        earlier = []
        if "'" not in run_dir:  # (a quote cannot be searched for: a new MLflow run)
            earlier = self._client.search_runs(
                [self.id], filter_string=f"tags.`{MLFLOW_RUN_TAG}` = '{run_dir}'", max_results=1
            )
        if earlier:  # a resumed run: running again
            self._client.update_run(earlier[0].info.run_id, status="RUNNING")
            return earlier[0]
        return self._client.create_run(
            self.id, run_name=self._run_dir.name, tags={MLFLOW_RUN_TAG: run_dir}
        )

    @property
    def run_id(self) -> str:
        """The MLflow run's id."""
        return self.experiment.info.run_id

    def log_scalar(self, name: str, value: float, step: int | None = None) -> None:
        self._client.log_metric(self.run_id, name, value, step=step)

    def finish(self) -> None:
        """Mark the MLflow run finished (a run stopped or failed stays running, as MLflow shows
        a run whose process ended without a word; its resume continues it)."""
        self._client.set_terminated(self.run_id)

    def log_video(
        self, name: str, video: torch.Tensor, step: int | None = None, fps: float = 4, **kwargs: Any
    ) -> None:
        """Log ``video`` (``[1, T, C, H, W]`` uint8) as the artifact
        ``videos/<name>_<step>.gif`` (``/`` in ``name`` becomes ``_``)."""
        import tempfile

        stem = name.replace("/", "_") + ("" if step is None else f"_{int(step):012d}")
        with tempfile.TemporaryDirectory() as tmp:
            path = Path(tmp) / f"{stem}.gif"
            path.write_bytes(gif_bytes(video, fps))
            self._client.log_artifact(self.run_id, str(path), "videos")


def truncate_csv_scalars(log_dir: str | os.PathLike, keep: Mapping[str, int]) -> list[Path]:
    """Cut the CSV scalar files of a torchrl ``CSVLogger`` experiment directory ``log_dir``
    (``scalars/<name>.csv``, rows ``step,value``) back to what a checkpoint saw: the rows of
    ``name`` whose step is at most ``keep[name]``; a file whose name ``keep`` lacks (logged
    only after the checkpoint) is deleted, and so is an unreadable or partly written row (a
    process killed mid-write). Files are rewritten atomically, only when they change (or have
    other names than this one, a hard link); a symbolic link among them is removed, never read
    or written through (:func:`~mapets_rl.experiment.files.read_own_file`). Returns the files
    changed."""
    scalars = Path(log_dir) / "scalars"
    if not scalars.is_dir():
        return []
    changed = []
    for path in sorted(scalars.rglob("*.csv")):
        name = path.relative_to(scalars).with_suffix("").as_posix()
        last = keep.get(name)
        read = read_own_file(path)
        if read is None:
            if not os.path.lexists(path):  # a symbolic link, which read_own_file removed
                changed.append(path)
            continue
        text, own = read
        rows = []
        for line in text.splitlines(keepends=True):
            step, _, value = line.rstrip("\n").partition(",")
            try:
                ok = line.endswith("\n") and last is not None and int(step) <= last
                float(value)
            except ValueError:
                ok = False
            if ok:
                rows.append(line)
        if "".join(rows) == text and own:
            continue
        if rows:
            atomic_write_text(path, "".join(rows))
        else:
            path.unlink()
        changed.append(path)
    return changed


class RunLogger:
    """The run's scalar logger: the torchrl logger of :func:`make_logger` plus, for every
    scalar name, the last step logged under it (:meth:`state_dict`, saved in checkpoints).

    Logs after a resume hold each step once, in order: a resumed run's logger is created
    ``deferred`` (nothing under ``logs/`` is touched and the scalars logged meanwhile are kept
    in memory) until :meth:`open` is called with the steps of the checkpoint restored, once the
    resumed run's first iteration has succeeded. :meth:`open` then

    - truncates the CSV logs (``logs/<exp>/scalars/<group>/<name>.csv``) to the rows of each
      name at or before the checkpoint's step of that name (:func:`truncate_csv_scalars`),
      dropping the rows that a run killed after its checkpoint had logged (the resumed run logs
      those steps again). A fresh run (no checkpoint) in a directory with logs of an attempt
      that never checkpointed starts from empty CSV logs;
    - for TensorBoard, whose event files cannot be truncated, starts a new event file (as every
      ``SummaryWriter`` does) whose first event is a restart marker at ``purge_step`` (one past
      the largest step any scalar reached at the checkpoint,
      :func:`~mapets_rl.experiment.runner.purge_step`): TensorBoard hides the events of the
      older event files at that step and later, for every scalar. No point logged before the
      checkpoint is hidden; a scalar whose steps lag behind that largest step (the frames of
      MA-PETS, whose ``model/nll`` runs ahead by epoch) may show the steps redone after a kill
      twice. wandb runs are left as they are.

    A checkpoint written before checkpoints held these steps leaves the logs as they are.
    """

    def __init__(
        self, kind: str, run_dir: str | os.PathLike, exp_name: str, deferred: bool = False
    ) -> None:
        if kind not in LOGGERS:
            raise ValueError(f"logger must be one of {list(LOGGERS)}, got {kind!r}")
        check_logger_package(kind)
        self.kind = kind
        self.run_dir = Path(run_dir)
        self.exp_name = exp_name
        self.steps: dict[str, int] = {}
        """Scalar name -> the last step logged under it, over the whole run."""
        self.logger: Logger | None = None
        """The torchrl logger (``None`` until :meth:`open`)."""
        self._pending: list[tuple[str, float, int]] | None = []
        if not deferred:
            self.open({})

    @property
    def is_open(self) -> bool:
        return self._pending is None

    @property
    def log_dir(self) -> Path:
        """The torchrl logger's experiment directory, ``run_dir/logs/<exp_name>``."""
        return self.run_dir / "logs" / self.exp_name

    def open(self, keep: Mapping[str, int] | None, purge_step: int | None = None) -> None:
        """Cut the logs back to ``keep`` (scalar name -> last step to keep; ``None``: leave
        them as they are), create the torchrl logger and write what was logged meanwhile."""
        if self.is_open:
            return
        if keep is not None and self.kind == "csv":
            truncate_csv_scalars(self.log_dir, keep)
        self.logger = make_logger(self.kind, self.run_dir, self.exp_name, purge_step)
        pending, self._pending = self._pending or [], None
        for name, value, step in pending:
            self._write(name, value, step)

    def log_scalar(self, name: str, value: float, step: int) -> None:
        """Log ``value`` under ``name`` at ``step`` (kept in memory until :meth:`open`)."""
        self.steps[name] = int(step)
        if self._pending is not None:
            self._pending.append((name, float(value), int(step)))
        else:
            self._write(name, float(value), int(step))

    def _write(self, name: str, value: float, step: int) -> None:
        try:
            self.logger.log_scalar(name, value, step=step)
        except OSError as err:
            path = self.log_dir / "scalars" / f"{name}.csv" if self.kind == "csv" else self.log_dir
            raise write_failed(path, err) from None

    @property
    def records_videos(self) -> bool:
        """Whether :meth:`log_video` sends videos to the logger (:data:`VIDEO_LOGGERS`)."""
        return self.kind in VIDEO_LOGGERS

    def log_video(self, name: str, video: torch.Tensor, step: int, **kwargs: Any) -> None:
        """Log ``video`` (``[1, T, C, H, W]`` uint8, from torchrl's ``VideoRecorder``) under
        ``name`` at ``step`` with the torchrl logger's ``log_video`` (``kwargs``: its
        ``fps``), when it :attr:`records_videos` and is open (a run resumed for
        ``mapets-rl evaluate`` logs none)."""
        if not (self.records_videos and self.is_open):
            return
        try:
            self.logger.log_video(name, video, step=step, **kwargs)
        except OSError as err:
            raise write_failed(self.log_dir, err) from None

    def finish(self) -> None:
        """The run has trained its whole budget: an MLflow run is marked finished (the other
        loggers have nothing to mark)."""
        if self.is_open and isinstance(self.logger, _RunMLFlowLogger):
            self.logger.finish()

    def state_dict(self) -> dict[str, int]:
        """Scalar name -> last step logged (for checkpoints)."""
        return dict(self.steps)

    def load_state_dict(self, steps: Mapping[str, int]) -> None:
        self.steps = {str(k): int(v) for k, v in steps.items()}


def log_scalars(
    logger: Logger | RunLogger | None, prefix: str, values: Mapping[str, float], step: int
) -> None:
    """Log ``{prefix}/{name}`` for every finite scalar of ``values`` at ``step`` (frames)."""
    if logger is None:
        return
    for name, value in values.items():
        if isinstance(value, (int, float)) and math.isfinite(value):
            logger.log_scalar(f"{prefix}/{name}", float(value), step=step)


def metric_units(names: Iterable[str]) -> dict[str, str]:
    """Name -> unit of the metrics among ``names`` that have one (see
    :data:`mapets_rl.metrics.METRIC_UNITS`), sorted by name."""
    return {name: metric_unit(name) for name in sorted(set(names)) if metric_unit(name)}


def mean_metrics(items: Iterable[Mapping[str, float]]) -> dict[str, float]:
    """Per-key mean over a sequence of metric dicts (keys missing from some items are averaged
    over the items that have them)."""
    sums: dict[str, float] = {}
    counts: dict[str, int] = {}
    for item in items:
        for key, value in item.items():
            sums[key] = sums.get(key, 0.0) + float(value)
            counts[key] = counts.get(key, 0) + 1
    return {key: sums[key] / counts[key] for key in sums}


SOURCES = ("eval", "train")
"""Kinds of results entries: ``"eval"`` (deterministic evaluations, ``results.json``'s
``evaluations``) and ``"train"`` (training entries, e.g. MA-PETS's episodes, its ``train``)."""
ENTRY_LISTS = {"eval": "evaluations", "train": "train"}
"""Source -> the ``results.json`` key of its entries."""


class ResultsWriter:
    """The run's ``results.json``: identity of the run plus its entries, training and
    evaluation kept apart.

    Layout::

        {"recipe": str, "env": str, "seed": int, "config": {...},
         ["simulator": "native" | "torch",]
         "units": {name: unit},
         "train": [{"frames": int, "metrics": {name: float}}, ...],
         "evaluations": [{"frames": int, "metrics": {name: float}}, ...]}

    ``simulator`` names the program that simulated the batched freeway (``backend="torch"``;
    see :func:`~mapets_rl.experiment.runner.simulator_program`): its fused C++ kernel or its
    torch program, different experiments whatever ``env_config.kernel`` says.

    ``units`` names the unit of every recorded metric that has one (``agility: m/step``,
    ``average_velocity: m/s``, ``frames: env steps``; :data:`mapets_rl.metrics.METRIC_UNITS`).

    ``evaluations`` holds deterministic evaluations (the runner's periodic ones);
    ``train`` holds metrics of training itself (e.g. each MA-PETS episode, whose actions come
    from the planner while it learns). Rewritten atomically after every entry;
    :func:`read_results` reads it back.

    Measured durations (:data:`~mapets_rl.metrics.TIMING_METRICS`, e.g. MA-PETS's
    ``train_time``) go to ``timings.json`` instead, ``{"units": ..., "train": [...],
    "evaluations": [...]}`` with entries of the same form: ``results.json`` and the
    checkpoints of two identical runs are then the same byte for byte. :func:`read_results`
    puts them back into their entries. A resumed run keeps the timings of the entries its
    checkpoint holds.

    Results files and checkpoints written before the two were kept apart hold one list,
    ``evaluations``, of whichever kind the recipe wrote (each recipe wrote one kind). Restored
    from such a checkpoint, the entries stay unsorted, and the file keeps that layout, until
    the first new entry arrives: its kind is theirs.
    """

    def __init__(
        self,
        run_dir: str | os.PathLike,
        recipe: str,
        env: str,
        seed: int,
        config: Mapping[str, Any],
        simulator: str | None = None,
    ) -> None:
        self.path = Path(run_dir) / RESULTS_FILE
        self.timings_path = Path(run_dir) / TIMINGS_FILE
        self.header = {"recipe": recipe, "env": env, "seed": seed, "config": dict(config)}
        if simulator is not None:
            self.header["simulator"] = simulator
        self.evaluations: list[dict[str, Any]] = []
        self.train: list[dict[str, Any]] = []
        self._unsorted: list[dict[str, Any]] | None = None

    def add_evaluation(self, frames: int, metrics: Mapping[str, float]) -> None:
        """Append a deterministic evaluation at ``frames`` and rewrite the file."""
        self._add(self.evaluations, frames, metrics)

    def add_train(self, frames: int, metrics: Mapping[str, float]) -> None:
        """Append a training entry (e.g. one training episode) at ``frames`` and rewrite the
        file."""
        self._add(self.train, frames, metrics)

    def _add(
        self, entries: list[dict[str, Any]], frames: int, metrics: Mapping[str, float]
    ) -> None:
        if self._unsorted is not None:
            entries[:0] = self._unsorted
            self._unsorted = None
        entries.append(
            {"frames": int(frames), "metrics": {k: float(v) for k, v in metrics.items()}}
        )
        self.write()

    def latest_metrics(self) -> dict[str, float]:
        """Metrics of the last evaluation, else of the last training entry, else ``{}``."""
        entries = self.evaluations or self.train or self._unsorted or []
        return dict(entries[-1]["metrics"]) if entries else {}

    def state_dict(self) -> dict[str, str]:
        """The entries as JSON strings (for checkpoints): ``evaluations`` and ``train``; only
        ``evaluations`` while entries of an old checkpoint are still unsorted."""
        if self._unsorted is not None:
            return {"evaluations": json.dumps(_split(self._unsorted, timed=False))}
        return {
            "evaluations": json.dumps(_split(self.evaluations, timed=False)),
            "train": json.dumps(_split(self.train, timed=False)),
        }

    def load_state_dict(self, state: Mapping[str, Any]) -> None:
        """Restore :meth:`state_dict`'s entries; a state without ``train`` (a checkpoint
        written before training and evaluation entries were kept apart) leaves its entries
        unsorted until the next entry is added."""
        entries = json.loads(state["evaluations"])
        if "train" in state:
            self.evaluations, self.train = entries, json.loads(state["train"])
            self._unsorted = None
        else:
            self.evaluations, self.train, self._unsorted = [], [], entries
        data = (
            {"evaluations": self._unsorted}
            if self._unsorted is not None
            else {"train": self.train, "evaluations": self.evaluations}
        )
        try:  # the timings of the restored entries; those of later ones are dropped with them
            _merge_timings(data, self.timings_path)
        except ValueError as err:
            log.warning("%s; the resumed run keeps no timings of its earlier entries", err)

    def write(self) -> None:
        """Rewrite ``results.json`` (the entries without their timings) and, when any entry
        has timings (or the file exists), ``timings.json``."""
        lists = {"train": self.train, "evaluations": self.evaluations}
        if self._unsorted is not None:
            lists = {"evaluations": self._unsorted}
        kept = {kind: _split(entries, timed=False) for kind, entries in lists.items()}
        timed = {kind: _split(entries, timed=True) for kind, entries in lists.items()}
        names = ["frames", *(k for es in kept.values() for e in es for k in e["metrics"])]
        atomic_write_text(
            self.path,
            json.dumps({**self.header, "units": metric_units(names), **kept}, indent=1),
        )
        timed_names = [k for es in timed.values() for e in es for k in e["metrics"]]
        if timed_names or self.timings_path.exists():
            atomic_write_text(
                self.timings_path,
                json.dumps({"units": metric_units(timed_names), **timed}, indent=1),
            )


def _split(entries: list[dict[str, Any]], timed: bool) -> list[dict[str, Any]]:
    """The entries with only their timing metrics (``timed``; entries without any left out)
    or without them (:data:`~mapets_rl.metrics.TIMING_METRICS`)."""
    out = []
    for entry in entries:
        metrics = {k: v for k, v in entry["metrics"].items() if is_timing_metric(k) == timed}
        if metrics or not timed:
            out.append({**entry, "metrics": metrics})
    return out


def read_results(run_dir: str | os.PathLike, legacy_as: str = "eval") -> dict[str, Any]:
    """Read ``run_dir/results.json``: the header (``recipe``, ``env``, ``seed``, ``config``)
    and the entry lists ``train`` and ``evaluations`` (each ``[{"frames": int, "metrics":
    {...}}, ...]``), plus ``legacy``: whether the file predates the split of the two.

    A file written before training and evaluation entries were kept apart has only
    ``evaluations``, which held whatever its recipe wrote (MA-PETS: its training episodes);
    ``legacy_as`` says where those entries go: ``"eval"`` (default) or ``"train"``.

    Raises:
        ValueError: naming the file, when the run has none or it is not a results file
            (invalid JSON, missing ``recipe`` / ``env`` / ``evaluations``, malformed entries),
            or when ``legacy_as`` is not ``"eval"`` / ``"train"``.
    """
    if legacy_as not in SOURCES:
        raise ValueError(f"legacy_as must be one of {list(SOURCES)}, got {legacy_as!r}")
    path = Path(run_dir) / RESULTS_FILE
    if not path.is_file():
        raise ValueError(f"run_dir {str(run_dir)!r} has no {RESULTS_FILE}")
    data = read_json_object(path)
    missing = [key for key in ("recipe", "env", "evaluations") if key not in data]
    if missing:
        raise ValueError(f"{str(path)!r} is not a results file: it lacks {missing}")
    for key in ("evaluations", "train"):
        entries = data.get(key, [])
        if not isinstance(entries, list) or not all(
            isinstance(e, dict)
            and isinstance(e.get("frames"), int)
            and isinstance(e.get("metrics"), dict)
            for e in entries
        ):
            raise ValueError(
                f"{str(path)!r} is not a results file: {key!r} must be a list "
                "of {'frames': int, 'metrics': {...}}"
            )
    _merge_timings(data, Path(run_dir) / TIMINGS_FILE)
    data["legacy"] = "train" not in data
    if data["legacy"]:
        entries = data.pop("evaluations")
        data["train"], data["evaluations"] = ([], entries) if legacy_as == "eval" else (entries, [])
    return data


def read_evaluation(run_dir: str | os.PathLike) -> dict[str, Any] | None:
    """Read ``run_dir/evaluation.json`` (:data:`EVALUATION_FILE`, written by ``mapets-rl
    evaluate``): ``{"frames": int, "episodes": int, "metrics": {name: float}}``, or ``None``
    when the run has none.

    Raises:
        ValueError: naming the file, when it is not such an object.
    """
    path = Path(run_dir) / EVALUATION_FILE
    if not path.is_file():
        return None
    data = read_json_object(path)
    metrics = data.get("metrics")
    if not (
        isinstance(data.get("frames"), int)
        and isinstance(data.get("episodes"), int)
        and isinstance(metrics, dict)
        and all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in metrics.values())
    ):
        raise ValueError(
            f"{str(path)!r} is not an evaluation file: it must hold "
            "{'frames': int, 'episodes': int, 'metrics': {name: number}}"
        )
    return data


def _merge_timings(data: dict[str, Any], path: Path) -> None:
    """Put the metrics of ``timings.json`` (``path``, when there is one) back into the entries
    of ``data`` (a ``results.json``) of the same kind and frames; ValueError naming the file
    when it is not a timings file."""
    if not path.is_file():
        return
    timings = read_json_object(path)
    for kind in ("train", "evaluations"):
        entries = timings.get(kind, [])
        if not isinstance(entries, list) or not all(
            isinstance(e, dict) and isinstance(e.get("metrics"), dict) for e in entries
        ):
            raise ValueError(
                f"{str(path)!r} is not a timings file: {kind!r} must be a list "
                "of {'frames': int, 'metrics': {...}}"
            )
        by_frames = {e["frames"]: e for e in data.get(kind, []) if isinstance(e, dict)}
        for timed in entries:
            entry = by_frames.get(timed.get("frames"))
            if entry is not None and isinstance(entry.get("metrics"), dict):
                entry["metrics"].update(timed["metrics"])


def read_json_object(path: str | os.PathLike) -> dict[str, Any]:
    """The JSON object in ``path``; a one-line ValueError naming the file when it cannot be
    read, is not valid JSON or is not an object."""
    try:
        text = Path(path).read_text()
    except (OSError, UnicodeDecodeError) as err:
        reason = err.strerror if isinstance(err, OSError) and err.strerror else str(err)
        raise ValueError(f"{str(path)!r} cannot be read: {reason}") from None
    try:
        data = json.loads(text)
    except json.JSONDecodeError as err:
        raise ValueError(
            f"{str(path)!r} is not valid JSON: {err.msg} at line {err.lineno}, column {err.colno}"
        ) from None
    if not isinstance(data, dict):
        raise ValueError(f"{str(path)!r} must hold a JSON object, got {type(data).__name__}")
    return data
