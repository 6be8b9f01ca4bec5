"""Ray start-up, shared by the sweeps' Ray backend (:mod:`mapets_rl.app.sweep`) and the
model-free recipes' ``collector="ray"`` (:mod:`mapets_rl.experiment.runner`): importing Ray with
a one-line remedy, the ``ray.init`` keywords (join ``RAY_ADDRESS`` or start a local instance),
a bounded check that a named cluster answers, and the reaper of the agents a local instance
leaves behind a driver killed with kill -9.

The ground floor: it imports nothing of the project, so both floors may use it.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path
from typing import Any


def import_ray() -> Any:
    """The ``ray`` module, or a one-line ValueError saying how to install it."""
    try:
        import ray
    except ImportError:
        raise ValueError(
            "backend 'ray' needs the ray package: pip install 'mapets-rl[ray]' "
            "(or use --backend local)"
        ) from None
    return ray


RAY_CONNECT_TIMEOUT_S = 20
"""Seconds a Ray cluster named by an address has to answer before a run refuses it."""


class RayUnreachable(ValueError):
    """No Ray cluster answered at the given address (one line, names it)."""


def check_ray_address(address: str, timeout_s: int | None = None) -> None:
    """:class:`RayUnreachable` unless a Ray cluster answers at ``address`` within about
    ``timeout_s`` seconds. A throwaway interpreter joins and leaves it: ``ray.init`` on an
    unreachable address retries for minutes and then ends the process from Ray's C++ core,
    which no ``except`` can turn into one line. ``"local"`` (start a new instance) passes.
    ``timeout_s`` defaults to :data:`RAY_CONNECT_TIMEOUT_S`."""
    if address == "local":
        return
    timeout_s = RAY_CONNECT_TIMEOUT_S if timeout_s is None else timeout_s
    code = "import ray, sys; ray.init(address=sys.argv[1], log_to_driver=False); ray.shutdown()"
    env = {**os.environ, "RAY_gcs_rpc_server_reconnect_timeout_s": str(int(timeout_s))}
    try:
        done = subprocess.run(
            [sys.executable, "-c", code, address],
            env=env,
            capture_output=True,
            timeout=timeout_s + 30,
        )
        ok = done.returncode == 0
    except subprocess.TimeoutExpired:
        ok = False
    if not ok:
        raise RayUnreachable(
            f"no Ray cluster answered at {address!r} within {timeout_s} s (RAY_ADDRESS or "
            "the address given): start one there (ray start --head) or leave the address "
            "unset to run a local instance"
        )


def ray_init_kwargs(address: str | None = None) -> dict[str, Any]:
    """``ray.init`` keywords: join ``address`` (else ``RAY_ADDRESS``) when one is given, else
    start a new local instance whose workers see this process's ``sys.path`` (so that they
    import the same code, e.g. a source checkout or an example folder)."""
    address = address or os.environ.get("RAY_ADDRESS") or None
    if address is not None:
        return {"address": address}
    path = os.pathsep.join(p for p in sys.path if p and os.path.isdir(p))
    return {
        "address": "local",
        "include_dashboard": False,
        "runtime_env": {"env_vars": {"PYTHONPATH": path}},
    }


RAY_AGENTS = ("ray::DashboardAgent", "ray::RuntimeEnvAgent")
"""Processes of a local Ray instance that outlive its driver after a kill -9 (for about a
minute: they notice their raylet's death but hang in a call to the dead GCS)."""

_REAPER = """
import os, signal, sys
targets = [line.split() for line in sys.argv[1:]]
sys.stdin.buffer.read()  # end of file: the driver exited, however it exited
for pid, start in targets:
    try:
        with open(f"/proc/{pid}/stat") as fh:
            fields = fh.read().rpartition(")")[2].split()
    except OSError:
        continue  # gone already
    if fields[19] == start:  # the same process, not a new one that got its pid
        os.kill(int(pid), signal.SIGKILL)
"""


def _proc_stat(pid: int) -> list[str] | None:
    """The fields of ``/proc/<pid>/stat`` after the command name (``[0]`` is the state,
    ``[1]`` the parent pid, ``[19]`` the start time), ``None`` when it cannot be read."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().rpartition(")")[2].split()
    except OSError:
        return None


def ray_agents_of_this_process() -> list[tuple[int, str]]:
    """``(pid, start time)`` of the :data:`RAY_AGENTS` whose parent (the raylet) is a child of
    this process: those of the local Ray instance it started. Empty without ``/proc``."""
    proc = Path("/proc")
    if not proc.is_dir():
        return []
    parents: dict[int, int] = {}
    for entry in proc.iterdir():
        stat = _proc_stat(int(entry.name)) if entry.name.isdigit() else None
        if stat is not None:
            parents[int(entry.name)] = int(stat[1])
    children = {pid for pid, parent in parents.items() if parent == os.getpid()}
    agents = []
    for pid, parent in parents.items():
        if parent not in children:
            continue
        try:
            name = (proc / str(pid) / "cmdline").read_bytes().split(b"\0")[0].decode()
        except (OSError, UnicodeDecodeError):
            continue
        stat = _proc_stat(pid)
        if stat is not None and name.strip() in RAY_AGENTS:
            agents.append((pid, stat[19]))
    return agents


def reap_ray_agents_on_exit() -> subprocess.Popen | None:
    """Start a reaper (its own session, so a signal to the driver's process group spares it)
    that waits for this process to exit, however it exits, and then SIGKILLs the
    :data:`RAY_AGENTS` of the local Ray instance this process started, if they still run
    (checked by pid and start time). Closing its ``stdin`` after ``ray.shutdown`` ends it.
    ``None`` where there are no such agents (no ``/proc``)."""
    agents = ray_agents_of_this_process()
    if not agents:
        return None
    return subprocess.Popen(
        [sys.executable, "-c", _REAPER, *(f"{pid} {start}" for pid, start in agents)],
        stdin=subprocess.PIPE,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        start_new_session=True,
    )
