"""Training episodes of the model-free loop: each episode that ended in a collected batch, its
system return (the Shapley paper's Fig. 2 quantity) and the scenario's episode metrics, kept in
the run's ``train_episodes.jsonl``.

:class:`EpisodeTracker` cuts the collected batches ``[*, T]`` (time last, one row per road or
env copy, consecutive batches continuing each row) into episodes: an episode's *system return*
is the reward summed over every CAV and step (``("next", "agents", "reward")``), its *length*
its steps; an episode begun in an earlier batch carries its partial sums over. The scenario's
metrics of each episode (``average_velocity``, ``average_comfort``, ``collisions``,
``ramp_stuck``, ...) come from the env the collector steps when it reports every episode
(:meth:`~mapets_rl.envs.torch_freeway.TorchFreewayEnv.pop_finished_episodes`, the batched
torch freeway), or from its ``last_episode_metrics`` when the batch ended exactly one episode
(an in-process highway-env env); an env in a worker process (``multi_sync``, ``ray``
collectors) gives only the system return and the length.

:class:`EpisodeLog` appends one JSON line per episode, ``{"frames": F, "system_return": x,
"length": n, ...}`` (``F``: the run's frame count after the batch the episode ended in), in
the order the episodes ended. Like the run's other logs it is cut back to a resumed run's
checkpoint (lines of a later frame count dropped) and untouched until the resumed run has
started; the collector is re-seeded and reset at every checkpoint, so episodes under way at a
checkpoint are never recorded, and a resumed run records the same episodes as an uninterrupted
one. :func:`read_train_episodes` reads the file back and :func:`window_means` gives the
paper's curve: the mean over each window of ``K`` consecutive training episodes.
"""

from __future__ import annotations

import json
import logging
import math
import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tensordict import TensorDictBase

from mapets_rl.experiment.files import atomic_write_text, open_append, read_own_file, write_failed

log = logging.getLogger(__name__)

TRAIN_EPISODES_FILE = "train_episodes.jsonl"
"""In the run directory: one JSON object per training episode, in the order they ended."""


class EpisodeTracker:
    """Cuts consecutive collected batches into finished episodes (module docstring).

    The partial sums of the episodes under way are kept between batches, per row of the batch;
    :meth:`reset` drops them (the collector's envs were reset: those episodes never end)."""

    def __init__(self) -> None:
        self._carry_return: torch.Tensor | None = None  # [R] float64
        self._carry_length: torch.Tensor | None = None  # [R] int64

    def reset(self) -> None:
        """Forget the episodes under way (call when the collector's envs are reset)."""
        self._carry_return = self._carry_length = None

    def update(self, batch: TensorDictBase) -> list[dict[str, float]]:
        """The episodes that ended in ``batch`` (shape ``[*, T]``, time last; its rows
        continue the rows of the previous batch), ordered by the step they ended at, then by
        row (the order of :meth:`TorchFreewayEnv.pop_finished_episodes`): each
        ``{"system_return": float, "length": float}``."""
        steps = batch.shape[-1] if batch.ndim else 1
        reward = batch.get(("next", "agents", "reward")).to(torch.float64)  # [*, T, I, 1]
        reward = reward.reshape(*batch.shape, -1).sum(-1).reshape(-1, steps)  # [R, T]
        done = batch.get(("next", "done")).reshape(-1, steps).bool()  # [R, T]
        rows = reward.shape[0]
        if self._carry_return is None or self._carry_return.shape[0] != rows:
            self._carry_return = torch.zeros(rows, dtype=torch.float64)
            self._carry_length = torch.zeros(rows, dtype=torch.int64)
        reward, done = reward.cpu(), done.cpu()
        csum = torch.cat([torch.zeros(rows, 1, dtype=torch.float64), reward.cumsum(-1)], -1)
        ends = done.nonzero()  # [E, 2] (row, step), sorted by row then step
        row, step = ends[:, 0], ends[:, 1]
        first = torch.ones_like(row, dtype=torch.bool)
        first[1:] = row[1:] != row[:-1]
        previous = torch.where(first, -1, torch.cat([step.new_full((1,), -1), step[:-1]]))
        returns = csum[row, step + 1] - csum[row, previous + 1]
        lengths = step - previous
        returns = returns + torch.where(first, self._carry_return[row], 0.0)
        lengths = lengths + torch.where(first, self._carry_length[row], 0)
        # what is under way at the batch's end: after each row's last end (or all of it)
        last = torch.full((rows,), -1, dtype=torch.int64).scatter_reduce(
            0, row, step, reduce="amax"
        )
        ended = last >= 0
        self._carry_return = torch.where(ended, 0.0, self._carry_return) + (
            csum[:, steps] - csum[torch.arange(rows), last + 1]
        )
        self._carry_length = torch.where(ended, 0, self._carry_length) + (steps - 1 - last)
        order = torch.argsort(step * rows + row).tolist()
        returns_list, lengths_list = returns.tolist(), lengths.tolist()
        return [{"system_return": returns_list[i], "length": float(lengths_list[i])} for i in order]


