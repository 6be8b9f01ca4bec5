"""The run loop every recipe shares: iterate (collect -> train_step) -> log -> evaluate ->
checkpoint.

A recipe subclasses :class:`Experiment`; see the package docstring of
:mod:`mapets_rl.experiment` for the contract.
"""

from __future__ import annotations

import contextlib
import functools
import json
import logging
import os
import re
import shutil
import signal
import sys
import threading
import time
from collections.abc import Callable, Iterator, Mapping
from datetime import datetime, timezone
from pathlib import Path
from typing import Any, ClassVar

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torchrl.collectors import BaseCollector, Collector, MultiSyncCollector
from torchrl.envs import EnvBase, TransformedEnv
from torchrl.envs.utils import ExplorationType, set_exploration_type, step_mdp
from tqdm import tqdm

from mapets_rl._entry_points import check_name
from mapets_rl.config import ConfigError, parse_override, read_yaml_mapping
from mapets_rl.envs import scenario_config
from mapets_rl.envs.registry import build_env
from mapets_rl.envs.torch_freeway.simulator import BatchedFreeway, check_roads_fit
from mapets_rl.experiment.checkpoint import (
    first_line,
    list_checkpoints,
    load_latest_checkpoint,
    remove_stale_files,
    rng_state,
    save_checkpoint,
    seed_everything,
    set_rng_state,
)
from mapets_rl.experiment.config import ExperimentConfig, RunConfig, check_device
from mapets_rl.experiment.episodes import (
    EpisodeLog,
    EpisodeTracker,
    drain_env_episodes,
    env_episode_metrics,
    summarize_episodes,
)
from mapets_rl.experiment.files import (
    OWN_FILES,
    RunDirLock,
    atomic_write,
    atomic_write_text,
    check_run_subdirs,
    check_writable_dir,
    make_writable_dir,
)
from mapets_rl.experiment.results import (
    ResultsWriter,
    RunLogger,
    log_scalars,
    mean_metrics,
    read_json_object,
)
from mapets_rl.modules import AgentGroupSpec, masked_mean
from mapets_rl.modules.tensor_checks import check_finite_many
from mapets_rl.threads import announce_threads, config_threads, configure_threads

log = logging.getLogger(__name__)

CONFIG_FILE = "config.yaml"
RUN_FILE = "run.json"
_TEMP_FILE = re.compile(r"^\..+\.tmp(\.[^.]+)?$")
"""Temp files of atomic writes and write probes (``.<name>.<random>.tmp<ext>``), which an
interrupted run of ours leaves behind."""
EVAL_SEED_OFFSET = 1_000_003
BOUNDARY_SEED_STRIDE = 7_919


def default_run_dir(recipe: str, env: str, seed: int, root: str | os.PathLike = "runs") -> Path:
    """``runs/<recipe>_<env>_seed<seed>_<UTC timestamp>``; ValueError when ``recipe`` or
    ``env`` is not a valid name (a path separator, ``..``, a control character), which would
    put the directory elsewhere than below ``root``."""
    check_name(recipe, "recipe")
    check_name(env, "scenario")
    stamp = datetime.now(timezone.utc).strftime("%Y%m%d-%H%M%S-%f")
    return Path(root) / f"{recipe}_{env}_seed{seed}_{stamp}"


STOP_SIGNALS = (signal.SIGTERM,)
"""The signals a training loop stops at (see :meth:`Experiment.training_loop`): SIGTERM, which
Slurm's preemption and ``timeout`` send."""


class RunStopped(Exception):
    """A training loop stopped at a signal (SIGTERM) after writing a checkpoint of the
    iteration it was in: ``mapets-rl resume`` (or ``from_run_dir``) continues the run.

    Attributes:
        signum: the signal.
        run_dir: the run directory.
        frames: the run's frames at the checkpoint.
    """

    def __init__(self, signum: int, run_dir: Path, frames: int) -> None:
        self.signum, self.run_dir, self.frames = signum, run_dir, frames
        super().__init__(
            f"stopped by {signal.Signals(signum).name} at frame {frames}: the run's checkpoint "
            f"is written, continue it with `mapets-rl resume {run_dir}`"
        )


class NonFiniteData(ValueError):
    """A collected batch holds NaN or infinite observations or rewards, which a run does not
    train on (see :meth:`Experiment.refuse_non_finite`): one line naming the entry."""


class TrainingLoop:
    """The bookkeeping of a training loop (see :meth:`Experiment.training_loop`), done by
    :meth:`end_iteration` after each iteration; ``finished`` is whether
    :meth:`Experiment.progress` (``(done, total)``) has reached its total, or a stop signal
    arrived (``stop_signal``, set by :meth:`Experiment.training_loop`'s handler).

    Args:
        experiment: the experiment being trained.
        bar: the progress bar, counting ``progress()`` units.
        on_iteration_end: called with each iteration's metrics (or ``None``).
        postfix: ``(metrics, fps) -> {name: text}``, what the bar shows after an iteration.
        eval_interval: evaluate every this many ``progress()`` units and after the last
            iteration (0: only after the last; ``None``: never).
        checkpoint_interval: checkpoint every this many ``progress()`` units and after the
            last iteration (0: only after the last).
        train_entries: keep each iteration's metrics in ``results.json`` as a training entry
            (and show them as the latest metrics).
    """

    def __init__(
        self,
        experiment: Experiment,
        bar: tqdm,
        on_iteration_end: Callable[[dict[str, float]], None] | None,
        postfix: Callable[[Mapping[str, float], float], dict[str, str]],
        *,
        eval_interval: int | None,
        checkpoint_interval: int,
        train_entries: bool,
    ) -> None:
        self.experiment = experiment
        self.bar = bar
        self.on_iteration_end = on_iteration_end
        self.postfix = postfix
        self.eval_interval = eval_interval
        self.checkpoint_interval = checkpoint_interval
        self.train_entries = train_entries
        self.done, self.total = experiment.progress()
        self.start, self.start_frames = time.perf_counter(), experiment.frames

    stop_signal: int | None = None
    """The stop signal (:data:`STOP_SIGNALS`) received during the loop, if any: the iteration
    under way ends with a checkpoint and the loop then finishes."""

    @property
    def finished(self) -> bool:
        return self.done >= self.total or self.stop_signal is not None

    def end_iteration(self, metrics: dict[str, float]) -> None:
        """After an iteration that advanced :meth:`Experiment.progress`, in this order: write
        what a resumed run deferred; log ``metrics`` under ``train`` and the frames per second
        under ``timers``; keep ``metrics`` as a training entry (with ``train_entries``);
        evaluate and checkpoint when due (see the class docstring); call
        ``on_iteration_end(metrics)``; advance the progress bar.

        An evaluation that fails (e.g. its video cannot be written) first writes the
        checkpoint due at this iteration, without that evaluation, so the training done is
        kept; then its error propagates. After a stop signal (``stop_signal``) the iteration
        ends with a checkpoint, the scheduled one or one more."""
        exp = self.experiment
        exp._start_writing()
        elapsed = max(time.perf_counter() - self.start, 1e-9)
        fps = (exp.frames - self.start_frames) / elapsed
        log_scalars(exp.logger, "train", metrics, exp.frames)
        log_scalars(exp.logger, "timers", {"fps": fps}, exp.frames)
        previous = self.done
        self.done, self.total = exp.progress()
        last = self.done >= self.total  # (a stop signal ends the loop, not the run)
        if self.train_entries:
            exp.results.add_train(exp.frames, metrics)
            exp.latest_metrics = dict(metrics)
        checkpoint_due = last or _crossed(previous, self.done, self.checkpoint_interval)
        if self.eval_interval is not None and (
            last or _crossed(previous, self.done, self.eval_interval)
        ):
            try:
                evaluation = exp.evaluate()
            except Exception:
                if checkpoint_due:
                    exp._save_boundary_checkpoint(last)
                raise
            exp.results.add_evaluation(exp.frames, evaluation)
            log_scalars(exp.logger, "eval", evaluation, exp.frames)
            exp.latest_metrics = evaluation
        if checkpoint_due:
            exp._save_boundary_checkpoint(last)
        if self.on_iteration_end is not None:
            self.on_iteration_end(metrics)
        self.bar.update(self.done - previous)
        self.bar.set_postfix(self.postfix(metrics, fps))
        if self.stop_signal is not None and not (last or checkpoint_due):
            # stopped between two scheduled checkpoints: keep this iteration's training
            exp._save_boundary_checkpoint(True)


