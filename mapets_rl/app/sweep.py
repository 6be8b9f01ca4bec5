"""Sweeps: the cartesian product of config grids x seeds, one normal run directory per trial,
executed by a process pool on this machine, by Ray or as Slurm jobs (submitit), summarised
with :func:`compare`.

    mapets-rl sweep RECIPE --env SCENARIO --seeds 0 1 2 --grid comm.comm_range=0,50,100
                    [--grid comm.p_fail=0,0.25 ...] [key=value ...] --out DIR
                    [--backend local|ray|submitit] [--address HOST:PORT] [--cpus-per-trial N]
                    [--gpus-per-trial N] [--executor-param KEY=VALUE ...] [--config FILE]
                    [--metrics a,b] [--source eval|train] [--x auto|frames|METRIC]

Layout of ``--out``::

    sweep.json                     the manifest: the sweep's spec and every trial's state
    trials/<key>=<value>__...__seed=<N>/   one run directory per trial (config.yaml,
                                   results.json, checkpoints/, logs/) plus trial.json (the
                                   trial's record) and, when it failed, error.txt (the traceback)
    summary/                       compare's learning_curves.png, final_metrics.md,
                                   summary.json, curves.json, grouped by the swept fields
    submitit/                      (submitit backend) submitit's files of each job

Everything the user typed is checked before any trial starts: the recipe, the scenario, every
grid key and value and every override (each trial's config is built, and the scenario is built
once for each distinct ``env_config``), the backend and its resources; errors are one-line
:class:`~mapets_rl.experiment.ConfigError` / ValueErrors naming the parameter.

Re-running the same command skips the trials whose ``trial.json`` records a finished run of
the same config, resumes the others from their latest checkpoint (``from_run_dir`` with the
trial's overrides) and starts the ones without checkpoints; a trial it would resume with a
change a resume refuses (anything but the budget and the intervals, see
:meth:`~mapets_rl.experiment.Experiment.check_resume`) stops the sweep before any trial
starts. A re-run with another grid or seeds keeps the trials of the earlier ones in
``sweep.json`` and the summary (grouped by every grid key, and by the settings their configs
differ in). ``--x`` and ``--metrics`` are checked before any trial starts, against the trials
already finished; in a sweep with none, ``--x`` against the metrics that have a unit and
``--metrics`` (of evaluations, the default ``--source``) against those of one evaluation
episode of the first trial's untrained policy (:func:`probe_metrics`). A trial that raises
is recorded as failed (the traceback in its ``error.txt``, the last line in the manifest); the
other trials still run, and :func:`run_sweep` reports the failed ones (the command then exits
with 1).

A stop signal (SIGTERM, as Slurm's preemption and ``timeout`` send it) to a sweep of the local
backend stops it as it stops a training run: every running trial ends its iteration with a
checkpoint (state ``"stopped"`` in its ``trial.json`` and the manifest), the trials not
started stay pending, the workers exit and the command exits with 143 (128 + 15); re-running
the same command resumes the sweep.

One sweep per ``--out`` at a time: a second one, while the first runs, is refused in one line
naming its pid (a sweep holds ``OUT/.lock``, a :class:`~mapets_rl.experiment.files.RunDirLock`).
One writer per trial: the local backend's workers die with the sweep process (kill -9
included), and a trial whose run directory another writer still holds (its lock: an orphaned
Ray task, a ``mapets-rl resume``) is reported as failed, naming the holder's pid, without a
byte written there; a later re-run resumes it.

Backends (none schedules by hand):

- ``local``: a ``concurrent.futures.ProcessPoolExecutor`` of ``cpu_count // cpus_per_trial``
  spawned processes, each running one trial at a time. Ray is not imported.
- ``ray``: every trial is a Ray core task with ``num_cpus=cpus_per_trial``,
  ``num_gpus=gpus_per_trial`` and no retries; Ray queues and places them. Without ``address``
  (nor ``RAY_ADDRESS``) a local Ray instance is started for the sweep; a small reaper
  process (:func:`mapets_rl.ray_runtime.reap_ray_agents_on_exit`) ends the Ray agents that
  would outlive a driver killed with kill -9 (its workers see this process's ``sys.path``) and
  shut down after it; with one, the sweep joins that cluster, whose
  nodes must have the recipe and scenario installed (entry points) and see ``--out`` (a shared
  file system). An already initialised Ray (``ray.init`` in this process) is used as it is.
  Ray core tasks rather than Ray Tune: a trial is already a resumable run directory with its
  own results file, checkpoints and evaluation, and there is nothing to search or stop early;
  Tune would add a second trial layout, checkpoint protocol and resume logic over ours (and
  the ``ray[tune]`` dependencies) for nothing.
- ``submitit``: every trial is a job of a ``submitit.AutoExecutor`` (one Slurm job array;
  ``--cpus-per-trial`` and ``--gpus-per-trial`` are its ``cpus_per_task`` and
  ``gpus_per_node``, ``--executor-param`` its other parameters: ``timeout_min``,
  ``slurm_partition``, ..., and ``cluster=local`` for jobs on this machine). The jobs belong to
  the cluster and outlive the sweep process; its nodes must have the project, the recipe and
  the scenario installed and see ``--out``. The trials are the same resumable run
  directories, so skipping and resuming are the other backends' (a job that ends without a
  result is a failed trial; a re-run resumes it from its checkpoint). Submitit rather than
  Hydra's submitit launcher: the configuration is this project's YAML files and typed fields
  (``key=value`` overrides, ``--grid``, published configs), not Hydra; the launcher would
  need the whole config system moved to Hydra's composition and its multirun directory
  layout in place of ``sweep.json`` and ``trials/``, while submitit alone submits the very
  :func:`run_trial` the other backends run.

Recipes and scenarios reach the trial processes by import path: a recipe installed under an
entry point, or a scenario registered in this process with :func:`register_env`, must be an
importable module-level object (not defined in ``__main__``).
"""

from __future__ import annotations

import argparse
import concurrent.futures
import contextlib
import copy
import dataclasses
import importlib
import itertools
import json
import math
import multiprocessing
import os
import re
import signal
import sys
import time
import traceback
from collections.abc import Callable, Iterator, Mapping, Sequence
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import yaml

from mapets_rl.config import ConfigError, check, load_yaml, parse_override
from mapets_rl.experiment.files import (
    ERROR_FILE,
    TRIAL_RECORD,
    RunDirLock,
    atomic_write_text,
    check_writable_dir,
    make_writable_dir,
)
from mapets_rl.experiment.runner import STOP_SIGNALS, on_stop_signal
from mapets_rl.ray_runtime import (
    check_ray_address,
    import_ray,
    ray_init_kwargs,
    reap_ray_agents_on_exit,
)