def env_episode_metrics(env: Any, count: int) -> list[dict[str, float]] | None:
    """The scenario's metrics of the ``count`` episodes that ``env`` (the env a collector
    steps, transformed or not) ended since the last call, in the order they ended; ``None``
    when it cannot tell (it reports no episodes, or not as many as ended; the latter is logged
    as a warning). Numbers only."""
    while hasattr(env, "base_env"):  # a TransformedEnv
        env = env.base_env
    pop = getattr(env, "pop_finished_episodes", None)
    if callable(pop):
        episodes = pop()
        if len(episodes) != count:
            log.warning(
                "the env reported %d finished episodes where the batch ended %d; their "
                "scenario metrics are left out",
                len(episodes),
                count,
            )
            return None
        return [_numbers(e) for e in episodes]
    last = getattr(env, "last_episode_metrics", None)
    if count == 1 and isinstance(last, Mapping) and last:
        return [_numbers(last)]
    return None


def drain_env_episodes(env: Any) -> None:
    """Drop the episodes ``env`` holds for :func:`env_episode_metrics` (after a reset of the
    collector: none of them is in a batch to come)."""
    while hasattr(env, "base_env"):
        env = env.base_env
    pop = getattr(env, "pop_finished_episodes", None)
    if callable(pop):
        pop()


def _numbers(metrics: Mapping[str, Any]) -> dict[str, float]:
    return {
        k: float(v)
        for k, v in metrics.items()
        if isinstance(v, (int, float)) and not isinstance(v, bool)
    }


def summarize_episodes(episodes: Sequence[Mapping[str, float]]) -> dict[str, float]:
    """Per-iteration training metrics of the episodes that ended in it: ``episodes`` (their
    count, also when 0) and the mean of every metric over the episodes that have it."""
    out: dict[str, float] = {"episodes": float(len(episodes))}
    sums: dict[str, float] = {}
    counts: dict[str, int] = {}
    for episode in episodes:
        for key, value in episode.items():
            sums[key] = sums.get(key, 0.0) + float(value)
            counts[key] = counts.get(key, 0) + 1
    out.update({key: sums[key] / counts[key] for key in sums})
    return out


