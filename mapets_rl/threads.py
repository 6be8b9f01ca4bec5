"""How many threads torch uses, and how its OpenMP threads wait: chosen by the machine's load.

torch's default intra-op thread count is the number of cores, and its OpenMP runtime lets idle
threads spin (busy-wait) between parallel regions. On a machine that other jobs already keep
busy, the spinning threads steal the cores the working ones need: a 2-episode MA-PETS run on 2
busy cores took 3.3x longer with 2 threads than with 1 (issue 14), and the README's ten-line
example 9.8x longer (issue 52). The policy here, the same for the ``mapets-rl`` command and the
Python API (:class:`~mapets_rl.experiment.Experiment` applies it when it is built):

1. OpenMP wait policy ``PASSIVE`` (idle threads sleep) unless ``OMP_WAIT_POLICY`` is set. The
   runtime reads it once, when torch is imported, so :func:`prepare_process` must run before
   the first ``import torch`` (the ``mapets-rl`` entry point calls it first thing); later, the
   choice is only reported. With one thread nothing spins, whatever the policy.
2. Thread count, first that applies:

   - an explicit request: a config's ``threads`` field (MA-PETS: ``num_threads``), else the
     ``MAPETS_RL_THREADS`` environment variable;
   - ``OMP_NUM_THREADS`` set by the user: torch already follows it, left alone;
   - a worker process started by a launcher (a ``multiprocessing`` child such as the local
     sweep's workers, a submitit job; Ray sets ``OMP_NUM_THREADS`` in its workers): the
     count its launcher gave it, left alone;
   - otherwise (a user's script or notebook, the ``mapets-rl`` command): the cores not already
     busy, ``round(cpus - load)`` clamped to ``[1, torch's count]``, with ``load`` the 1-minute
     load average (one thread on a busy machine, all cores on a quiet one). This choice is
     made once per process and kept by every later experiment of the process: by then the
     load average counts the process's own training.

The count changes the order of floating-point reductions, so a run resumed under another load
can differ in the last bits from an uninterrupted one; set ``threads`` or ``MAPETS_RL_THREADS``
where bitwise-identical resumes matter.

Every choice is logged (level INFO) on the ``mapets_rl.threads`` logger with its reason, and
kept on the experiment as ``Experiment.threads`` (a :class:`ThreadChoice`); the first training
of a process that shows progress prints it once on stderr (:func:`announce_threads`).
"""

from __future__ import annotations

import dataclasses
import logging
import multiprocessing
import os
import sys
from collections.abc import MutableMapping

THREADS_ENV = "MAPETS_RL_THREADS"
"""Environment variable with an explicit torch intra-op thread count (an integer >= 1)."""

log = logging.getLogger("mapets_rl.threads")

SUBMITIT_ENV = "SUBMITIT_EXECUTOR"
"""Set by submitit in the processes of its jobs (the sweep's ``submitit`` backend)."""

_load_choice: ThreadChoice | None = None
"""The load's choice in this process, made by the first :func:`configure_threads` that chose."""

_announced = False
"""Whether :func:`announce_threads` has printed in this process."""


@dataclasses.dataclass(frozen=True)
class ThreadChoice:
    """What :func:`choose_threads` decided.

    Attributes:
        threads: torch intra-op threads, ``None`` to leave torch's own choice (it follows
            ``OMP_NUM_THREADS``).
        reason: why, in words.
        by_load: whether the load average chose it (nothing was requested).
    """

    threads: int | None
    reason: str
    by_load: bool = False