MANIFEST = "sweep.json"
TRIALS_DIR = "trials"
SUMMARY_DIR = "summary"
BACKENDS = ("local", "ray", "submitit")
SUBMITIT_DIR = "submitit"
"""Under ``--out``: submitit's job files (pickled trial, stdout / stderr), one folder per job."""
SUBMITIT_POLL_S = 1.0
"""Seconds between two looks at the submitit jobs not finished yet (submitit rate-limits
its queries of the Slurm accounting itself)."""
RESERVED_KEYS = {"env": "--env", "seed": "--seeds"}
"""Config keys a sweep sets itself, with the option that sets them."""
ERROR_TAIL_LINES = 60
"""Lines of a failed trial's traceback kept in its ``error.txt``."""
STOPPED = "stopped"
"""The state of a trial that a stop signal (SIGTERM) stopped with a checkpoint."""


@dataclasses.dataclass
class SweepSpec:
    """What to run.

    Attributes:
        recipe: an installed recipe name (entry point of ``mapets_rl.recipes``).
        env: a scenario name.
        seeds: seeds, each >= 0, no repeats.
        grid: dotted config key -> the values it takes (each list non-empty, no repeats); the
            trials are the cartesian product of the grids x ``seeds``.
        overrides: ``key=value`` strings applied to every trial (as ``mapets-rl train``).
        out: the sweep directory.
        config_file: a YAML file of config fields applied before ``overrides``.
        backend: ``"local"``, ``"ray"`` or ``"submitit"``.
        address: Ray cluster address to join (``ray`` backend; default ``RAY_ADDRESS``, else a
            local Ray instance is started).
        cpus_per_trial: CPUs each trial reserves and its torch threads (> 0; ``local``: >= 1).
        gpus_per_trial: GPUs each trial reserves (>= 0; ``ray`` and ``submitit`` backends;
            ``submitit``: a whole number).
        executor_params: ``submitit`` backend only: the parameters of its
            ``submitit.AutoExecutor`` (``timeout_min``, ``mem_gb``, ``slurm_partition``,
            ``slurm_account``, ...; see submitit's ``update_parameters``), plus ``cluster``:
            ``"slurm"``, ``"local"`` (jobs as processes of this machine) or ``"debug"``
            (default: submitit's choice, Slurm where ``sbatch`` is found).
        metrics, source, x: what the summary compares (see :func:`compare`); ``x="auto"`` is
            ``"episode"`` when every entry numbers its episode (MA-PETS), else ``"frames"``.
    """

    recipe: str
    env: str
    seeds: list[int]
    out: Path
    grid: dict[str, list[Any]] = dataclasses.field(default_factory=dict)
    overrides: list[str] = dataclasses.field(default_factory=list)
    config_file: str | None = None
    backend: str = "local"
    address: str | None = None
    cpus_per_trial: float = 1.0
    gpus_per_trial: float = 0.0
    executor_params: dict[str, Any] = dataclasses.field(default_factory=dict)
    metrics: list[str] | None = None
    source: str = "eval"
    x: str = "auto"

    def __post_init__(self) -> None:
        self.out = Path(self.out)
        self.seeds = list(self.seeds)
        check(len(self.seeds) >= 1, "seeds", "at least one seed", self.seeds)
        check(
            all(isinstance(s, int) and not isinstance(s, bool) and s >= 0 for s in self.seeds),
            "seeds",
            "integers >= 0",
            self.seeds,
        )
        check(len(set(self.seeds)) == len(self.seeds), "seeds", "without repeats", self.seeds)
        check(self.backend in BACKENDS, "backend", f"one of {list(BACKENDS)}", self.backend)
        check(
            math.isfinite(self.cpus_per_trial) and self.cpus_per_trial > 0,
            "cpus_per_trial",
            "> 0",
            self.cpus_per_trial,
        )
        check(
            math.isfinite(self.gpus_per_trial) and self.gpus_per_trial >= 0,
            "gpus_per_trial",
            ">= 0",
            self.gpus_per_trial,
        )
        if self.backend == "local":
            check(
                self.cpus_per_trial >= 1,
                "cpus_per_trial",
                ">= 1 with the local backend (fractions need --backend ray)",
                self.cpus_per_trial,
            )
            check(
                self.gpus_per_trial == 0,
                "gpus_per_trial",
                "0 with the local backend (--backend ray assigns GPUs to trials)",
                self.gpus_per_trial,
            )
        if self.backend != "ray":
            check(
                self.address is None,
                "address",
                "unset without the ray backend (it joins a Ray cluster: --backend ray)",
                self.address,
            )
        if self.backend == "submitit":
            for name, value in (("cpus", self.cpus_per_trial), ("gpus", self.gpus_per_trial)):
                check(
                    float(value).is_integer() and value >= (name == "cpus"),
                    f"{name}_per_trial",
                    f"a whole number >= {int(name == 'cpus')} with the submitit backend (Slurm "
                    f"reserves whole {name.upper()}s)",
                    value,
                )
        else:
            check(
                not self.executor_params,
                "executor_params",
                "empty without the submitit backend",
                self.executor_params,
            )
        if self.address is not None:
            check(bool(self.address.strip()), "address", "HOST:PORT", self.address)
        for key, values in self.grid.items():
            check(bool(key) and "=" not in key, "grid", "KEY=v1,v2,... entries", key)
            check(len(values) >= 1, f"grid {key}", "at least one value", values)
            unique = {json.dumps(v, sort_keys=True) for v in values}
            check(len(unique) == len(values), f"grid {key}", "values without repeats", values)
        keys = [*self.grid, *(parse_override(o)[0] for o in self.overrides)]
        for key, option in RESERVED_KEYS.items():
            check(key not in keys, key, f"set with {option}, not as a grid or override", key)
        check("progress" not in self.grid, "grid", "keys other than progress", "progress")
        for item in self.overrides:
            key, value = parse_override(item)
            check(
                key != "progress" or value is False,
                "progress",
                "false or unset in a sweep (its trials draw no progress bars)",
                value,
            )
        fixed = {parse_override(o)[0] for o in self.overrides}
        both = sorted(fixed & set(self.grid))
        check(not both, "grid", "keys that no key=value override also sets", both)
        for key in self.grid:
            nested = [k for k in [*self.grid, *fixed] if k != key and k.startswith(key + ".")]
            check(not nested, f"grid {key}", f"a key that no other key nests in ({nested})", key)


@dataclasses.dataclass
class Trial:
    """One run of a sweep: a seed and one value of every grid key.

    Attributes:
        id: its directory name, ``<key>=<value>__...__seed=<N>``.
        run_dir: ``OUT/trials/<id>``.
        seed: the seed.
        values: grid key -> value of this trial.
        overrides: every ``key=value`` of the trial, in order: the config file's fields,
            ``progress=false``, ``env``, ``seed``, the sweep's overrides, the grid values (the
            sweep sets ``progress`` itself: a ``progress`` of the config file or the
            overrides is left out).
        config: the resolved config (``to_dict``), to tell a finished trial of the same config.
    """

    id: str
    run_dir: Path
    seed: int
    values: dict[str, Any]
    overrides: list[str]
    config: dict[str, Any]


