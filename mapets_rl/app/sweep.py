"""Sweeps: the cartesian product of config grids x seeds, one normal run directory per trial,
executed by a process pool on this machine or by Ray, summarised with :func:`compare`.

    mapets-rl sweep RECIPE --env SCENARIO --seeds 0 1 2 --grid comm.comm_range=0,50,100
                    [--grid comm.p_fail=0,0.25 ...] [key=value ...] --out DIR
                    [--backend local|ray] [--address HOST:PORT] [--cpus-per-trial N]
                    [--gpus-per-trial N] [--config FILE] [--metrics a,b] [--source eval|train]
                    [--x auto|frames|METRIC]

Layout of ``--out``::

    sweep.json                     the manifest: the sweep's spec and every trial's state
    trials/<key>=<value>__...__seed=<N>/   one run directory per trial (config.yaml,
                                   results.json, checkpoints/, logs/) plus trial.json (the
                                   trial's record) and, when it failed, error.txt (the traceback)
    summary/                       compare's learning_curves.png, final_metrics.md,
                                   summary.json, curves.json, grouped by the swept fields

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
already finished (``--x`` of a sweep with none against the metrics that have a unit). A
trial that raises is recorded as failed (the traceback in its ``error.txt``, the last line in
the manifest); the other trials still run, and :func:`run_sweep` reports the failed ones (the
command then exits with 1).

One sweep per ``--out`` at a time: a second one, while the first runs, is refused in one line
naming its pid (a sweep holds ``OUT/.lock``, a :class:`~mapets_rl.experiment.files.RunDirLock`).
One writer per trial: the local backend's workers die with the sweep process (kill -9
included), and a trial whose run directory another writer still holds (its lock: an orphaned
Ray task, a ``mapets-rl resume``) is reported as failed, naming the holder's pid, without a
byte written there; a later re-run resumes it.

Backends (neither schedules by hand):

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

Recipes and scenarios reach the trial processes by import path: a recipe installed under an
entry point, or a scenario registered in this process with :func:`register_env`, must be an
importable module-level object (not defined in ``__main__``).
"""

from __future__ import annotations

import argparse
import concurrent.futures
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
from mapets_rl.ray_runtime import (
    check_ray_address,
    import_ray,
    ray_init_kwargs,
    reap_ray_agents_on_exit,
)

