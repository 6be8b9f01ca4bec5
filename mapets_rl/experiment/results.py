"""Loggers (torchrl.record.loggers), the per-run results JSON, and metric aggregation."""

from __future__ import annotations

import json
import math
import os
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

from torchrl.record.loggers import CSVLogger, Logger, TensorboardLogger, WandbLogger

from mapets_rl.experiment.config import LOGGERS, check_logger_package
from mapets_rl.experiment.files import atomic_write_text
from mapets_rl.metrics import METRIC_UNITS, metric_unit

RESULTS_FILE = "results.json"
UNITS_FILE = "units.json"
"""Written beside the logger's files (``RUN_DIR/logs/units.json``): metric name -> unit."""


def make_logger(kind: str, run_dir: str | os.PathLike, exp_name: str) -> Logger | None:
    """A torchrl logger writing under ``run_dir/logs``.

    Args:
        kind: ``"csv"`` (always available), ``"tensorboard"`` (needs the tensorboard package),
            ``"wandb"`` (needs wandb; runs offline unless WANDB_MODE says otherwise) or
            ``"none"`` (returns None). ``run_dir/logs/units.json`` names the unit of every
            metric (:data:`mapets_rl.metrics.METRIC_UNITS`).
        run_dir: the run directory.
        exp_name: experiment name (a sub-directory of ``logs``).
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
        return CSVLogger(exp_name=exp_name, log_dir=log_dir)
    if kind == "tensorboard":
        return TensorboardLogger(exp_name=exp_name, log_dir=log_dir)
    return WandbLogger(
        exp_name=exp_name,
        save_dir=log_dir,
        offline=os.environ.get("WANDB_MODE", "offline") == "offline",
    )


def log_scalars(logger: Logger | None, prefix: str, values: Mapping[str, float], step: int) -> None:
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
         "units": {name: unit},
         "train": [{"frames": int, "metrics": {name: float}}, ...],
         "evaluations": [{"frames": int, "metrics": {name: float}}, ...]}

    ``units`` names the unit of every recorded metric that has one (``agility: m/step``,
    ``average_velocity: m/s``, ``frames: env steps``; :data:`mapets_rl.metrics.METRIC_UNITS`).

    ``evaluations`` holds deterministic evaluations (the runner's periodic ones);
    ``train`` holds metrics of training itself (e.g. each MA-PETS episode, whose actions come
    from the planner while it learns). Rewritten atomically after every entry;
    :func:`read_results` reads it back.

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
    ) -> None:
        self.path = Path(run_dir) / RESULTS_FILE
        self.header = {"recipe": recipe, "env": env, "seed": seed, "config": dict(config)}
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
            return {"evaluations": json.dumps(self._unsorted)}
        return {"evaluations": json.dumps(self.evaluations), "train": json.dumps(self.train)}

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

    def write(self) -> None:
        entries = (self._unsorted or []) + self.train + self.evaluations
        units = metric_units(["frames", *(k for e in entries for k in e["metrics"])])
        header = {**self.header, "units": units}
        if self._unsorted is not None:
            data = {**header, "evaluations": self._unsorted}
        else:
            data = {**header, "train": self.train, "evaluations": self.evaluations}
        atomic_write_text(self.path, json.dumps(data, indent=1))


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
    data["legacy"] = "train" not in data
    if data["legacy"]:
        entries = data.pop("evaluations")
        data["train"], data["evaluations"] = ([], entries) if legacy_as == "eval" else (entries, [])
    return data


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