class EpisodeLog:
    """The run's :data:`TRAIN_EPISODES_FILE`, appended to after each iteration.

    A resumed run's log is created ``deferred``: the episodes are kept in memory, and the file
    is not touched, until :meth:`open` is called with the checkpoint's frame count (once the
    resumed run has started); :meth:`open` then drops the lines of a later frame count (and any
    line a killed process left half written) and writes what was kept. A fresh run opens it at
    once with ``keep_frames=0``: a file of an earlier attempt that never checkpointed is
    removed."""

    def __init__(self, run_dir: str | os.PathLike, deferred: bool = False) -> None:
        self.path = Path(run_dir) / TRAIN_EPISODES_FILE
        self._pending: list[str] | None = []
        if not deferred:
            self.open(0)

    @property
    def is_open(self) -> bool:
        return self._pending is None

    def open(self, keep_frames: int | None) -> None:
        """Cut the file back to the episodes of frame counts up to ``keep_frames`` (``None``:
        leave it as it is) and write the episodes kept meanwhile; no-op once open. A file that
        is a symbolic link is removed, never read or written through, and one with other names
        (a hard link) is replaced by a file of its own
        (:func:`~mapets_rl.experiment.files.read_own_file`)."""
        if self._pending is None:
            return
        pending, self._pending = self._pending, None
        read = read_own_file(self.path) if keep_frames is not None else None
        if read is not None:  # rewritten: a hard link is replaced by a file of its own
            kept = [
                line
                for line in read[0].splitlines(keepends=True)
                if _line_frames(line) is not None and _line_frames(line) <= keep_frames
            ]
            if kept:
                atomic_write_text(self.path, "".join(kept))
            else:
                self.path.unlink()
        self._write(pending)

    def append(self, frames: int, episodes: Sequence[Mapping[str, float]]) -> None:
        """Record ``episodes`` as ended by ``frames`` frames (in memory until :meth:`open`)."""
        lines = [
            json.dumps({"frames": int(frames), **{k: float(v) for k, v in e.items()}}) + "\n"
            for e in episodes
        ]
        if self._pending is not None:
            self._pending.extend(lines)
        else:
            self._write(lines)

    def _write(self, lines: list[str]) -> None:
        if not lines:
            return
        try:
            with open_append(self.path) as f:
                f.write("".join(lines))
        except OSError as err:
            raise write_failed(self.path, err) from None


def _line_frames(line: str) -> int | None:
    """The frame count of a complete, valid line of the file, else ``None``."""
    if not line.endswith("\n"):
        return None
    try:
        data = json.loads(line)
    except json.JSONDecodeError:
        return None
    frames = data.get("frames") if isinstance(data, dict) else None
    return frames if isinstance(frames, int) and not isinstance(frames, bool) else None


def read_train_episodes(run_dir: str | os.PathLike) -> dict[str, np.ndarray]:
    """The training episodes of ``run_dir`` (:data:`TRAIN_EPISODES_FILE`), one array ``[N]``
    per field in the order the episodes ended: ``frames`` (int64), ``system_return``,
    ``length`` and the scenario's metrics (float64; NaN for an episode that lacks one).
    Empty arrays for a run with no file (no episode ended, or a recipe that records none).
    A half-written last line (a killed process) is skipped; ValueError naming the file for any
    other invalid line."""
    path = Path(run_dir) / TRAIN_EPISODES_FILE
    rows: list[dict[str, Any]] = []
    if path.is_file():
        lines = path.read_text(errors="replace").splitlines(keepends=True)
        for number, line in enumerate(lines, 1):
            if _line_frames(line) is None:
                if number == len(lines) and not line.endswith("\n"):
                    continue
                raise ValueError(f"{str(path)!r} line {number} is not a training episode")
            rows.append(json.loads(line))
    keys = ["frames", "system_return", "length"]
    keys += sorted({k for row in rows for k in row} - set(keys))
    out = {k: np.array([row.get(k, math.nan) for row in rows], dtype=np.float64) for k in keys}
    out["frames"] = out["frames"].astype(np.int64)
    return out


def window_means(values: Sequence[float] | np.ndarray, window: int) -> np.ndarray:
    """Means ``[N // window]`` of ``values`` ``[N]`` over consecutive windows of ``window``
    episodes (the Shapley paper's Fig. 2 averages every 1,000 training episodes); an
    incomplete last window is left out. ValueError unless ``window >= 1``."""
    if window < 1:
        raise ValueError(f"window must be >= 1, got {window}")
    values = np.asarray(values, dtype=np.float64)
    full = len(values) // window
    return values[: full * window].reshape(full, window).mean(-1)