class Experiment:
    """Base class of recipes: owns the run directory, seeding, collector, logger, evaluation,
    checkpoints and results; the recipe supplies modules, losses and one training step.

    Subclasses set ``name`` and ``Config`` and implement :meth:`train_step`,
    :meth:`stateful_components`; they build their modules in ``__init__`` after
    ``super().__init__`` and set ``self.collector = self.make_collector(policy)`` and
    ``self.eval_policy``.

    :meth:`train` is the model-free loop: an iteration collects one batch and passes it to
    :meth:`train_step`, on the frame budget of an :class:`ExperimentConfig`, then evaluates
    every ``eval_interval`` and checkpoints every ``checkpoint_interval`` frames. A recipe
    with another unit of work (MA-PETS: one episode of its Algorithm 1 per iteration, on a
    :class:`RunConfig` without a frame budget) writes its own ``train`` as one loop on
    :meth:`training_loop` and overrides :meth:`progress`; both loops end each iteration with
    one call, :meth:`TrainingLoop.end_iteration` (logging, results, evaluation and checkpoint
    when due, the ``on_iteration_end`` callback, the progress bar).

    An experiment is the only writer of its run directory: it takes the directory's
    :class:`~mapets_rl.experiment.files.RunDirLock` before it writes anything there (a second
    experiment on the same directory, in this process or another, is refused with one line
    naming the holder's pid) and holds it until :meth:`train` returns or :meth:`close` is
    called (or the object is garbage collected, or the process dies). :meth:`train` and
    :meth:`save_checkpoint` take it again when it was released.
    """

    name: ClassVar[str] = "experiment"
    Config: ClassVar[type[RunConfig]] = ExperimentConfig
    action_kinds: ClassVar[tuple[str, ...]] = ("continuous", "discrete")
    """The kinds of per-agent actions the recipe handles: ``"continuous"`` (a Bounded spec)
    and/or ``"discrete"`` (one-hot); ``mapets-rl train RECIPE --help`` lists the scenarios
    whose actions are of one of these kinds."""
    action_kinds_reason: ClassVar[str] = ""
    """Why the recipe takes only :attr:`action_kinds` (said in the refusal of another kind)."""
    progress_unit: ClassVar[str] = "frame"
    resumable_fields: ClassVar[frozenset[str]] = frozenset(
        {
            "total_frames",
            "eval_interval",
            "eval_roads",
            "eval_references",
            "checkpoint_interval",
            "keep_last",
            "device",
            "logger",
            "progress",
            "video",
        }
    )
    """The config fields a resume may change (:meth:`from_run_dir`): the budget
    (``total_frames``; a recipe with another unit adds its own, MA-PETS ``episodes``), the
    intervals (``eval_interval``, ``checkpoint_interval``) and where and how the run is kept
    and shown (``keep_last``, ``device``, ``logger``, ``progress``, ``video``). A resume that
    changes any other field (``gamma``, a network size, the scenario's settings) is refused:
    the run's results would be attributed to settings it was not trained with."""
    # set by from_run_dir on the instance before __init__ runs: the run directory's checkpoints
    # are the ones being restored; the run directory is written to only once the resumed run
    # has started (see _start_writing)
    _resuming: bool = False
    # what a resumed run writes once its first iteration has succeeded (see _start_writing):
    # None when there is nothing left to write
    _deferred: dict[str, Any] | None = None
    # the run directory's lock while this experiment may write there (see close)
    _lock: RunDirLock | None = None
    # the batches of this process whose train_step returned losses (made an update)
    _batches_updated: int = 0
    # whether this new run created its run directory (removed if the run fails to start)
    _made_run_dir: bool = False

    def __init_subclass__(cls, **kwargs: Any) -> None:
        """Wrap a recipe's own ``__init__`` so that an instance whose construction fails
        releases the run directory's lock at once (a traceback kept alive, e.g. by a notebook
        or ``pytest.raises``, would otherwise hold it until it is collected), and removes the
        run directory it made (:meth:`_abandon`)."""
        super().__init_subclass__(**kwargs)
        init = cls.__dict__.get("__init__")
        if init is None or getattr(init, "_releases_lock_on_error", False):
            return

        @functools.wraps(init)
        def __init__(self: Experiment, *args: Any, **kw: Any) -> None:
            try:
                init(self, *args, **kw)
            except BaseException:
                self._abandon()
                raise

        __init__._releases_lock_on_error = True  # type: ignore[attr-defined]
        cls.__init__ = __init__  # type: ignore[method-assign]

    def __init__(
        self,
        config: RunConfig,
        run_dir: str | os.PathLike | None = None,
        env: EnvBase | None = None,
    ) -> None:
        """``env`` is the environment to train on, evaluate on and read the specs of (default:
        ``config.env`` with ``config.env_config``, one road of it when ``env_config.num_envs``
        batches the env; the collector builds the batched one); a recipe that transforms the
        scenario (MA-PETS appends its communication transform) builds it in its own
        ``__init__`` and passes it here."""
        if not isinstance(config, self.Config):
            raise ValueError(
                f"config must be a {self.Config.__name__}, got {type(config).__name__}"
            )
        self.config = config
        self.run_dir = (
            Path(run_dir)
            if run_dir is not None
            else default_run_dir(self.name, config.env, config.seed)
        )
        restoring = self._resuming
        check_writable_dir(self.run_dir if run_dir is None else run_dir)  # '' is refused
        if not restoring:
            self._refuse_occupied_dir()
        seed_everything(config.seed)
        self.threads = configure_threads(config_threads(config))
        self.device = torch.device(config.device)
        self.frames = 0
        self.batches = 0
        self.boundaries = 0
        # a bad env_config fails here, before the run directory is touched
        self.env = build_env(config.env, config.unbatched_env_config()) if env is None else env
        try:
            self.refuse_action_kind(self.env, config.env)
            check_batch_fits(self.env, config.env_batch_size)
        except ValueError:
            self.env.close()
            raise
        made = not restoring and not os.path.lexists(self.run_dir)
        make_writable_dir(self.run_dir)
        self._made_run_dir = made
        try:
            self._init_run_dir(restoring)
        except BaseException:
            self._abandon()
            raise
        if run_dir is None:  # a directory the caller did not name: say where the run goes
            print(f"{self.name}: writing the run to {self.run_dir}", file=sys.stderr)
        self.collector: BaseCollector | None = None
        self._collector_args: tuple[TensorDictModuleBase, int, dict[str, Any]] | None = None
        self.eval_policy: TensorDictModuleBase | None = None
        self.latest_metrics: dict[str, float] = {}
        self._video_env: EnvBase | None = None
        self._reference_scores: dict[str, Any] = {}  # the protocol's references, by name

    @classmethod
    def refuse_action_kind(cls, env: EnvBase, env_name: str) -> None:
        """ValueError when the actions of ``env`` (scenario ``env_name``) are not of a kind in
        :attr:`action_kinds`, with :attr:`action_kinds_reason`; the caller closes ``env``."""
        if {"continuous", "discrete"} <= set(cls.action_kinds):
            return
        kind = "discrete" if AgentGroupSpec.from_env(env).discrete else "continuous"
        if kind not in cls.action_kinds:
            reason = f" ({cls.action_kinds_reason})" if cls.action_kinds_reason else ""
            raise ValueError(
                f"{cls.name} needs {' or '.join(cls.action_kinds)} actions{reason}; env "
                f"{env_name!r} has {kind} actions"
            )

    def _init_run_dir(self, restoring: bool) -> None:
        """Lock the (existing) run directory, then prepare it: stale temp files removed,
        ``config.yaml`` and ``run.json`` written, logger and results writer opened (unless
        ``restoring``: a resumed run writes its config, results and logs only once its first
        iteration has succeeded, see :meth:`_start_writing`)."""
        self._hold_lock()
        check_run_subdirs(self.run_dir)
        config = self.config
        if not restoring:  # again under the lock: a writer that held it may have finished
            self._refuse_occupied_dir()
        remove_stale_files(self.run_dir)
        self.simulator = simulator_program(self.env)
        if not restoring:  # run.json first: it marks the directory as a run directory of ours
            record = {"recipe": self.name, "env": config.env, "seed": config.seed}
            if self.simulator is not None:
                record["simulator"] = self.simulator
            atomic_write_text(self.run_dir / RUN_FILE, json.dumps(record))
            config.to_yaml(self.run_dir / CONFIG_FILE)
        self.logger: RunLogger | None = None
        if config.logger != "none":
            self.logger = RunLogger(
                config.logger, self.run_dir, f"{self.name}_{config.env}", deferred=restoring
            )
        if restoring:
            self._deferred = {"config": False, "results": False, "frames": 0, "log_steps": {}}
        self.results = ResultsWriter(
            self.run_dir, self.name, config.env, config.seed, config.to_dict(), self.simulator
        )
        self.episode_log = EpisodeLog(self.run_dir, deferred=restoring)
        self.episode_tracker = EpisodeTracker()

    def _refuse_occupied_dir(self) -> None:
        """ValueError when the run directory of a new run already holds checkpoints (of
        another run), or holds files but is not a run directory (no valid ``run.json``; only
        the lock and a sweep's trial records, :data:`~mapets_rl.experiment.files.OWN_FILES`,
        may precede it): another program's files are never overwritten. A run directory whose
        earlier attempt never checkpointed is started afresh."""
        if list_checkpoints(self.run_dir):
            raise ValueError(
                f"run_dir {str(self.run_dir)!r} already holds a run with "
                "checkpoints; continue it with from_run_dir / `mapets-rl resume` "
                "or choose another run_dir"
            )
        if not self.run_dir.is_dir():
            return
        try:
            run_recipe_name(self.run_dir)
            return  # a run directory of ours
        except ValueError:
            pass  # no run.json, or one that is not ours: refused below when not empty
        theirs = sorted(
            entry.name
            for entry in self.run_dir.iterdir()
            if entry.name not in OWN_FILES and not _TEMP_FILE.match(entry.name)
        )
        if theirs:
            shown = ", ".join(repr(name) for name in theirs[:3])
            more = f" and {len(theirs) - 3} more" if len(theirs) > 3 else ""
            raise ValueError(
                f"run_dir {str(self.run_dir)!r} is not empty and is not a run directory (no "
                f"valid {RUN_FILE}; it holds {shown}{more}): its files would be overwritten; "
                "choose a new or empty directory"
            )

    def _abandon(self) -> None:
        """After a failed construction: remove the run directory when this new run made it and
        still holds its lock (so a run that fails to start, e.g. on a recipe's refusal of the
        scenario's actions, leaves no half-made run directory, and nothing there is anyone
        else's), then release the lock (see :meth:`close`)."""
        if self._made_run_dir and self._lock is not None and self._lock.held:
            shutil.rmtree(self.run_dir, ignore_errors=True)
        self.close()

    def _hold_lock(self) -> None:
        """Take the run directory's lock unless this experiment holds it already;
        :class:`~mapets_rl.experiment.files.RunDirLocked` (one line naming the holder's pid)
        when another writer has it."""
        if self._lock is None or not self._lock.held:
            self._lock = RunDirLock.acquire(self.run_dir)

    def close(self) -> None:
        """Release the run directory's lock (idempotent): another experiment may then write
        there. :meth:`train` calls it when it returns; :meth:`train` and
        :meth:`save_checkpoint` take the lock again when called later."""
        lock, self._lock = self._lock, None
        if lock is not None:
            lock.release()

    def __enter__(self) -> Experiment:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ------------------------------------------------------------------ recipe-facing helpers
    def modules_to_device(self) -> None:
        """Move every torch module this experiment holds (policies, critics, normalisers,
        exploration modules; not the environments, which step on the CPU) to
        ``config.device``. :meth:`make_collector` calls it, so the collector's policy, the
        losses and optimisers a recipe builds after it, and ``eval_policy`` share one device."""
        for value in vars(self).values():
            if isinstance(value, torch.nn.Module) and not isinstance(value, EnvBase):
                value.to(self.device)

    def make_collector(
        self, policy: TensorDictModuleBase, init_random_frames: int = 0, **kwargs: Any
    ) -> BaseCollector:
        """An endless torchrl collector for ``policy``, of the kind ``config.collector`` names
        (see :class:`ExperimentConfig`): ``Collector`` in this process, ``MultiSyncCollector``
        with ``collector_workers`` worker processes, or torchrl's ``RayCollector`` with
        ``collector_workers`` remote collectors (one CPU each; synchronous, so each batch holds
        ``frames_per_batch / collector_workers`` steps of every env); the run loop stops it at
        ``total_frames``. A batched env (``env_config.num_envs = B`` roads) is stepped by one
        ``Collector``, whose batches are ``[B, frames_per_batch / B]`` (road, time). The
        first ``init_random_frames`` frames of the run use uniformly random actions (counted
        over the whole run, resumes included). Extra ``kwargs`` go to the collector (to each
        remote collector with ``"ray"``)."""
        if init_random_frames < 0:
            raise ValueError(f"init_random_frames must be >= 0, got {init_random_frames}")
        self.modules_to_device()
        self._collector_args = (policy, init_random_frames, kwargs)
        cfg = self.config
        remaining = max(init_random_frames - self.frames, 0)
        env_fn = functools.partial(build_env, cfg.env, cfg.env_config)
        kind = cfg.collector
        if kind == "auto":
            kind = "single" if cfg.collector_workers == 1 else "multi_sync"
        if kind == "ray":
            return _ray_collector(env_fn, policy, cfg, self.device, remaining, kwargs)
        if remaining:
            kwargs = {**kwargs, "init_random_frames": remaining}
        common = dict(
            frames_per_batch=cfg.frames_per_batch,
            total_frames=-1,
            device=self.device,
            exploration_type=ExplorationType.RANDOM,
            auto_register_policy_transforms=False,
        )
        common.update(kwargs)
        if kind == "single":
            return Collector(env_fn, policy, **common)
        with _stop_signals_ignored():  # by the workers it starts: the run stops them
            return MultiSyncCollector([env_fn] * cfg.collector_workers, policy, **common)

    def train_step(self, batch: TensorDictBase) -> dict[str, float]:
        """Consume one collected batch (extend buffers, optimise); return scalar losses."""
        raise NotImplementedError

    def stateful_components(self) -> dict[str, Any]:
        """Objects with ``state_dict``/``load_state_dict`` that a checkpoint must hold
        (modules, losses, optimisers, replay buffers, schedulers)."""
        raise NotImplementedError

    def batch_metrics(self, batch: TensorDictBase) -> dict[str, float]:
        """Training metrics of a collected batch [*, T] (time last; [B, T] from B roads): mean
        reward of the CAVs alive (``("agents", "mask")``) and, on the freeway, the mean traffic
        velocity and comfort."""
        mask = batch.get(("next", "agents", "mask"), None)
        out = {"reward": masked_mean(batch.get(("next", "agents", "reward")), mask)}
        info = batch.get(("next", "agents", "info"), None)
        if info is not None:
            for key in ("traffic_velocity", "traffic_comfort"):
                if key in info.keys():
                    out[key.removeprefix("traffic_")] = masked_mean(info.get(key), mask)
        return out

    def episode_metrics(self, rollout: TensorDictBase) -> dict[str, float]:
        """Metrics of one evaluation episode ``rollout`` (shape [T]).

        ``reward``: mean reward per step of the CAVs alive; ``return``: per-CAV summed reward,
        averaged over CAVs; ``length``: steps; plus the scenario's episode metrics that the env
        reports in ``last_episode_metrics`` (figure-eight: agility, safety, mean speed; freeway:
        velocity, comfort).
        """
        reward = rollout.get(("next", "agents", "reward")).float()  # [T, I, 1]
        out = {
            "reward": masked_mean(reward, rollout.get(("next", "agents", "mask"), None)),
            "return": reward.sum(0).mean().item(),
            "length": float(rollout.shape[0]),
        }
        scenario = getattr(self.env, "last_episode_metrics", None)
        if isinstance(scenario, Mapping):
            out.update({k: float(v) for k, v in scenario.items() if isinstance(v, (int, float))})
        return out

    # --------------------------------------------------------------------------- the loop
    def train(
        self, on_iteration_end: Callable[[dict[str, float]], None] | None = None
    ) -> list[dict[str, Any]]:
        """Run (or continue) training until :meth:`progress` reaches ``config.total_frames``:
        each iteration collects a batch and passes it to :meth:`train_step`; then
        :meth:`TrainingLoop.end_iteration` logs its metrics, evaluates every
        ``eval_interval`` frames, checkpoints every ``checkpoint_interval`` frames (both after
        the last iteration too) and calls ``on_iteration_end(metrics)``. Returns the
        evaluations (``results.json``'s ``evaluations`` entries).

        The run directory's lock is held for the whole loop and released when it ends,
        normally or not (see :meth:`training_loop`). A SIGTERM ends the batch under way with a
        checkpoint, ends the collector and raises :class:`RunStopped`. A run trained from frame
        0 whose :meth:`train_step` never returned a loss (no update: a budget shorter than the
        recipe's warm-up) ends with a one-line warning saying so."""
        cfg = self.config
        with self.training_loop(
            on_iteration_end,
            eval_interval=cfg.eval_interval,
            checkpoint_interval=cfg.checkpoint_interval,
        ) as loop:
            if self.collector is None or self.eval_policy is None:
                raise RuntimeError(
                    f"{type(self).__name__}.__init__ must set self.collector and self.eval_policy"
                )
            start = self.frames
            self.reset_collector()
            while not loop.finished:
                loop.end_iteration(self.train_on_batch())
            self.collector.shutdown()  # before the RunStopped of a stop signal, if any
        if start == 0 and self.batches and not self._batches_updated:
            log.warning(
                "%s: the run made no training update: train_step returned no loss in any of its "
                "%d batches (%d frames), so its policy is the initial one (a replay-buffer recipe "
                "first waits for batch_size transitions and init_random_frames: raise "
                "total_frames or lower those)",
                self.name,
                self.batches,
                self.frames,
            )
        return self.results.evaluations

    @contextlib.contextmanager
    def training_loop(
        self,
        on_iteration_end: Callable[[dict[str, float]], None] | None = None,
        *,
        eval_interval: int | None,
        checkpoint_interval: int,
        train_entries: bool = False,
        label: str | None = None,
        postfix: Callable[[Mapping[str, float], float], dict[str, str]] | None = None,
    ) -> Iterator[TrainingLoop]:
        """The bookkeeping every training loop shares, for a loop written in the recipe (MA-PETS
        writes Algorithm 1 this way, one episode per iteration; :meth:`train`'s own loop uses
        it too)::

            with self.training_loop(on_episode_end, eval_interval=None,
                                    checkpoint_interval=1, train_entries=True) as loop:
                while not loop.finished:
                    metrics = ...              # one iteration; it advances self.progress()
                    loop.end_iteration(metrics)  # log, results, evaluation, checkpoint, bar

        ``eval_interval``, ``checkpoint_interval`` and ``train_entries`` are those of
        :class:`TrainingLoop`, counted in :meth:`progress` units (:attr:`progress_unit`).
        ``label`` and ``postfix(metrics, fps)`` are the progress bar's description (default
        ``"<recipe> <scenario> seed <seed>"``) and what it shows after an iteration (default:
        the frames per second and the latest evaluation's metrics). What a resumed run
        deferred is written after its first iteration (and at the end, when nothing was left
        to do). The run directory's lock is taken on entry (another writer is refused before
        anything runs) and released on exit, normally or not (see :meth:`close`); ValueError
        for a negative interval. With ``config.progress``, the first training loop of the
        process prints the torch thread count and why, once (:mod:`mapets_rl.threads`).

        A stop signal (:data:`STOP_SIGNALS`: SIGTERM, as Slurm's preemption and ``timeout``
        send it) received while the loop runs in the main thread ends the iteration under way
        with a checkpoint, finishes the loop and raises :class:`RunStopped` on exit: resuming
        the run continues it (exactly as an uninterrupted run when the iteration ended at a
        scheduled checkpoint, as every one of MA-PETS's episodes does; else the extra
        checkpoint restarts the collector's episodes there, as every checkpoint does). A
        second signal before that ends the process at once. The previous handlers are put
        back on exit."""
        if eval_interval is not None and eval_interval < 0:
            raise ValueError(f"eval_interval must be >= 0 or None, got {eval_interval}")
        if checkpoint_interval < 0:
            raise ValueError(f"checkpoint_interval must be >= 0, got {checkpoint_interval}")
        self._hold_lock()
        try:
            if self.config.progress:
                announce_threads(self.threads)
            done, total = self.progress()
            bar = tqdm(
                total=total,
                initial=done,
                disable=not self.config.progress,
                desc=label or f"{self.name} {self.config.env} seed {self.config.seed}",
                unit=self.progress_unit,
            )
            loop = TrainingLoop(
                self,
                bar,
                on_iteration_end,
                postfix or self._evaluation_postfix,
                eval_interval=eval_interval,
                checkpoint_interval=checkpoint_interval,
                train_entries=train_entries,
            )
            try:
                with on_stop_signal(functools.partial(setattr, loop, "stop_signal")):
                    yield loop
            finally:
                bar.close()
            self._start_writing()
            if loop.stop_signal is not None and loop.done < loop.total:
                raise RunStopped(loop.stop_signal, self.run_dir, self.frames)
            if self.logger is not None:
                self.logger.finish()
        finally:
            self.close()

    def progress(self) -> tuple[int, int]:
        """``(done, total)`` in :attr:`progress_unit`: a training loop runs while
        ``done < total`` (default: frames, up to ``config.total_frames``)."""
        return self.frames, self.config.total_frames

    def _evaluation_postfix(self, metrics: Mapping[str, float], fps: float) -> dict[str, str]:
        """The progress bar's default postfix: frames per second and the latest metrics."""
        return {"fps": f"{fps:.0f}", **{k: f"{v:.3g}" for k, v in self.latest_metrics.items()}}

    def train_on_batch(self) -> dict[str, float]:
        """One iteration of :meth:`train`: collect a batch (its environment steps counted in
        ``self.frames``), :meth:`train_step` on it; returns its training metrics, with those of
        the training episodes that ended in the batch (:meth:`training_episodes`)."""
        batch = self.collector.next()
        self.refuse_non_finite(batch)
        self.frames += batch.numel()
        self.batches += 1
        episodes = self.training_episodes(batch)
        losses = self.train_step(batch)
        self._batches_updated += bool(losses)
        self.collector.update_policy_weights_()
        return {**self.batch_metrics(batch), **summarize_episodes(episodes), **losses}

    def refuse_non_finite(self, batch: TensorDictBase) -> None:
        """:class:`NonFiniteData` (one line naming the entry and the frames) when an
        observation, a reward or a position of the collected ``batch`` (every float entry
        named ``observation``, ``reward`` or ``position``, at the step and in ``next``) is NaN
        or infinite, before anything trains on it: an update on it would spread NaN into every
        weight (MA-PETS refuses such data for its models the same way). The checkpoints
        written before are kept. One host sync per batch when all is finite."""
        where = f"of the batch {self.name} collected after frame {self.frames}"
        entries = {
            f"{'/'.join(key)} {where}": batch.get(key)
            for key in batch.keys(include_nested=True, leaves_only=True)
            if isinstance(key, tuple) and key[-1] in ("observation", "reward", "position")
        }
        try:
            check_finite_many({k: v for k, v in entries.items() if v.is_floating_point()})
        except ValueError as err:
            raise NonFiniteData(
                f"{err}: the environment produced them, and a run does not train on non-finite data"
            ) from None

    def training_episodes(self, batch: TensorDictBase) -> list[dict[str, float]]:
        """The training episodes that ended in the collected ``batch`` [*, T] (see
        :mod:`mapets_rl.experiment.episodes`), each ``{"system_return", "length"}`` (reward
        summed over CAVs and steps; steps) plus the scenario's episode metrics when the
        collector's env reports them (the torch freeway: ``average_velocity``,
        ``average_comfort``, ``collisions``, ``ramp_stuck`` on the ramp); appended to the run's
        ``train_episodes.jsonl`` at the run's frame count."""
        episodes = self.episode_tracker.update(batch)
        scenario = env_episode_metrics(getattr(self.collector, "env", None), len(episodes))
        if scenario is not None:
            episodes = [{**s, **e} for s, e in zip(scenario, episodes, strict=True)]
        self.episode_log.append(self.frames, episodes)
        return episodes

    def _save_boundary_checkpoint(self, last: bool) -> None:
        """The checkpoint of a training loop: one more boundary, then the checkpoint; unless
        it is the ``last``, the collector (when the recipe has one) is then re-seeded from
        (seed, boundary), so a resumed run sees the episodes an uninterrupted one sees."""
        self.boundaries += 1
        self.save_checkpoint()
        if not last and self.collector is not None:
            self.reset_collector()

    def reset_collector(self) -> None:
        """Re-seed and reset the collector's envs: a function of (seed, boundary) only, so a
        resumed run and an uninterrupted one see the same episodes after a checkpoint."""
        self.collector.set_seed(self.config.seed + BOUNDARY_SEED_STRIDE * self.boundaries)
        self.collector.reset()
        # the episodes under way end with the reset: none of them is recorded
        self.episode_tracker.reset()
        drain_env_episodes(getattr(self.collector, "env", None))

    # ------------------------------------------------------------------------- evaluation
    @torch.no_grad()
    def evaluate(self, episodes: int | None = None, video: bool | None = None) -> dict[str, float]:
        """Mean metrics over ``episodes`` deterministic episodes (default
        ``config.eval_episodes``) on the evaluation env, re-seeded identically every call.
        With ``video`` the first episode is saved as ``videos/eval_<frames>.gif`` (and sent to
        the logger, see :meth:`_write_video`). A progress
        bar counts the episodes on stderr (with ``config.progress``; it is removed when the
        evaluation ends)."""
        episodes = self.config.eval_episodes if episodes is None else episodes
        if episodes < 1:
            raise ValueError(f"episodes must be >= 1, got {episodes}")
        video = self.config.video if video is None else video
        if self.config.eval_roads and not video:
            return self._protocol_evaluation()
        # with video, evaluate on a rendering copy of the env (same seed, same episodes);
        # episode_metrics hooks read self.env, so it points at the env being evaluated
        previous = self.env
        self.env = self._render_env() if video else previous
        try:
            self.env.set_seed(self.config.seed + EVAL_SEED_OFFSET)
            per_episode = []
            with set_exploration_type(ExplorationType.DETERMINISTIC):
                for ep in tqdm(
                    range(episodes),
                    desc=f"evaluate {self.name} {self.config.env} seed {self.config.seed}",
                    unit="episode",
                    disable=not self.config.progress,
                    leave=False,
                ):
                    frames: list[Any] | None = [] if (video and ep == 0) else None
                    rollout = self._eval_episode(frames)
                    per_episode.append(self.episode_metrics(rollout))
                    if frames:
                        self._write_video(frames)
        finally:
            self.env = previous
        return mean_metrics(per_episode)

    def _protocol_evaluation(self) -> dict[str, float]:
        """The evaluation protocol on ``config.eval_roads`` roads (``config.eval_references``,
        default every reference of the scenario), as flat metrics; the references are scored
        once per run (the same roads every time)."""
        from mapets_rl.experiment.protocol import evaluate_protocol, protocol_metrics

        result = evaluate_protocol(
            self,
            self.config.eval_roads,
            self.config.eval_references,
            write=False,
            reference_cache=self._reference_scores,
        )
        return protocol_metrics(result)

    def _render_env(self) -> EnvBase:
        """The env with ``render_mode="rgb_array"`` (built once). Frames are drawn off screen,
        so SDL gets its ``offscreen`` video driver (unless the user chose one): no display is
        needed and SDL prints no XDG_RUNTIME_DIR error. (Its ``dummy`` driver would make
        highway-env skip drawing.)"""
        if self._video_env is None:
            os.environ.setdefault("SDL_VIDEODRIVER", "offscreen")
            try:
                self._video_env = build_env(
                    self.config.env,
                    {**self.config.unbatched_env_config(), "render_mode": "rgb_array"},
                )
            except TypeError as err:
                raise ValueError(
                    f"video needs scenario {self.config.env!r} to accept "
                    f"render_mode='rgb_array' ({err})"
                ) from err
            for transform in self.observation_transforms():
                self._video_env = self._video_env.append_transform(transform)
        return self._video_env

    def observation_transforms(self) -> list[Any]:
        """Named callback: torchrl transforms the recipe appends to its environment, appended
        to the video environment of :meth:`evaluate` too (MA-PETS: the tile-coded
        observation of its discretised variant). Default: none."""
        return []

    def on_evaluation_episode_start(self) -> None:
        """Named callback: called before each evaluation episode (MA-PETS forgets its
        planner's warm start). Default: nothing."""

    def _eval_episode(self, frames: list[Any] | None) -> TensorDictBase:
        """One episode until the root ``done``; returns the stacked steps [T]."""
        self.on_evaluation_episode_start()
        td = self.env.reset()
        steps = []
        while True:
            td = self.eval_policy(td.to(self.device)).to(self.env.device)
            td = self.env.step(td)
            steps.append(td.clone())
            if frames is not None:
                frame = self._render()
                if frame is not None:
                    frames.append(frame)
            if td.get(("next", "done")).any():
                break
            td = step_mdp(
                td,
                reward_keys=self.env.reward_keys,
                done_keys=self.env.done_keys,
                action_keys=self.env.action_keys,
            )
        return torch.stack(steps)

    def _render(self) -> Any:
        render = getattr(self.env, "render", None)
        return render() if callable(render) else None

    def _write_video(self, frames: list[Any]) -> Path:
        """An animated GIF of ``frames``, one per policy step, played in real time (imageio's
        GIF writer reads ``duration`` in milliseconds per frame); with a logger that records
        videos (:attr:`~mapets_rl.experiment.results.RunLogger.records_videos`), the same
        frames through torchrl's ``VideoRecorder`` to its ``log_video`` too, as
        :data:`VIDEO_TAG` at the run's frames."""
        import imageio.v2 as imageio

        fps = policy_frequency(self._video_env)
        path = self.run_dir / "videos" / f"eval_{self.frames:012d}.gif"
        atomic_write(path, lambda tmp: imageio.mimsave(tmp, frames, duration=1000.0 / fps))
        if self.logger is not None and self.logger.records_videos:
            from torchrl.record import VideoRecorder

            recorder = VideoRecorder(
                self.logger, VIDEO_TAG, in_keys=["pixels"], skip=1, make_grid=False, fps=fps
            )
            for frame in frames:
                recorder(TensorDict({"pixels": torch.as_tensor(frame)}, batch_size=[]))
            recorder.dump(step=self.frames)
        return path

    # ----------------------------------------------------------------------- checkpoints
    def state_dict(self) -> dict[str, Any]:
        """Whole training state: components, counters, results entries (``evaluations``,
        ``train``) and RNG states, plus the env's tensor shapes (so that a resume with another
        scenario shape is refused)."""
        return {
            "recipe": self.name,
            "env_shapes": env_shapes(self.env),
            "frames": self.frames,
            "batches": self.batches,
            "boundaries": self.boundaries,
            **self.results.state_dict(),
            **self._collector_state(),
            "log_steps": {} if self.logger is None else self.logger.state_dict(),
            "rng": rng_state(),
            "components": {k: v.state_dict() for k, v in self.stateful_components().items()},
        }

    def _traj_pool(self) -> Any:
        """The collector's trajectory-id counter (torchrl's ``_TrajectoryPool``, which numbers
        the ``("collector", "traj_ids")`` of the collected steps), ``None`` when there is no
        collector or it keeps none (a Ray collector's are remote)."""
        if self.collector is None or not getattr(self.collector, "track_traj_ids", True):
            return None
        return getattr(self.collector, "_traj_pool", None)

    def _collector_state(self) -> dict[str, Any]:
        """``{"collector": {"traj_id": next id}}`` of the collector's trajectory-id counter (so
        that a resumed run numbers its trajectories, and the replay buffers that store them,
        like an uninterrupted one), ``{}`` when it has none."""
        pool = self._traj_pool()
        if pool is None:
            return {}
        return {"collector": {"traj_id": pool.state_dict()["traj_id"].clone()}}

    def load_state_dict(self, state: Mapping[str, Any]) -> None:
        if state.get("recipe") != self.name:
            raise ValueError(f"checkpoint is of recipe {state.get('recipe')!r}, not {self.name!r}")
        components = self.stateful_components()
        missing = sorted(set(components) - set(state["components"]))
        if missing:
            raise ValueError(f"checkpoint lacks components {missing}")
        for key, obj in components.items():
            obj.load_state_dict(state["components"][key])
        self.frames = int(state["frames"])
        self.batches = int(state["batches"])
        self.boundaries = int(state["boundaries"])
        self.results.load_state_dict(state)
        self.latest_metrics = self.results.latest_metrics()
        if self._deferred is not None:
            # the logs are cut back to these steps when the resumed run starts writing; a
            # checkpoint from before checkpoints held them leaves the logs as they are
            self._deferred["log_steps"] = state.get("log_steps")
            self._deferred["frames"] = self.frames
        if self.logger is not None:
            self.logger.load_state_dict(state.get("log_steps") or {})
        if self._collector_args is not None and self._collector_args[1] > 0:
            # the random-action warm-up is counted over the run: rebuild for what is left
            self.collector.shutdown()
            policy, init_random, kwargs = self._collector_args
            self.collector = self.make_collector(policy, init_random, **kwargs)
        pool = self._traj_pool()
        if pool is not None and "collector" in state:
            # the next trajectory id of the run; the collector's reset at the start of train()
            # numbers its new trajectories from it, as the uninterrupted run's did
            pool.load_state_dict({"traj_id": state["collector"]["traj_id"]})
        set_rng_state(state["rng"])

    def save_checkpoint(self) -> Path:
        """Write the training state as ``checkpoints/ckpt_<frames>.pt`` (see
        :func:`~mapets_rl.experiment.checkpoint.save_checkpoint`), under the run directory's
        lock (a resumed run first writes what it deferred, see :meth:`_start_writing`)."""
        self._hold_lock()
        self._start_writing()
        return save_checkpoint(self.state_dict(), self.run_dir, self.frames, self.config.keep_last)

    def _start_writing(self) -> None:
        """Write what a resumed run deferred until it has started (its first iteration
        succeeded, or it had nothing left to do, or a checkpoint is saved): ``config.yaml``
        when overrides changed it, ``results.json`` as the restored checkpoint has it, the logs
        cut back to the checkpoint's steps (see
        :class:`~mapets_rl.experiment.results.RunLogger`) with the scalars logged meanwhile,
        and ``train_episodes.jsonl`` cut back to the checkpoint's frames with the episodes
        ended meanwhile (:class:`~mapets_rl.experiment.episodes.EpisodeLog`). Until then a
        resume that fails (an override that runs out of memory in the first iteration) leaves
        the run directory as it was, and a plain resume starts from the same state. No-op for
        a run that is not a resume, and after the first call."""
        deferred, self._deferred = self._deferred, None
        if deferred is None:
            return
        if deferred["config"]:
            self.config.to_yaml(self.run_dir / CONFIG_FILE)
        if deferred["results"]:
            self.results.write()
        self.episode_log.open(int(deferred["frames"]))
        if self.logger is not None:
            steps = deferred["log_steps"]
            self.logger.open(steps, purge_step=purge_step(int(deferred["frames"]), steps))

    @classmethod
    def from_run_dir(
        cls, run_dir: str | os.PathLike, overrides: list[str] | None = None, load: bool = True
    ) -> Experiment:
        """Rebuild from ``run_dir/config.yaml`` (+ overrides) and load the newest checkpoint
        that verifies (newer ones that do not are skipped with a logged warning).

        Nothing in ``run_dir`` changes unless the resumed run starts: overrides are validated
        first, an override that changes a field :attr:`resumable_fields` does not list (any
        but the budget, the intervals, ``keep_last``, ``device``, ``logger``, ``progress`` and
        ``video``) is refused naming the field (the run was trained with the old value; see
        :meth:`check_resume`), and the new ``config.yaml`` (with the
        overrides), ``results.json`` (as the checkpoint has it) and the logs (cut back to the
        checkpoint) are written only once the first iteration of :meth:`train` has succeeded
        (or a checkpoint is saved): a resume whose override fails then (out of memory) leaves
        the run directory byte for byte as it was, and a plain resume still works. (A
        ``config.yaml`` in an older layout is rewritten in today's at once, with the same
        values.) Overrides that set the budget below what the run has done (``episodes=1``
        after 2 episodes) are refused. Every failure is a one-line ValueError.

        The run directory's lock is taken before anything is read: a run directory that
        another experiment (or process) writes to is refused with
        :class:`~mapets_rl.experiment.files.RunDirLocked` naming the holder's pid. The
        experiment returned holds the lock (until its :meth:`train` returns or
        :meth:`close`).
        """
        run_dir = Path(run_dir)
        overrides = list(overrides or [])
        if not (run_dir / CONFIG_FILE).is_file():  # no lock file in what is not a run dir
            raise ConfigError(f"run_dir {str(run_dir)!r} has no {CONFIG_FILE}")
        lock = RunDirLock.acquire(run_dir)
        try:
            return cls._from_locked_run_dir(run_dir, overrides, load, lock)
        except BaseException:
            lock.release()
            raise

    @classmethod
    def _from_locked_run_dir(
        cls, run_dir: Path, overrides: list[str], load: bool, lock: RunDirLock
    ) -> Experiment:
        """:meth:`from_run_dir` once ``lock`` (of ``run_dir``) is held."""
        check_run_subdirs(run_dir)
        saved, config, on_disk, absent = cls._run_config(run_dir, overrides)
        if config.env != saved.env:
            raise ConfigError(
                f"env cannot change when resuming: run_dir {str(run_dir)!r} was "
                f"trained on {saved.env!r}; start a new run for {config.env!r}"
            )
        cls._refuse_relabel(run_dir, saved, config, absent)
        state = ckpt = None
        if load:
            ckpt, state = load_latest_checkpoint(run_dir, map_location=config.device)
        exp = cls.__new__(cls)
        exp._resuming = True
        exp._lock = lock
        exp.__init__(config, run_dir)
        _refuse_another_simulator(run_dir, exp.simulator)
        if state is not None:
            exp._restore(state, ckpt, _changed_keys(saved.to_dict(), config.to_dict()))
            done, total = exp.progress()
            if overrides and done > total:
                raise ConfigError(
                    f"cannot resume run_dir {str(run_dir)!r} with {' '.join(overrides)}: the "
                    f"run has done {done} {exp.progress_unit}s, more than the {total} it would "
                    "ask for; a resume only extends a run's budget (start a new run for a "
                    "shorter one)"
                )
        if saved.to_dict() != on_disk:  # an older layout of the same config
            saved.to_yaml(run_dir / CONFIG_FILE)
        if exp._deferred is not None:
            exp._deferred["config"] = config.to_dict() != saved.to_dict()
            exp._deferred["results"] = state is not None
        return exp

    @classmethod
    def check_resume(cls, run_dir: str | os.PathLike, overrides: list[str] | None = None) -> None:
        """ConfigError (one line) when :meth:`from_run_dir` would refuse ``overrides`` for the
        config of ``run_dir`` (a bad ``config.yaml`` or override, or a change of a field that
        :attr:`resumable_fields` does not list); reads ``config.yaml`` only, writes nothing
        and takes no lock (a sweep checks its trials with it before any of them starts)."""
        run_dir = Path(run_dir)
        saved, config, _, absent = cls._run_config(run_dir, list(overrides or []))
        cls._refuse_relabel(run_dir, saved, config, absent)

    @classmethod
    def _refuse_relabel(
        cls, run_dir: Path, saved: RunConfig, config: RunConfig, absent: set[str]
    ) -> None:
        """ConfigError naming the fields, old and new values, when ``config`` (the resumed
        run's) differs from ``saved`` (``run_dir``'s) in a field that :attr:`resumable_fields`
        does not list; a field that ``config.yaml`` lacked (``absent``: the recipe gained it
        after the run was made) is filled in, not changed."""
        old, new = _flatten(saved.to_dict()), _flatten(config.to_dict())
        changed = [
            key
            for key in _changed_keys(saved.to_dict(), config.to_dict())
            if key.partition(".")[0] not in cls.resumable_fields | absent
        ]
        if not changed:
            return
        shown = ", ".join(f"{key}: {old.get(key)!r} -> {new.get(key)!r}" for key in changed)
        allowed = sorted(cls.resumable_fields & set(cls.Config.field_names()))
        raise ConfigError(
            f"cannot resume with {', '.join(changed)} changed ({shown}): run_dir "
            f"{str(run_dir)!r} was trained with the old values, and a resume changes only "
            f"{', '.join(allowed)}; start a new run for other settings"
        )

    @classmethod
    def _run_config(
        cls, run_dir: Path, overrides: list[str]
    ) -> tuple[RunConfig, RunConfig, dict[str, Any], set[str]]:
        """(saved config of ``run_dir``, the config with ``overrides``, the mapping in
        ``config.yaml``, the fields that mapping lacks); one-line ConfigErrors naming
        ``config.yaml`` when it is missing, malformed, incomplete or another recipe's."""
        path = run_dir / CONFIG_FILE
        if not path.is_file():
            raise ConfigError(f"run_dir {str(run_dir)!r} has no {CONFIG_FILE}")
        on_disk = read_yaml_mapping(path)
        # keys an older version of the recipe wrote under an old name are read under the new
        # one; keys it no longer has are dropped or mapped to today's layout (config.yaml is
        # rewritten in today's layout)
        data = cls.Config.upgrade_dict(cls.Config.rename_old_keys(on_disk, repr(str(path))))
        fields = cls.Config.field_names()
        unknown = sorted(set(data) - set(fields))
        if unknown:
            raise ConfigError(
                f"{str(path)!r} is not a {cls.name!r} config (the recipe that "
                f"run.json names): unknown keys {unknown}; it belongs to another "
                "recipe or was edited"
            )
        parsed = [parse_override(item) for item in overrides]
        overridden = {key.partition(".")[0] for key, _ in parsed}
        missing = [name for name in fields if name not in data and name not in overridden]
        if missing:
            raise ConfigError(
                f"{str(path)!r} is incomplete: it lacks the keys {missing} (if the "
                "recipe gained them after the run was made, pass them as "
                "key=value overrides)"
            )
        # a run may move to another device: apply a device override before validating
        devices = [value for key, value in parsed if key == "device"]
        if devices:
            check_device(devices[-1])
            data["device"] = devices[-1]
        try:
            saved = cls.Config.from_dict(data)
        except ConfigError as err:
            raise ConfigError(f"{str(path)!r}: {err}") from None
        config = saved.with_overrides(overrides) if overrides else saved
        return saved, config, on_disk, {name for name in fields if name not in data}

    def _restore(self, state: Mapping[str, Any], path: Path, changed: list[str]) -> None:
        """Load checkpoint ``state`` (from ``path``) into this fresh experiment; ValueError
        naming the changed config keys when the state's tensor shapes do not fit."""
        fresh = self.state_dict()
        mismatch = [
            (f"env {key}", saved, fresh["env_shapes"][key])
            for key, saved in state.get("env_shapes", {}).items()
            if key in fresh["env_shapes"] and saved != fresh["env_shapes"][key]
        ]
        mismatch += _shape_mismatches(state.get("components", {}), fresh["components"])
        if mismatch:
            key, saved_shape, new_shape = mismatch[0]
            # name the keys that can change shapes: the env's for the env's shapes, the
            # recipe's own fields (network sizes, ...) for the components'
            env_keys = [k for k in changed if k.partition(".")[0] in ("env", "env_config")]
            recipe_keys = [
                k for k in changed if k.partition(".")[0] not in ExperimentConfig.field_names()
            ]
            changed = (env_keys if key.startswith("env ") else recipe_keys + env_keys) or changed
            if changed:
                raise ConfigError(
                    f"cannot resume with {', '.join(changed)} changed: it changes the shape of "
                    f"the saved state ({key}: {saved_shape} -> {new_shape}); scenario, agent "
                    "count and network sizes are fixed for a run, start a new run instead"
                )
            raise ValueError(
                f"checkpoint {str(path)!r} does not fit this {self.name} run "
                f"({key}: {saved_shape} in the checkpoint, {new_shape} here)"
            )
        try:
            self.load_state_dict(state)
        except (KeyError, RuntimeError, TypeError, ValueError) as err:
            raise ValueError(
                f"checkpoint {str(path)!r} cannot be restored into this "
                f"{self.name} run: {first_line(err)}"
            ) from None

    def write_evaluation(self, metrics: Mapping[str, float], episodes: int) -> Path:
        """Save a standalone evaluation as ``run_dir/evaluation.json``."""
        path = self.run_dir / "evaluation.json"
        atomic_write_text(
            path,
            json.dumps(
                {"frames": self.frames, "episodes": episodes, "metrics": dict(metrics)}, indent=1
            ),
        )
        return path