@dataclasses.dataclass
class SweepResult:
    """What :func:`run_sweep` did: the trials and their records (``state`` ``"done"`` or
    ``"failed"``, ``ran``, ``resumed``, ``seconds``, ``error``), the failed trials' ids, and
    compare's output paths (``{}`` when no trial finished, or ``summary_error`` says why)."""

    trials: list[Trial]
    records: dict[str, dict[str, Any]]
    failed: list[str]
    summary: dict[str, Path]
    summary_error: str | None = None


# ------------------------------------------------------------------------------- planning
def parse_grid(items: Sequence[str]) -> dict[str, list[Any]]:
    """``["comm.comm_range=0,50,100", "model.hidden=[[32,32],[64,64]]"]`` -> ``{key: values}``.

    Values are comma separated and each parsed as YAML; a value list written as a YAML
    list (``KEY=[v1, v2]``) is taken as it is, so values may themselves be lists.
    """
    grid: dict[str, list[Any]] = {}
    for item in items:
        key, sep, raw = item.partition("=")
        key = key.strip()
        if not sep or not key or not raw.strip():
            raise ConfigError(f"grid {item!r} must look like KEY=v1,v2,...")
        if key in grid:
            raise ConfigError(f"grid key {key!r} is given twice; list its values once")
        if raw.strip().startswith("["):
            try:
                values = load_yaml(raw)
            except yaml.YAMLError:
                raise ConfigError(f"grid {key!r}: {raw!r} is not a YAML list") from None
            if not isinstance(values, list):
                raise ConfigError(f"grid {key!r}: {raw!r} is not a YAML list")
        else:
            values = [parse_override(f"{key}={v}")[1] for v in raw.split(",")]
        if any(v == "" for v in values):
            raise ConfigError(f"grid {key!r} has an empty value in {raw!r}")
        grid[key] = values
    return grid


def _value_text(value: Any) -> str:
    """A grid value as an override value: JSON, which YAML reads back as the same value (a
    string stays a string, even ``"on"`` or ``"1"``)."""
    return json.dumps(value)


def _slug(value: Any) -> str:
    if isinstance(value, float) and value.is_integer():
        text = f"{value:g}"
    elif isinstance(value, (bool, int, float)) or value is None:
        text = json.dumps(value) if not isinstance(value, float) else f"{value:g}"
    else:
        text = value if isinstance(value, str) else json.dumps(value, separators=(",", ":"))
    return re.sub(r"[^A-Za-z0-9.+-]+", "-", text).strip("-") or "-"


def trial_id(values: Mapping[str, Any], seed: int) -> str:
    """``comm.comm_range=50__comm.p_fail=0.25__seed=0``."""
    return "__".join([*(f"{k}={_slug(v)}" for k, v in values.items()), f"seed={seed}"])


def config_file_fields(path: str | None) -> dict[str, Any]:
    """The fields of ``--config``: a published configuration by name or a YAML file
    (:func:`~mapets_rl.experiment.published.load_published`, includes resolved)."""
    from mapets_rl.experiment.published import load_published

    return {} if path is None else load_published(path).fields


def fold_into_fields(
    fields: Mapping[str, Any], overrides: Sequence[str]
) -> tuple[list[str], list[str]]:
    """A config file's ``fields`` as ``key=value`` items with ``overrides`` folded in, so that
    all of them apply in one call (a trial's overrides, resumed or not): an override reaching
    into a mapping the file gives (``env_config.num_envs=4`` beside the file's ``env_config``)
    is set inside it, one naming a field the file gives replaces it. Returns the file's items
    and the overrides left to apply after them."""
    data = copy.deepcopy(dict(fields))
    rest = []
    for item in overrides:
        key, value = parse_override(item)
        head, *path = key.split(".")
        if path and isinstance(data.get(head), dict):
            node = data[head]
            for part in path[:-1]:
                if not isinstance(node.get(part), dict):
                    node[part] = {}
                node = node[part]
            node[path[-1]] = value
            continue
        data.pop(key, None)
        rest.append(item)
    return [f"{k}={json.dumps(v)}" for k, v in data.items()], rest


def _sets_progress(item: str) -> bool:
    """Whether the ``key=value`` ``item`` sets ``progress``."""
    return parse_override(item)[0] == "progress"


def _import_path(obj: Any, what: str) -> str:
    """``module:qualname`` of a module-level object; ValueError when other processes could
    not import it."""
    module, qualname = getattr(obj, "__module__", None), getattr(obj, "__qualname__", "")
    if not module or module == "__main__" or "<" in qualname:
        raise ValueError(
            f"{what} {obj!r} is not importable by the trial processes (defined in "
            f"{module or 'no module'}); define it at module level in an importable module or "
            "declare it as an entry point"
        )
    return f"{module}:{qualname}"


def trial_scenarios(env: str) -> dict[str, str]:
    """``{env: "module:qualname"}`` of the factory that scenario ``env`` was registered with in
    this process (:func:`~mapets_rl.envs.registry.register_env`), which every trial registers
    before it starts; ``{}`` for a built-in or installed scenario, which every process knows.
    ValueError when the factory is not importable by the trial processes."""
    from mapets_rl.envs.registry import registered_scenario

    scenario = registered_scenario(env)
    if scenario is None or scenario.builtin:
        return {}
    return {env: _import_path(scenario.factory, f"scenario {env!r}")}


def _load_import_path(target: str) -> Any:
    module, _, qualname = target.partition(":")
    obj: Any = importlib.import_module(module)
    for part in qualname.split("."):
        obj = getattr(obj, part)
    return obj


