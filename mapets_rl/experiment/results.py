"""Loggers (torchrl.record.loggers), the per-run results JSON, and metric aggregation."""

from __future__ import annotations

import json
import math
import os
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

from torchrl.record.loggers import CSVLogger, Logger, TensorboardLogger, WandbLogger

from mapets_rl.experiment.config import LOGGERS, atomic_write_text, check_logger_package

RESULTS_FILE = "results.json"


def make_logger(kind: str, run_dir: str | os.PathLike, exp_name: str) -> Logger | None:
    """A torchrl logger writing under ``run_dir/logs``.

    Args:
        kind: ``"csv"`` (always available), ``"tensorboard"`` (needs the tensorboard package),
            ``"wandb"`` (needs wandb; runs offline unless WANDB_MODE says otherwise) or
            ``"none"`` (returns None).
        run_dir: the run directory.
        exp_name: experiment name (a sub-directory of ``logs``).
    """
    if kind not in LOGGERS:
        raise ValueError(f"logger must be one of {list(LOGGERS)}, got {kind!r}")
    check_logger_package(kind)
    log_dir = str(Path(run_dir) / "logs")
    if kind == "none":
        return None
    if kind == "csv":
        return CSVLogger(exp_name=exp_name, log_dir=log_dir)
    if kind == "tensorboard":
        return TensorboardLogger(exp_name=exp_name, log_dir=log_dir)
    return WandbLogger(exp_name=exp_name, save_dir=log_dir,
                       offline=os.environ.get("WANDB_MODE", "offline") == "offline")


def log_scalars(logger: Logger | None, prefix: str, values: Mapping[str, float], step: int) -> None:
    """Log ``{prefix}/{name}`` for every finite scalar of ``values`` at ``step`` (frames)."""
    if logger is None:
        return
    for name, value in values.items():
        if isinstance(value, (int, float)) and math.isfinite(value):
            logger.log_scalar(f"{prefix}/{name}", float(value), step=step)


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


class ResultsWriter:
    """The run's ``results.json``: identity of the run plus one entry per evaluation.

    Layout::

        {"recipe": str, "env": str, "seed": int, "config": {...},
         "evaluations": [{"frames": int, "metrics": {name: float}}, ...]}

    Rewritten atomically after every evaluation; :func:`read_results` reads it back.
    """

    def __init__(self, run_dir: str | os.PathLike, recipe: str, env: str, seed: int,
                 config: Mapping[str, Any]) -> None:
        self.path = Path(run_dir) / RESULTS_FILE
        self.header = {"recipe": recipe, "env": env, "seed": seed, "config": dict(config)}
        self.evaluations: list[dict[str, Any]] = []

    def add(self, frames: int, metrics: Mapping[str, float]) -> None:
        self.evaluations.append({"frames": int(frames),
                                 "metrics": {k: float(v) for k, v in metrics.items()}})
        self.write()

    def write(self) -> None:
        atomic_write_text(self.path, json.dumps({**self.header, "evaluations": self.evaluations},
                                                indent=1))


def read_results(run_dir: str | os.PathLike) -> dict[str, Any]:
    """Read ``run_dir/results.json``; a ValueError naming the file when the run has none or it
    is not a results file (invalid JSON, missing ``recipe`` / ``env`` / ``evaluations``)."""
    path = Path(run_dir) / RESULTS_FILE
    if not path.is_file():
        raise ValueError(f"run_dir {str(run_dir)!r} has no {RESULTS_FILE}")
    data = read_json_object(path)
    missing = [key for key in ("recipe", "env", "evaluations") if key not in data]
    if missing:
        raise ValueError(f"{str(path)!r} is not a results file: it lacks {missing}")
    evaluations = data["evaluations"]
    if not isinstance(evaluations, list) or not all(
            isinstance(e, dict) and isinstance(e.get("frames"), int)
            and isinstance(e.get("metrics"), dict) for e in evaluations):
        raise ValueError(f"{str(path)!r} is not a results file: 'evaluations' must be a list "
                         "of {'frames': int, 'metrics': {...}}")
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
        raise ValueError(f"{str(path)!r} is not valid JSON: {err.msg} at line {err.lineno}, "
                         f"column {err.colno}") from None
    if not isinstance(data, dict):
        raise ValueError(f"{str(path)!r} must hold a JSON object, got {type(data).__name__}")
    return data