RAY_COLLECTOR_FRAMES = 2**62
"""``total_frames`` of a Ray collector: endless in practice (its iterator stops at its budget,
and ``-1`` would stop it at once); the run loop stops at ``config.total_frames``."""


def _ray_collector(
    env_fn: Callable[[], EnvBase],
    policy: TensorDictModuleBase,
    cfg: ExperimentConfig,
    device: torch.device,
    init_random_frames: int,
    kwargs: Mapping[str, Any],
) -> BaseCollector:
    """torchrl's ``RayCollector`` with ``cfg.collector_workers`` remote ``Collector`` actors (1
    CPU each), synchronous, on the Ray instance of this process, else the cluster of
    ``RAY_ADDRESS``, else a local instance started for it (and stopped at its ``shutdown``)."""
    import ray
    from torchrl.collectors.distributed import RayCollector

    from mapets_rl.ray_runtime import check_ray_address, ray_init_kwargs

    init = ray_init_kwargs()
    if not ray.is_initialized():
        check_ray_address(init["address"])

    class _Collector(RayCollector):
        def reset(self) -> None:
            """Reset the envs of every remote collector (``RayCollector`` has no reset)."""
            import ray

            ray.get([c.reset.remote() for c in self.remote_collectors])

    return _Collector(
        [env_fn] * cfg.collector_workers,
        policy,
        frames_per_batch=cfg.frames_per_batch,
        total_frames=RAY_COLLECTOR_FRAMES,
        device=device,
        exploration_type=ExplorationType.RANDOM,
        init_random_frames=init_random_frames,
        collector_class=Collector,
        collector_kwargs={"auto_register_policy_transforms": False, **kwargs},
        sync=True,
        ray_init_config=init,
        remote_configs={"num_cpus": 1},
    )