def plan_trials(spec: SweepSpec) -> tuple[type, list[Trial]]:
    """The recipe class and every trial of ``spec``, validated: each trial's config is built,
    and the scenario once for each distinct ``env_config``. Nothing is written.

    Raises:
        ConfigError / ValueError: one line naming the parameter, for an unknown recipe or
            scenario, a bad grid key or value, a bad override or config file, or two trials
            whose directory names collide.
    """
    from mapets_rl.app.plugins import load_recipe
    from mapets_rl.envs.registry import available_envs, build_env

    cls = load_recipe(spec.recipe)
    known = available_envs()
    check(spec.env in known, "env", f"one of the registered scenarios {known}", spec.env)
    # the sweep's trials draw no progress bars: its own progress=false replaces the config
    # file's progress and the user's progress=false (SweepSpec refuses progress=true)
    fields = {k: v for k, v in config_file_fields(spec.config_file).items() if k != "progress"}
    fixed = [i for i in spec.overrides if not _sets_progress(i)]
    trials: list[Trial] = []
    envs: dict[str, Any] = {}
    combos = list(itertools.product(*spec.grid.values())) if spec.grid else [()]
    for combo in combos:
        values = dict(zip(spec.grid, combo, strict=True))
        grid_items = [f"{k}={_value_text(v)}" for k, v in values.items()]
        for seed in spec.seeds:
            given = [f"env={spec.env}", f"seed={seed}", *fixed, *grid_items]
            head, rest = fold_into_fields(fields, given)
            overrides = [*head, "progress=false", *rest]
            # a trial's GPU is on the node Ray places it on, not necessarily on this machine:
            # its device is checked there
            devices = [v for k, v in map(parse_override, overrides) if k == "device"]
            checked = overrides
            if spec.gpus_per_trial > 0:
                checked = [o for o in checked if parse_override(o)[0] != "device"]
            try:
                config = cls.Config().with_overrides(checked)
            except ConfigError as err:
                where = f" (grid values {values})" if values else ""
                raise ConfigError(f"{err}{where}") from None
            data = config.to_dict()
            if spec.gpus_per_trial > 0 and devices:
                data["device"] = devices[-1]
            envs.setdefault(json.dumps(data.get("env_config", {}), sort_keys=True), data)
            tid = trial_id(values, seed)
            trials.append(Trial(tid, spec.out / TRIALS_DIR / tid, seed, values, overrides, data))
    ids = [t.id for t in trials]
    dupes = sorted({i for i in ids if ids.count(i) > 1})
    check(not dupes, "grid", "values whose directory names differ", dupes)
    for data in envs.values():
        env = build_env(spec.env, data.get("env_config", {}))
        env.close()
    return cls, trials


# ----------------------------------------------------------------------------- one trial
def _write_record(run_dir: Path, record: Mapping[str, Any]) -> None:
    atomic_write_text(run_dir / TRIAL_RECORD, json.dumps(dict(record), indent=1))


def read_trial_record(run_dir: str | os.PathLike) -> dict[str, Any] | None:
    """A trial directory's ``trial.json``, or None when it has none (or an unreadable one)."""
    path = Path(run_dir) / TRIAL_RECORD
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    return data if isinstance(data, dict) else None


def _now() -> str:
    return datetime.now(timezone.utc).isoformat(timespec="seconds")


def run_trial(payload: Mapping[str, Any]) -> dict[str, Any]:
    """Run (or resume) one trial in this process; what the backends execute.

    ``payload``: ``recipe`` (``module:qualname`` of the recipe class), ``scenarios`` (name ->
    ``module:qualname`` of factories to register first), ``run_dir``, ``overrides``,
    ``config`` (the resolved config, recorded) and ``threads`` (torch threads).

    Returns ``{"state": "done" | "failed" | "stopped", "resumed", "seconds", "frames",
    "error"}``; an exception is not raised but recorded: the traceback's last
    :data:`ERROR_TAIL_LINES` lines in ``run_dir/error.txt``, its last line in the result and
    ``trial.json``. ``"stopped"``: a SIGTERM stopped the run with a checkpoint
    (:class:`~mapets_rl.experiment.runner.RunStopped`), or reached a local-backend worker
    before the run's training loop started (see :func:`_init_worker`); a re-run resumes it. A
    local-backend worker that was told to stop before this call returns ``"pending"`` (with
    ``"ran": False``) and writes nothing.
    """
    from mapets_rl import quiet_dependencies

    quiet_dependencies()  # a trial's process is an application of its own, as the CLI is
    run_dir = Path(payload["run_dir"])
    start = time.perf_counter()
    if _stop_requested:  # a worker told to stop starts no trial: it stays pending, unwritten
        return {"state": "pending", "ran": False, "frames": None, "error": None, "seconds": 0.0}
    from mapets_rl.experiment.files import RunDirLock, RunDirLocked
    from mapets_rl.experiment.runner import RunStopped

    # another writer (a worker of a sweep killed with kill -9 that is still running this trial,
    # a `mapets-rl resume`) has the run directory: leave it alone, write nothing there
    try:
        run_dir.mkdir(parents=True, exist_ok=True)
        RunDirLock.acquire(run_dir).release()
    except RunDirLocked as err:
        return _locked(err, time.perf_counter() - start)
    record: dict[str, Any] = {
        "state": "running",
        "started": _now(),
        "host": os.uname().nodename,
        "pid": os.getpid(),
        "overrides": list(payload["overrides"]),
        "config": payload["config"],
    }
    resumed = False
    try:
        _write_record(run_dir, record)
        import torch

        from mapets_rl.envs.registry import register_env
        from mapets_rl.experiment.checkpoint import latest_checkpoint

        torch.set_num_threads(max(1, int(payload["threads"])))
        cls = _load_import_path(payload["recipe"])
        for name, target in payload["scenarios"].items():
            register_env(name, _load_import_path(target), overwrite=True)
        if latest_checkpoint(run_dir) is not None:
            exp = cls.from_run_dir(run_dir, overrides=list(payload["overrides"]))
            resumed = True
        else:
            config = cls.Config().with_overrides(payload["overrides"])
            exp = cls(config, run_dir)
        if _stop_requested:  # the worker was told to stop before its training loop started
            exp.close()
            result = {"state": STOPPED, "frames": int(exp.frames), "error": None}
        else:
            exp.train()
            (run_dir / ERROR_FILE).unlink(missing_ok=True)
            result = {"state": "done", "frames": int(exp.frames), "error": None}
    except RunDirLocked as err:  # taken by another writer since the check above
        return _locked(err, time.perf_counter() - start)
    except RunStopped as err:  # SIGTERM: the training loop wrote a checkpoint and stopped
        if _local_worker:  # and the worker starts no further trial
            _note_stop(err.signum, None)
        result = {"state": STOPPED, "frames": int(err.frames), "error": None}
    except Exception:
        lines = traceback.format_exc().rstrip().splitlines()
        atomic_write_text(run_dir / ERROR_FILE, "\n".join(lines[-ERROR_TAIL_LINES:]) + "\n")
        result = {"state": "failed", "frames": None, "error": lines[-1]}
    result.update(resumed=resumed, seconds=time.perf_counter() - start)
    _write_record(run_dir, {**record, **result, "finished": _now()})
    return result


# ------------------------------------------------------------------------------- backends
Outcome = Iterator[tuple[int, dict[str, Any]]]
"""``(index of the payload, run_trial's result)`` in the order the trials finish."""


def _locked(err: BaseException, seconds: float) -> dict[str, Any]:
    """The result of a trial whose run directory another writer holds (nothing written)."""
    return {
        "state": "failed",
        "frames": None,
        "error": str(err),
        "resumed": False,
        "seconds": seconds,
        "locked": True,
    }


PR_SET_PDEATHSIG = 1
"""``prctl`` option (Linux ``<sys/prctl.h>``): the signal a process gets when its parent dies."""