MANIFEST = "sweep.json"
TRIALS_DIR = "trials"
SUMMARY_DIR = "summary"
BACKENDS = ("local", "ray")
RESERVED_KEYS = {"env": "--env", "seed": "--seeds"}
"""Config keys a sweep sets itself, with the option that sets them."""
ERROR_TAIL_LINES = 60
"""Lines of a failed trial's traceback kept in its ``error.txt``."""


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
        backend: ``"local"`` or ``"ray"``.
        address: Ray cluster address to join (``ray`` backend; default ``RAY_ADDRESS``, else a
            local Ray instance is started).
        cpus_per_trial: CPUs each trial reserves and its torch threads (> 0; ``local``: >= 1).
        gpus_per_trial: GPUs each trial reserves (>= 0; ``ray`` backend only).
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
            check(
                self.address is None,
                "address",
                "unset with the local backend (it joins a Ray cluster: --backend ray)",
                self.address,
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

    Returns ``{"state": "done" | "failed", "resumed", "seconds", "frames", "error"}``; an
    exception is not raised but recorded: the traceback's last :data:`ERROR_TAIL_LINES` lines
    in ``run_dir/error.txt``, its last line in the result and ``trial.json``.
    """
    from mapets_rl import quiet_dependencies

    quiet_dependencies()  # a trial's process is an application of its own, as the CLI is
    run_dir = Path(payload["run_dir"])
    start = time.perf_counter()
    from mapets_rl.experiment.files import RunDirLock, RunDirLocked

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
        exp.train()
        (run_dir / ERROR_FILE).unlink(missing_ok=True)
        result = {"state": "done", "frames": int(exp.frames), "error": None}
    except RunDirLocked as err:  # taken by another writer since the check above
        return _locked(err, time.perf_counter() - start)
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
    :func:`_die_with_parent`)."""
    workers = min(local_workers(cpus_per_trial), len(payloads))
    with concurrent.futures.ProcessPoolExecutor(
        max_workers=workers,
        mp_context=multiprocessing.get_context("spawn"),
        initializer=_die_with_parent,
        initargs=(os.getpid(),),
    ) as pool:
        futures = {pool.submit(run_trial, p): i for i, p in enumerate(payloads)}
        for future in concurrent.futures.as_completed(futures):
            try:
                result = future.result()
            except Exception as err:  # the process died (killed, out of memory)
                result = _died(err)
            yield futures[future], result


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


def _check_summary_options(spec: SweepSpec, run_dirs: Sequence[Path]) -> None:
    """ConfigError naming ``x`` or ``metrics`` when the summary could not compare them,
    before any trial starts: against the metrics every entry of the finished trials
    ``run_dirs`` holds (a re-run), else ``x`` against the metrics of
    :data:`~mapets_rl.metrics.METRIC_UNITS` (an x axis is a counter with a unit: ``episode``,
    ``train_time``, ...). The metrics of a sweep that has not finished a trial are only known
    once one has."""
    from mapets_rl.experiment.results import ENTRY_LISTS, read_results
    from mapets_rl.metrics import METRIC_UNITS

    if not run_dirs:
        axes = ["auto", "frames", *METRIC_UNITS]
        check(spec.x in axes, "x", f"one of {axes}", spec.x)
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
    _check_manifest(spec)
    _check_resumes(cls, spec, trials)
    earlier = _earlier_trials(spec, trials)
    earlier_done = [spec.out / e["run_dir"] for e in earlier if e.get("state") == "done"]
    _check_summary_options(spec, [*(t.run_dir for t in trials if _finished(t)), *earlier_done])
    recipe = _import_path(cls, f"recipe {spec.recipe!r}")
    scenarios = trial_scenarios(spec.env)
    make_writable_dir(spec.out, "out")
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
        outcomes = (
            run_local(payloads, spec.cpus_per_trial)
            if spec.backend == "local"
            else run_ray(payloads, spec.cpus_per_trial, spec.gpus_per_trial, spec.address)
        )
        for index, result in outcomes:
            trial = todo[index]
            if (
                result["state"] == "failed"
                and not result.get("locked")  # another writer's directory: not ours to write
                and not (trial.run_dir / ERROR_FILE).is_file()
            ):
                # the worker died before it could record why
                atomic_write_text(trial.run_dir / ERROR_FILE, str(result["error"]) + "\n")
            records[trial.id] = {"ran": True, **result}
            atomic_write_text(
                manifest, json.dumps(_manifest_data(spec, trials, records, earlier), indent=1)
            )
            how = "resumed, " if result.get("resumed") else ""
            seconds = result.get("seconds")
            took = f"{seconds:.1f} s" if seconds is not None else "?"
            echo(
                f"trial {trial.id}: {result['state']} ({how}{took})"
                + (f": {result['error']}" if result["state"] == "failed" else "")
            )
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
        metrics=metrics,
        source=args.source,
        x=args.x,
    )


def cmd_sweep(args: argparse.Namespace) -> int:
    """``mapets-rl sweep``: 0 when every trial finished, 1 when some failed, 2 for bad input
    (before any trial starts)."""
    try:
        spec = spec_from_args(args)
        result = run_sweep(spec, echo=lambda line: print(line, flush=True))
    except ValueError as err:
        lines = [line.strip() for line in str(err).splitlines() if line.strip()]
        sys.stderr.write(f"mapets-rl: error: {lines[0] if lines else 'failed'}\n")
        return 2
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
    "Trial",
    "cmd_sweep",
    "parse_grid",
    "plan_trials",
    "run_sweep",
    "run_trial",
    "trial_id",
]