VIDEO_TAG = "eval/video"
"""The name of the evaluation videos sent to a logger (see :meth:`Experiment._write_video`)."""
VIDEO_FALLBACK_FREQUENCY = 10.0
"""Frames per second of an evaluation GIF whose scenario has no ``policy_frequency`` (a
registered scenario that is not a traffic scenario of ours)."""


def policy_frequency(env: EnvBase) -> float:
    """Policy steps per second of ``env``'s scenario, the frame rate of its evaluation GIFs:
    ``policy_frequency`` of its config (a highway-env scenario of ours or the torch freeway,
    transformed or not: 1 on the freeways, 10 on the figure-eights);
    :data:`VIDEO_FALLBACK_FREQUENCY` for another env."""
    try:
        config = scenario_config(env)
    except ValueError:
        return VIDEO_FALLBACK_FREQUENCY
    return float(config["policy_frequency"])


def purge_step(frames: int, log_steps: Mapping[str, int] | None) -> int | None:
    """The TensorBoard ``purge_step`` of a run resumed from a checkpoint at ``frames`` whose
    scalars were last logged at ``log_steps`` (name -> step): one past the largest step any
    scalar reached, so that no point logged before the checkpoint is hidden (a scalar on
    another axis than frames, MA-PETS's ``model/nll`` by epoch, may run ahead of the frames);
    ``None`` for a run that had logged nothing."""
    last = max([frames, *(log_steps or {}).values()])
    return last + 1 if last else None