def _die_with_parent(parent: int) -> None:
    """Initializer of the local backend's workers: a worker dies with the sweep process that
    started it (kill -9 included), so no trial goes on writing its run directory while
    ``sweep.json`` says "pending" and a re-run resumes it. On Linux the kernel sends the worker
    SIGKILL when its parent dies (``prctl(PR_SET_PDEATHSIG)``); elsewhere, or when prctl is
    refused, a daemon thread polls the parent's pid every second. A worker whose parent died
    before this ran exits at once."""
    watched = False
    if sys.platform.startswith("linux"):
        import ctypes

        try:
            libc = ctypes.CDLL(None, use_errno=True)
            watched = libc.prctl(PR_SET_PDEATHSIG, int(signal.SIGKILL), 0, 0, 0) == 0
        except (OSError, AttributeError):
            watched = False
    if os.getppid() != parent:
        os._exit(1)
    if not watched:
        import threading

        def watch() -> None:
            while os.getppid() == parent:
                time.sleep(1.0)
            os._exit(1)

        threading.Thread(target=watch, name="sweep-parent-watch", daemon=True).start()


_local_worker = False
"""Whether this process is a worker of the local backend (see :func:`_init_worker`)."""
_stop_requested = False
"""In a local-backend worker: a stop signal arrived (see :func:`_init_worker`)."""


def _note_stop(signum: int, frame: Any) -> None:
    """A local-backend worker's handler of the stop signals outside a training loop."""
    global _stop_requested
    _stop_requested = True


def _init_worker(parent: int) -> None:
    """Initializer of the local backend's workers: die with the sweep process
    (:func:`_die_with_parent`), and take SIGTERM as a request to stop rather than an end.
    A training loop under way handles the signal itself (checkpoint, then
    :class:`~mapets_rl.experiment.runner.RunStopped`) and puts this handler back after it, so
    a second copy of the signal (``timeout`` and Slurm signal every process of the group, and
    the sweep forwards the one it got) cannot end the worker before its checkpoint; a trial
    that had not reached its training loop stops before training, and one that the worker
    is handed after the signal does not start (:func:`run_trial`)."""
    global _local_worker
    _local_worker = True
    _die_with_parent(parent)
    for signum in STOP_SIGNALS:
        signal.signal(signum, _note_stop)


class SweepStopped(Exception):
    """A sweep stopped by a signal (SIGTERM) after its running trials wrote a checkpoint and
    stopped: re-running the same command resumes them.

    Attributes:
        signum: the signal.
        stopped: the ids of the trials it stopped.
    """

    def __init__(self, signum: int, stopped: Sequence[str] = ()) -> None:
        self.signum, self.stopped = signum, list(stopped)
        name = signal.Signals(signum).name
        super().__init__(
            f"stopped by {name}: {len(self.stopped)} running trial(s) checkpointed and "
            "stopped; re-run the same command to resume the sweep"
        )


def _died(err: BaseException) -> dict[str, Any]:
    return {
        "state": "failed",
        "frames": None,
        "error": f"the trial's worker died: {type(err).__name__}: {err}".strip(),
        "resumed": False,
        "seconds": None,
    }