def available_cpus() -> int:
    """CPUs this process may run on (its affinity mask where the OS has one)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        return os.cpu_count() or 1


def load_average() -> float | None:
    """The 1-minute load average, ``None`` where the OS has none."""
    try:
        return os.getloadavg()[0]
    except (AttributeError, OSError):
        return None


def launched_worker(environ: MutableMapping[str, str] | None = None) -> bool:
    """Whether this process is a worker its launcher gave a thread count: a ``multiprocessing``
    child (the local sweep's spawned workers) or a submitit job (``SUBMITIT_EXECUTOR`` set)."""
    environ = os.environ if environ is None else environ
    return multiprocessing.parent_process() is not None or bool(environ.get(SUBMITIT_ENV))


def _parse_threads(value: object, source: str) -> int:
    """``value`` as a thread count >= 1; ``ValueError`` naming ``source`` otherwise."""
    try:
        threads = int(str(value).strip())
    except ValueError:
        threads = 0
    if threads < 1 or str(value).strip() != str(threads):
        raise ValueError(f"{source} must be an integer >= 1 (torch threads), got {value!r}")
    return threads


def choose_threads(
    requested: int | None = None,
    *,
    environ: MutableMapping[str, str] | None = None,
    cpus: int | None = None,
    load: float | None = None,
    default: int | None = None,
    automatic: bool = True,
) -> ThreadChoice:
    """The torch intra-op thread count for this process (see the module docstring).

    Args:
        requested: an explicit count (``None`` or 0: not requested).
        environ: environment variables (default ``os.environ``).
        cpus: CPUs available (default :func:`available_cpus`).
        load: 1-minute load average of other processes (default :func:`load_average`).
        default: torch's default count (default ``cpus``).
        automatic: choose by the load when nothing is requested; ``False`` in a launcher's
            worker (:func:`launched_worker`), which keeps the count it was given
            (``threads=None``).

    Raises:
        ValueError: ``requested`` or ``MAPETS_RL_THREADS`` is not an integer >= 1.
    """
    environ = os.environ if environ is None else environ
    if requested:
        return ThreadChoice(_parse_threads(requested, "threads"), "requested")
    if environ.get(THREADS_ENV, "").strip():
        threads = _parse_threads(environ[THREADS_ENV], THREADS_ENV)
        return ThreadChoice(threads, f"{THREADS_ENV}={threads}")
    omp = environ.get("OMP_NUM_THREADS", "").strip()
    if omp:
        return ThreadChoice(None, f"OMP_NUM_THREADS={omp} (torch follows it)")
    if not automatic:
        return ThreadChoice(None, "a launcher's worker keeps the count it was given")
    cpus = available_cpus() if cpus is None else cpus
    load = load_average() if load is None else load
    default = cpus if default is None else default
    if load is None:
        return ThreadChoice(default, f"{cpus} CPUs, load average unknown", by_load=True)
    threads = max(1, min(default, round(cpus - load)))
    busy = "busy" if threads < default else "quiet"
    return ThreadChoice(threads, f"load average {load:.2f} on {cpus} CPUs: {busy}", by_load=True)


def prepare_process(environ: MutableMapping[str, str] | None = None) -> str:
    """Before torch is imported: OpenMP wait policy ``PASSIVE`` unless ``OMP_WAIT_POLICY`` is
    set, and ``OMP_NUM_THREADS`` from a valid ``MAPETS_RL_THREADS`` where only the latter is set
    (so that worker processes and every OpenMP library follow it too).

    ``environ``: environment variables to read and update (default ``os.environ``).
    Returns the wait policy in effect: ``"PASSIVE"``, the user's value, or
    ``"runtime default"`` when torch was imported first and no policy was set.
    """
    environ = os.environ if environ is None else environ
    explicit = environ.get(THREADS_ENV, "").strip()
    if explicit.isdigit() and int(explicit) >= 1 and not environ.get("OMP_NUM_THREADS"):
        environ["OMP_NUM_THREADS"] = explicit
    policy = environ.get("OMP_WAIT_POLICY", "").strip()
    if policy:
        return policy
    if "torch" in sys.modules:
        return "runtime default"
    environ["OMP_WAIT_POLICY"] = "PASSIVE"
    return "PASSIVE"


def config_threads(config: object) -> int | None:
    """The thread count a config asks for: its ``threads`` field, else ``num_threads``
    (MA-PETS), ``None`` when it has neither or leaves the choice open (0)."""
    for field in ("threads", "num_threads"):
        value = getattr(config, field, None)
        if value:
            return int(value)
    return None


def configure_threads(requested: int | None = None) -> ThreadChoice:
    """Apply :func:`choose_threads` to torch (``torch.set_num_threads``) and log the choice.

    ``requested``: an explicit count (a config field); ``None`` or 0 leaves the choice to the
    environment and the load. The load's choice is made at the first call of the process and
    reused by every later one (the load average counts this process too once it runs, so the
    runner calls this early, when an experiment is built)."""
    import torch

    global _load_choice
    choice = choose_threads(
        requested, default=torch.get_num_threads(), automatic=not launched_worker()
    )
    if choice.by_load:
        _load_choice = _load_choice or choice
        choice = _load_choice
    if choice.threads is not None and choice.threads != torch.get_num_threads():
        torch.set_num_threads(choice.threads)
    policy = os.environ.get("OMP_WAIT_POLICY", "").strip() or "runtime default"
    log.info(
        "torch threads: %d (%s); OpenMP wait policy: %s",
        torch.get_num_threads(),
        choice.reason,
        policy,
    )
    return choice


def announce_threads(choice: ThreadChoice) -> bool:
    """Print the torch thread count and ``choice``'s reason as one line on stderr, the first
    time in the process (the runner calls it when a training that shows progress starts).
    Returns whether it printed."""
    global _announced
    if _announced:
        return False
    import torch

    _announced = True
    print(
        f"torch threads: {torch.get_num_threads()} ({choice.reason}; "
        f"{THREADS_ENV}=N or a config's num_threads sets them)",
        file=sys.stderr,
        flush=True,
    )
    return True