SIMULATORS = {"native": "the fused C++ kernel", "torch": "the torch program"}
"""The programs that simulate the batched freeway (:func:`simulator_program`)."""


def simulator_program(env: EnvBase) -> str | None:
    """Which program simulates ``env`` (transformed or not): ``"native"`` (the fused C++ kernel)
    or ``"torch"`` (the torch program) for the batched freeway (``backend="torch"``), whose
    ``kernel="auto"`` runs the kernel where a C++ toolchain exists and the torch program
    elsewhere; ``None`` for another env. The two programs are different experiments (their
    trajectories part after some steps), so a run records which one ran (``run.json``,
    ``results.json``)."""
    sim = _freeway_simulator(env)
    if sim is None:
        return None
    return "native" if sim.kernel is not None else "torch"


def _freeway_simulator(env: EnvBase) -> BatchedFreeway | None:
    """The batched freeway's simulator of ``env`` (transformed or not), None for another env."""
    while isinstance(env, TransformedEnv):
        env = env.base_env
    sim = getattr(env, "sim", None)
    return sim if isinstance(sim, BatchedFreeway) else None


def check_batch_fits(env: EnvBase, roads: int | None) -> None:
    """ValueError (one line, naming ``env_config.num_envs``) when ``roads`` roads of the batched
    freeway ``env`` (one road of the run's scenario) would not fit in its device's memory while
    they step: a run checks it before it makes its run directory (the collector builds the
    batched env later). Nothing for another env or without ``roads``."""
    sim = _freeway_simulator(env)
    if sim is not None and roads is not None:
        check_roads_fit(sim.config, sim.merge, roads, sim.device, sim.dtype, "env_config.num_envs")