def local_workers(cpus_per_trial: float) -> int:
    """Worker processes of the local backend: ``cpu_count // cpus_per_trial`` (at least 1)."""
    return max(1, int((os.cpu_count() or 1) // cpus_per_trial))


def run_local(payloads: Sequence[Mapping[str, Any]], cpus_per_trial: float) -> Outcome:
    """The trials in a pool of spawned processes (a worker runs one trial at a time and
    imports torch once for all the trials it runs); the workers die with this process (see
    :func:`_die_with_parent`).

    A stop signal (:data:`~mapets_rl.experiment.runner.STOP_SIGNALS`: SIGTERM, as Slurm's
    preemption and ``timeout`` send it) received while the trials run in the main thread is
    forwarded once to every worker: each running trial ends its iteration with a checkpoint
    and stops (state ``"stopped"``), the trials not started stay pending, and once the
    workers have returned this raises :class:`SweepStopped`. A second signal ends this
    process at once (and its workers with it)."""
    workers = min(local_workers(cpus_per_trial), len(payloads))
    stop: list[int] = []
    with (
        concurrent.futures.ProcessPoolExecutor(
            max_workers=workers,
            mp_context=multiprocessing.get_context("spawn"),
            initializer=_init_worker,
            initargs=(os.getpid(),),
        ) as pool,
        _forward_stop_signals(stop),
    ):
        futures = {pool.submit(run_trial, p): i for i, p in enumerate(payloads)}
        for future in concurrent.futures.as_completed(futures):
            if stop:
                for pending in futures:
                    pending.cancel()  # not started yet: it stays pending
            if future.cancelled():
                continue
            try:
                result = future.result()
            except Exception as err:  # the process died (killed, out of memory)
                result = _died(err)
            yield futures[future], result
    if stop:
        raise SweepStopped(stop[0])


def _forward_stop_signals(stop: list[int]) -> contextlib.AbstractContextManager[None]:
    """While the block runs in the main thread, the first stop signal is appended to
    ``stop`` and forwarded to this process's children (the pool's workers, which stop their
    trial, see :func:`_init_worker`); a second one puts the previous handler back and
    signals again (by default this ends the process); see
    :func:`~mapets_rl.experiment.runner.on_stop_signal`."""

    def forward(signum: int) -> None:
        stop.append(signum)
        for child in multiprocessing.active_children():
            if child.pid is not None:
                with contextlib.suppress(ProcessLookupError):
                    os.kill(child.pid, signum)

    return on_stop_signal(forward)


def run_ray(
    payloads: Sequence[Mapping[str, Any]],
    cpus_per_trial: float,
    gpus_per_trial: float,
    address: str | None = None,
) -> Outcome:
    """The trials as Ray core tasks (``num_cpus``, ``num_gpus``, no retries); Ray schedules
    them. Starts a local Ray instance unless Ray is initialised or ``address`` (or
    ``RAY_ADDRESS``) names a cluster to join; shuts down only what it started."""
    ray = import_ray()
    started = False
    if not ray.is_initialized():
        kwargs = ray_init_kwargs(address)
        check_ray_address(kwargs["address"])
        ray.init(**kwargs)
        started = True
    reaper = reap_ray_agents_on_exit() if started and kwargs["address"] == "local" else None
    try:
        task = ray.remote(run_trial).options(
            num_cpus=cpus_per_trial, num_gpus=gpus_per_trial, max_retries=0
        )
        refs = {task.remote(dict(p)): i for i, p in enumerate(payloads)}
        pending = list(refs)
        while pending:
            done, pending = ray.wait(pending, num_returns=1)
            try:
                result = ray.get(done[0])
            except Exception as err:  # worker crashed, node lost
                result = _died(err)
            yield refs[done[0]], result
    finally:
        if started:
            ray.shutdown()
        if reaper is not None:
            reaper.stdin.close()  # a normal end: the agents have exited with Ray
            reaper.wait()


def import_submitit() -> Any:
    """The ``submitit`` module, or a one-line ValueError saying how to install it."""
    try:
        import submitit
    except ImportError:
        raise ValueError(
            "backend 'submitit' needs the submitit package: pip install 'mapets-rl[slurm]' "
            "(or use --backend local)"
        ) from None
    return submitit


def submitit_executor(
    folder: Path, params: Mapping[str, Any], cpus_per_trial: float, gpus_per_trial: float
) -> Any:
    """submitit's ``AutoExecutor`` writing its job files under ``folder`` (one folder per job),
    each job reserving ``cpus_per_trial`` CPUs and ``gpus_per_trial`` GPUs; ``params`` are
    its other parameters (``cluster`` chooses the executor, see
    :attr:`SweepSpec.executor_params`). ConfigError naming ``executor_params`` for an unknown
    cluster or parameter."""
    submitit = import_submitit()
    params = dict(params)
    cluster = params.pop("cluster", None)
    try:
        executor = submitit.AutoExecutor(folder=folder / "%j", cluster=cluster)
        executor.update_parameters(
            cpus_per_task=int(cpus_per_trial), gpus_per_node=int(gpus_per_trial), **params
        )
    except (NameError, ValueError, TypeError, RuntimeError, AssertionError) as err:
        first = next((line for line in str(err).splitlines() if line.strip()), repr(err))
        raise ConfigError(f"executor_params {dict(params, cluster=cluster)}: {first}") from None
    return executor


def run_submitit(payloads: Sequence[Mapping[str, Any]], executor: Any) -> Outcome:
    """The trials as submitit jobs of ``executor`` (:func:`submitit_executor`; one job array
    on Slurm), each running :func:`run_trial` on a node of the cluster, which must have the
    project, the recipe and the scenario installed and see ``--out`` (a shared file system).
    The jobs are the cluster's: they outlive this process (a re-run finds a trial still
    running in its lock and reports it, see :func:`run_trial`, and resumes it once its job has
    ended); a job that ends without a result (killed, out of time, out of memory) is a failed
    trial that a re-run resumes from its latest checkpoint."""
    with executor.batch():
        jobs = [executor.submit(run_trial, dict(p)) for p in payloads]
    pending = dict(enumerate(jobs))
    while pending:
        for index, job in list(pending.items()):
            if not job.done():
                continue
            del pending[index]
            try:
                result = job.result()
            except Exception as err:  # the job failed outside run_trial (killed, timed out)
                result = _died(err)
            yield index, result
        if pending:
            time.sleep(SUBMITIT_POLL_S)


# ------------------------------------------------------------------------------ the sweep
def _manifest_data(
    spec: SweepSpec,
    trials: Sequence[Trial],
    records: Mapping[str, Mapping[str, Any]],
    earlier: Sequence[Mapping[str, Any]] = (),
) -> dict[str, Any]:
    """``sweep.json``: the spec, every trial of it with its record, then the ``earlier``
    trials of ``OUT`` that this spec does not plan (:func:`_earlier_trials`)."""
    return {
        "recipe": spec.recipe,
        "env": spec.env,
        "seeds": spec.seeds,
        "grid": spec.grid,
        "overrides": spec.overrides,
        "config_file": spec.config_file,
        "backend": spec.backend,
        "address": spec.address,
        "cpus_per_trial": spec.cpus_per_trial,
        "gpus_per_trial": spec.gpus_per_trial,
        "executor_params": spec.executor_params,
        "updated": _now(),
        "trials": [
            {
                "id": t.id,
                "run_dir": str(Path(TRIALS_DIR) / t.id),
                "seed": t.seed,
                "values": t.values,
                **records[t.id],
            }
            for t in trials
        ]
        + [dict(entry) for entry in earlier],
    }


def _earlier_trials(spec: SweepSpec, trials: Sequence[Trial]) -> list[dict[str, Any]]:
    """The trials that ``OUT/sweep.json`` lists and ``trials`` (this spec's) do not: those of
    an earlier sweep into ``OUT`` with another grid or seeds, which its manifest and summary
    keep (marked ``"ran": false``). An entry whose id is not a plain directory name, or whose
    directory is gone, is dropped."""
    path = spec.out / MANIFEST
    if not path.is_file():
        return []
    from mapets_rl.experiment.results import read_json_object

    entries = read_json_object(path).get("trials")
    planned = {t.id for t in trials}
    kept = []
    for entry in entries if isinstance(entries, list) else []:
        tid = entry.get("id") if isinstance(entry, dict) else None
        if (
            isinstance(tid, str)
            and tid not in planned
            and tid not in (".", "..")
            and "/" not in tid
            and (spec.out / TRIALS_DIR / tid).is_dir()
        ):
            kept.append({**entry, "run_dir": str(Path(TRIALS_DIR) / tid), "ran": False})
    return kept


def _check_manifest(spec: SweepSpec) -> None:
    """ConfigError when ``spec.out`` holds a sweep of another recipe or scenario."""
    path = spec.out / MANIFEST
    if not path.is_file():
        return
    from mapets_rl.experiment.results import read_json_object

    old = read_json_object(path)
    for key in ("recipe", "env"):
        if old.get(key) != getattr(spec, key):
            raise ConfigError(
                f"out {str(spec.out)!r} holds a sweep of {key} {old.get(key)!r}, not "
                f"{getattr(spec, key)!r}; choose another --out"
            )


def _check_resumes(cls: type, spec: SweepSpec, trials: Sequence[Trial]) -> None:
    """ConfigError (one line naming the trial) when a trial that has checkpoints and is not
    finished with the same config would be resumed with a change that a resume refuses
    (:meth:`~mapets_rl.experiment.Experiment.check_resume`: an added or changed override
    other than the budget and the intervals), before any trial starts."""
    from mapets_rl.experiment.checkpoint import latest_checkpoint

    for trial in trials:
        if _finished(trial) or latest_checkpoint(trial.run_dir) is None:
            continue
        try:
            cls.check_resume(trial.run_dir, trial.overrides)
        except ConfigError as err:
            raise ConfigError(
                f"out {str(spec.out)!r}: trial {trial.id}: {err} (a sweep with other "
                "settings needs another --out)"
            ) from None


def _finished(trial: Trial) -> bool:
    record = read_trial_record(trial.run_dir)
    return bool(record and record.get("state") == "done" and record.get("config") == trial.config)


def default_x(run_dirs: Sequence[Path], source: str) -> str:
    """``"episode"`` when every entry compared numbers its episode (e.g. MA-PETS's training
    episodes, whose frames differ between runs), else ``"frames"``."""
    from mapets_rl.experiment.results import ENTRY_LISTS, read_results

    for run_dir in run_dirs:
        res = read_results(run_dir)
        entries = res[ENTRY_LISTS[source]] or res["train"]
        if not entries or any("episode" not in e["metrics"] for e in entries):
            return "frames"
    return "episode"


def _summary_fields(
    spec: SweepSpec, earlier: Sequence[Mapping[str, Any]], run_dirs: Sequence[Path]
) -> list[str]:
    """What the summary of the finished trials ``run_dirs`` groups by: the grid keys of
    ``spec``, then those of the ``earlier`` trials it keeps and, when there are such trials,
    every other config key whose value differs among ``run_dirs`` (their ``trial.json``; the
    seed aside), so that trials of different settings never share a group."""
    fields = list(spec.grid)
    for entry in earlier:
        values = entry.get("values")
        fields += [k for k in (values if isinstance(values, dict) else {}) if k not in fields]
    if not earlier:
        return fields
    configs = [_flat_config((read_trial_record(d) or {}).get("config")) for d in run_dirs]
    for key in sorted(set().union(*configs)):
        differs = len({json.dumps(c.get(key), sort_keys=True) for c in configs}) > 1
        nested = any(key == f or key.startswith(f"{f}.") for f in fields)
        if differs and key != "seed" and not nested:
            fields.append(key)
    return fields


def _flat_config(config: Any, prefix: str = "") -> dict[str, Any]:
    """A ``to_dict`` config as ``{"dotted.key": leaf}`` (``{}`` for what is not a mapping)."""
    if not isinstance(config, Mapping):
        return {prefix: config} if prefix else {}
    out: dict[str, Any] = {}
    for key, value in config.items():
        out.update(_flat_config(value, f"{prefix}.{key}" if prefix else str(key)))
    return out


PROBE_OVERRIDES = ("logger=none", "video=false", "eval_episodes=1", "device=cpu")
"""What :func:`probe_metrics` changes in a trial's config: nothing written beside the
evaluation, one episode on this machine's CPU (the metrics' names are those of the trial)."""
PROBE_COLLECTOR = ("collector=single", "collector_workers=1")
"""And, for the recipes that have a collector, one in this process (no Ray, no workers)."""


def probe_metrics(cls: type, trial: Trial) -> set[str]:
    """The names of the metrics in an evaluation entry of ``trial``'s run: one evaluation
    episode of its untrained policy (its config with :data:`PROBE_OVERRIDES`), in a
    temporary run directory that is removed after it. A run's evaluation entries are its
    :meth:`~mapets_rl.experiment.Experiment.evaluate`'s metrics, whose names do not depend on
    the training."""
    import tempfile

    changed = [*PROBE_OVERRIDES]
    if "collector" in {f.name for f in dataclasses.fields(cls.Config)}:
        changed += PROBE_COLLECTOR
    keys = {parse_override(o)[0] for o in changed}
    overrides = [o for o in trial.overrides if parse_override(o)[0] not in keys] + changed
    config = cls.Config().with_overrides(overrides)
    with tempfile.TemporaryDirectory(prefix="mapets-rl-probe-") as tmp:
        exp = cls(config, Path(tmp) / "run")
        try:
            return set(exp.evaluate(episodes=1, video=False))
        finally:
            exp.close()
            collector = getattr(exp, "collector", None)
            if collector is not None:
                collector.shutdown()


def _check_summary_options(
    spec: SweepSpec, run_dirs: Sequence[Path], cls: type, trials: Sequence[Trial]
) -> None:
    """ConfigError naming ``x`` or ``metrics`` when the summary could not compare them,
    before any trial starts: against the metrics every entry of the finished trials
    ``run_dirs`` holds (a re-run), else ``x`` against the metrics of
    :data:`~mapets_rl.metrics.METRIC_UNITS` (an x axis is a counter with a unit: ``episode``,
    ``train_time``, ...) and, when the summary compares evaluations (``source="eval"``),
    ``metrics`` against those of an evaluation of the first trial's untrained policy
    (:func:`probe_metrics`). The training metrics of a sweep that has not finished a trial
    (``source="train"``: losses appear once the updates start) are only known once one has."""
    from mapets_rl.experiment.results import ENTRY_LISTS, read_results
    from mapets_rl.metrics import METRIC_UNITS

    if not run_dirs:
        axes = ["auto", "frames", *METRIC_UNITS]
        check(spec.x in axes, "x", f"one of {axes}", spec.x)
        if spec.metrics and spec.source == "eval":
            names = probe_metrics(cls, trials[0])
            unknown = [m for m in spec.metrics if m not in names]
            check(not unknown, "metrics", f"metrics of an evaluation {sorted(names)}", unknown)
        return
    common: set[str] | None = None
    for run_dir in run_dirs:
        res = read_results(run_dir)
        for entry in res[ENTRY_LISTS[spec.source]] or res["train"]:
            names = set(entry["metrics"])
            common = names if common is None else common & names
    common = common or set()
    if spec.x not in ("auto", "frames"):
        check(
            spec.x in common,
            "x",
            f"'auto', 'frames' or a metric of every finished trial {sorted(common)}",
            spec.x,
        )
    unknown = [m for m in spec.metrics or [] if m not in common]
    check(not unknown, "metrics", f"metrics of every finished trial {sorted(common)}", unknown)


def summarise(
    spec: SweepSpec, run_dirs: Sequence[Path], group_by: Sequence[str] | None = None
) -> dict[str, Path]:
    """:func:`compare` of ``run_dirs`` grouped by ``group_by`` (default: the grid keys) into
    ``OUT/summary``."""
    from mapets_rl.app.comparison import compare

    x = default_x(run_dirs, spec.source) if spec.x == "auto" else spec.x
    title = f"sweep of {spec.recipe} on {spec.env}"
    return compare(
        run_dirs,
        spec.out / SUMMARY_DIR,
        spec.metrics,
        source=spec.source,
        group_by=list(spec.grid) if group_by is None else list(group_by),
        x=x,
        title=title,
    )


def run_sweep(spec: SweepSpec, echo: Callable[[str], None] = print) -> SweepResult:
    """Run every unfinished trial of ``spec`` on its backend, keep ``OUT/sweep.json`` up to
    date (atomically) as trials finish, then summarise the finished ones with
    :func:`compare` into ``OUT/summary``.

    Everything is validated before the first trial starts (see :func:`plan_trials`); a trial
    that fails does not stop the others. ``echo`` receives one line per event.
    """
    from mapets_rl.experiment.runner import refuse_run_dir_as_out

    refuse_run_dir_as_out(spec.out, "out")
    check_writable_dir(spec.out, "out")
    cls, trials = plan_trials(spec)
    if spec.backend == "ray":
        import_ray()
    elif spec.backend == "submitit":
        import_submitit()
    _check_manifest(spec)
    _check_resumes(cls, spec, trials)
    earlier = _earlier_trials(spec, trials)
    earlier_done = [spec.out / e["run_dir"] for e in earlier if e.get("state") == "done"]
    done = [*(t.run_dir for t in trials if _finished(t)), *earlier_done]
    _check_summary_options(spec, done, cls, trials)
    recipe = _import_path(cls, f"recipe {spec.recipe!r}")
    scenarios = trial_scenarios(spec.env)
    make_writable_dir(spec.out, "out")
    executor = None
    if spec.backend == "submitit":
        executor = submitit_executor(
            spec.out / SUBMITIT_DIR,
            spec.executor_params,
            spec.cpus_per_trial,
            spec.gpus_per_trial,
        )
    # one sweep writes OUT at a time (a second one is refused naming the holder's pid); the
    # lock is released at the return, or with the process
    lock = RunDirLock.acquire(spec.out, "out")
    records: dict[str, dict[str, Any]] = {}
    todo: list[Trial] = []
    for trial in trials:
        if _finished(trial):
            old = read_trial_record(trial.run_dir) or {}
            records[trial.id] = {
                "state": "done",
                "ran": False,
                "resumed": False,
                "seconds": old.get("seconds"),
                "error": None,
            }
        else:
            records[trial.id] = {"state": "pending", "ran": True, "error": None}
            todo.append(trial)
    manifest = spec.out / MANIFEST
    atomic_write_text(
        manifest, json.dumps(_manifest_data(spec, trials, records, earlier), indent=1)
    )
    echo(
        f"sweep: {len(trials)} trials ({len(trials) - len(todo)} already finished), "
        f"{len(todo)} to run on the {spec.backend} backend"
        + (f"; {len(earlier)} trials of earlier grids kept" if earlier else "")
    )
    payloads = [
        {
            "recipe": recipe,
            "scenarios": scenarios,
            "run_dir": str(t.run_dir),
            "overrides": t.overrides,
            "config": t.config,
            "threads": max(1, int(spec.cpus_per_trial)),
        }
        for t in todo
    ]
    if payloads:
        if spec.backend == "local":
            outcomes = run_local(payloads, spec.cpus_per_trial)
        elif spec.backend == "ray":
            outcomes = run_ray(payloads, spec.cpus_per_trial, spec.gpus_per_trial, spec.address)
        else:
            outcomes = run_submitit(payloads, executor)
        try:
            for index, result in outcomes:
                trial = todo[index]
                if (
                    result["state"] == "failed"
                    and not result.get("locked")  # another writer's directory: not ours
                    and not (trial.run_dir / ERROR_FILE).is_file()
                ):
                    # the worker died before it could record why
                    atomic_write_text(trial.run_dir / ERROR_FILE, str(result["error"]) + "\n")
                records[trial.id] = {"ran": True, **result}
                atomic_write_text(
                    manifest, json.dumps(_manifest_data(spec, trials, records, earlier), indent=1)
                )
                if result["state"] == "pending":
                    echo(f"trial {trial.id}: not started (the sweep is stopping)")
                    continue
                how = "resumed, " if result.get("resumed") else ""
                seconds = result.get("seconds")
                took = f"{seconds:.1f} s" if seconds is not None else "?"
                echo(
                    f"trial {trial.id}: {result['state']} ({how}{took})"
                    + (f": {result['error']}" if result["state"] == "failed" else "")
                )
        except SweepStopped as err:
            lock.release()
            stopped = [t.id for t in trials if records[t.id]["state"] == STOPPED]
            raise SweepStopped(err.signum, stopped) from None
    failed = [t.id for t in trials if records[t.id]["state"] == "failed"]
    finished = [t.run_dir for t in trials if records[t.id]["state"] == "done"]
    finished += earlier_done
    summary: dict[str, Path] = {}
    summary_error = None
    if finished:
        try:
            summary = summarise(spec, finished, _summary_fields(spec, earlier, finished))
        except ValueError as err:
            summary_error = str(err)
    else:
        summary_error = "no trial finished"
    lock.release()
    return SweepResult(trials, records, failed, summary, summary_error)


# ------------------------------------------------------------------------------------ CLI
def spec_from_args(args: argparse.Namespace) -> SweepSpec:
    """A :class:`SweepSpec` from the parsed ``sweep`` arguments (``key=value`` items that
    followed ``--seeds`` are overrides)."""
    seeds, overrides = [], list(args.overrides)
    recipe, env = args.recipe, args.env
    if recipe is not None and "=" in recipe:  # `sweep --config NAME key=value ...`
        overrides.insert(0, recipe)
        recipe = None
    from mapets_rl.experiment.published import load_published, recipe_and_env

    published = None if args.config is None else load_published(args.config)
    recipe, env = recipe_and_env("sweep", recipe, env, published)
    for item in args.seeds:
        if "=" in item:
            overrides.append(item)
            continue
        try:
            seeds.append(int(item))
        except ValueError:
            raise ConfigError(f"seeds must be integers >= 0, got {item!r}") from None
    metrics = None
    if args.metrics is not None:
        metrics = [m.strip() for m in args.metrics.split(",") if m.strip()]
        check(bool(metrics), "metrics", "at least one metric name (a,b,...)", args.metrics)
    for item in overrides:
        parse_override(item)
    executor_params = dict(parse_override(item) for item in args.executor_param)
    return SweepSpec(
        recipe=recipe,
        env=env,
        seeds=seeds,
        out=Path(args.out),
        grid=parse_grid(args.grid),
        overrides=overrides,
        config_file=args.config,
        backend=args.backend,
        address=args.address,
        cpus_per_trial=args.cpus_per_trial,
        gpus_per_trial=args.gpus_per_trial,
        executor_params=executor_params,
        metrics=metrics,
        source=args.source,
        x=args.x,
    )


def cmd_sweep(args: argparse.Namespace) -> int:
    """``mapets-rl sweep``: 0 when every trial finished, 1 when some failed, 2 for bad input
    (before any trial starts), 128 + the signal's number when a stop signal stopped it
    (:class:`SweepStopped`)."""
    try:
        spec = spec_from_args(args)
        result = run_sweep(spec, echo=lambda line: print(line, flush=True))
    except ValueError as err:
        lines = [line.strip() for line in str(err).splitlines() if line.strip()]
        sys.stderr.write(f"mapets-rl: error: {lines[0] if lines else 'failed'}\n")
        return 2
    except SweepStopped as err:  # as a train run stopped by the signal: 128 + its number
        sys.stderr.write(f"mapets-rl: {err}\n")
        return 128 + err.signum
    if result.summary:
        print(result.summary["table"].read_text(), end="")
    if result.summary_error:
        sys.stderr.write(f"mapets-rl: warning: no summary: {result.summary_error}\n")
    print(
        json.dumps(
            {
                "out": str(spec.out),
                "trials": len(result.trials),
                "failed": result.failed,
                **{k: str(v) for k, v in result.summary.items()},
            }
        )
    )
    if result.failed:
        sys.stderr.write(
            f"mapets-rl: error: {len(result.failed)} of {len(result.trials)} trials failed: "
            + "; ".join(
                f"{tid} ({result.records[tid]['error']}; see "
                f"{spec.out / TRIALS_DIR / tid / ERROR_FILE})"
                for tid in result.failed
            )
            + "\n"
        )
        return 1
    return 0


__all__ = [
    "SweepResult",
    "SweepSpec",
    "SweepStopped",
    "Trial",
    "cmd_sweep",
    "parse_grid",
    "plan_trials",
    "run_sweep",
    "run_trial",
    "trial_id",
]