def _refuse_another_simulator(run_dir: Path, simulator: str | None) -> None:
    """ConfigError when ``run_dir``'s ``run.json`` records another simulator
    (:func:`simulator_program`) than ``simulator``, the one the resumed run would use: the rest
    of the run would be another experiment than its first part."""
    path = run_dir / RUN_FILE
    recorded = read_json_object(path).get("simulator") if path.is_file() else None
    if recorded is None or recorded == simulator:
        return
    here = SIMULATORS.get(str(simulator), "no batched freeway")
    raise ConfigError(
        f"run_dir {str(run_dir)!r} was simulated by {SIMULATORS.get(recorded, recorded)} "
        f"({recorded!r}) and would go on with {here} here (env_config.kernel 'auto' picks "
        "the kernel only where a C++ toolchain builds it): the two are different experiments; "
        "resume the run where its simulator runs"
    )


def run_recipe_name(run_dir: str | os.PathLike) -> str:
    """The recipe name recorded in ``run_dir/run.json``; a one-line ValueError naming the file
    when it is not a run directory or ``run.json`` is malformed."""
    path = Path(run_dir) / RUN_FILE
    if not path.is_file():
        raise ValueError(f"run_dir {str(run_dir)!r} is not a run directory (no {RUN_FILE})")
    recipe = read_json_object(path).get("recipe")
    if not isinstance(recipe, str) or not recipe:
        raise ValueError(
            f"{str(path)!r} does not name the run's recipe (it needs a "
            f'"recipe": "<name>" entry, got {recipe!r})'
        )
    return recipe


def refuse_run_dir_as_out(out: str | os.PathLike, what: str = "out") -> None:
    """ValueError (one line naming ``what``) when the output folder ``out`` is a run directory
    or lies inside one (it, or a directory above it, holds a ``run.json``): a run directory is
    not an output folder (``compare`` and ``sweep`` would write their files into a run)."""
    out = Path(out).resolve()
    for folder in (out, *out.parents):
        if (folder / RUN_FILE).is_file():
            where = "is" if folder == out else f"lies inside {str(folder)!r}, which is"
            raise ValueError(
                f"{what} {str(out)!r} {where} a run directory (it holds {RUN_FILE}); choose an "
                "output folder outside every run"
            )


def env_shapes(env: EnvBase) -> dict[str, list[int]]:
    """Shape of every observation, action and reward entry of ``env``'s specs, keyed by the
    dotted entry name (e.g. ``"agents.observation": [8, 7]``)."""
    shapes: dict[str, list[int]] = {}
    for spec in (env.full_observation_spec, env.full_action_spec, env.full_reward_spec):
        for key in spec.keys(include_nested=True, leaves_only=True):
            name = ".".join(key) if isinstance(key, tuple) else key
            shapes[name] = list(spec[key].shape)
    return shapes


def _flatten(tree: Any, prefix: str = "") -> dict[str, Any]:
    """Nested mappings -> ``{"a.b.c": leaf}``."""
    if not isinstance(tree, Mapping):
        return {prefix: tree}
    out: dict[str, Any] = {}
    for key, value in tree.items():
        out.update(_flatten(value, f"{prefix}.{key}" if prefix else str(key)))
    return out


def _changed_keys(saved: Mapping[str, Any], new: Mapping[str, Any]) -> list[str]:
    """Dotted config keys whose values differ between two ``to_dict()`` configs."""
    old_flat, new_flat = _flatten(saved), _flatten(new)
    return sorted(
        k for k in old_flat.keys() | new_flat.keys() if old_flat.get(k) != new_flat.get(k)
    )


def _shape_mismatches(saved: Any, fresh: Any) -> list[tuple[str, list[int], list[int]]]:
    """``(key, saved shape, fresh shape)`` of every tensor present in both state trees whose
    shape differs (entries only one side has, e.g. a replay buffer not filled yet, are
    skipped)."""
    saved_flat, fresh_flat = _flatten(saved), _flatten(fresh)
    return [
        (key, list(saved_flat[key].shape), list(fresh_flat[key].shape))
        for key in sorted(saved_flat.keys() & fresh_flat.keys())
        if isinstance(saved_flat[key], torch.Tensor)
        and isinstance(fresh_flat[key], torch.Tensor)
        and saved_flat[key].shape != fresh_flat[key].shape
    ]


@contextlib.contextmanager
def _stop_signals_ignored() -> Iterator[None]:
    """While the block runs, the stop signals (:data:`STOP_SIGNALS`) are ignored, and so they
    are by the processes it starts (an ignored signal stays ignored in a child, forked or
    spawned): a collector's worker processes outlive the SIGTERM that ``timeout`` or Slurm
    send to every process of the run, and the run's training loop, which takes the signal,
    ends the batch under way with a checkpoint and shuts them down (no worker killed
    mid-batch, no traceback, no leaked semaphore). Outside the main thread nothing changes."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = {signum: signal.signal(signum, signal.SIG_IGN) for signum in STOP_SIGNALS}
    try:
        yield
    finally:
        for signum, handler in previous.items():
            signal.signal(signum, handler if handler is not None else signal.SIG_DFL)


@contextlib.contextmanager
def on_stop_signal(first: Callable[[int], None]) -> Iterator[None]:
    """While the block runs, the first stop signal (:data:`STOP_SIGNALS`) calls
    ``first(signum)``; a second one restores the previous handler and signals again (the
    default ends the process). The previous handlers are put back after the block. Outside the
    main thread, where Python cannot handle signals, nothing changes."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    received: list[int] = []

    def handle(signum: int, frame: Any) -> None:
        if received:
            signal.signal(signum, previous[signum] or signal.SIG_DFL)
            signal.raise_signal(signum)
            return
        received.append(signum)
        first(signum)

    previous = {signum: signal.getsignal(signum) for signum in STOP_SIGNALS}
    for signum in STOP_SIGNALS:
        signal.signal(signum, handle)
    try:
        yield
    finally:
        for signum, handler in previous.items():
            signal.signal(signum, handler or signal.SIG_DFL)


def _crossed(prev: int, now: int, interval: int) -> bool:
    """True when a multiple of ``interval`` lies in (prev, now]; never for interval 0."""
    return interval > 0 and now // interval > prev // interval


__all__ = [
    "ConfigError",
    "Experiment",
    "NonFiniteData",
    "RunStopped",
    "default_run_dir",
    "run_recipe_name",
]


class SystemRewardMetrics:
    """Mixin for an :class:`Experiment` (list it first among the bases): adds the system
    reward, the Shapley paper's Fig. 2 quantity, to the shared metrics: ``system_reward``
    per training step (reward summed over CAVs, averaged over steps) and ``system_return``
    per evaluation episode (reward summed over CAVs and steps)."""

    def batch_metrics(self, batch: TensorDictBase) -> dict[str, float]:
        out = super().batch_metrics(batch)
        reward = batch.get(("next", "agents", "reward")).float()
        out["system_reward"] = reward.sum((-2, -1)).mean().item()
        return out

    def episode_metrics(self, rollout: TensorDictBase) -> dict[str, float]:
        out = super().episode_metrics(rollout)
        out["system_return"] = rollout.get(("next", "agents", "reward")).float().sum().item()
        return out
