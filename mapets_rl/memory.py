"""How much memory a device can still allocate, and the refusal of what cannot fit.

On a CPU the bound is the smallest of what the machine and the limits on this process leave:
the host's ``MemAvailable`` (``/proc/meminfo``), the address-space limit ``RLIMIT_AS``
(``ulimit -v``) less what the process already maps (``VmSize``), and the memory limit less the
usage of the process's own cgroup and of every cgroup above it (v2 ``memory.max``, v1
``memory.limit_in_bytes``; the cgroup named in ``/proc/self/cgroup``, e.g. a Slurm job's or a
container's without a cgroup namespace): a container's limit or a ``ulimit -v`` is then a
one-line refusal, not an allocator traceback or the OOM killer; a cgroup at its limit leaves
nothing. On a CUDA device it is CUDA's free memory.
"""

from __future__ import annotations

import resource
from pathlib import Path

import torch

__all__ = ["available_memory", "check_memory"]

_CGROUP = Path("/sys/fs/cgroup")
_PROC_CGROUP = Path("/proc/self/cgroup")


def _read_int(path: Path) -> int | None:
    """The integer a one-line file holds, ``None`` when it is absent, ``max`` or unreadable."""
    try:
        text = path.read_text().strip()
    except OSError:
        return None
    return int(text) if text.isdigit() else None


def _meminfo(field: str, path: str = "/proc/meminfo") -> int | None:
    """``field`` of a ``/proc`` status file in bytes (its values are kB), ``None`` if absent."""
    try:
        with open(path) as fh:
            for line in fh:
                if line.startswith(f"{field}:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        return None
    return None


def _address_space_left() -> int | None:
    """``RLIMIT_AS`` less the process's mapped size, ``None`` without a limit."""
    soft, _ = resource.getrlimit(resource.RLIMIT_AS)
    if soft == resource.RLIM_INFINITY:
        return None
    mapped = _meminfo("VmSize", "/proc/self/status") or 0
    return max(soft - mapped, 0)


def _stat_field(path: Path, key: str) -> int | None:
    """The value of ``key`` in a cgroup's ``memory.stat`` (``key value`` lines), ``None`` when
    the file or the key is absent."""
    try:
        lines = path.read_text().splitlines()
    except OSError:
        return None
    for line in lines:
        name, _, value = line.partition(" ")
        if name == key and value.strip().isdigit():
            return int(value)
    return None


def _own_cgroups(proc: Path, v1: bool) -> list[Path]:
    """The path of this process's cgroup (v2: the ``0::`` line of ``proc``; ``v1``: the line of
    the ``memory`` controller) and of every cgroup above it, the root last; ``[/]`` when
    ``proc`` names none."""
    try:
        lines = proc.read_text().splitlines()
    except OSError:
        lines = []
    for line in lines:
        _, controllers, path = (line.split(":", 2) + ["", ""])[:3]
        if (v1 and "memory" in controllers.split(",")) or (not v1 and line.startswith("0::")):
            own = Path("/", path.strip() or "/")
            return [own, *own.parents]
    return [Path("/")]


def _cgroup_left(root: Path = _CGROUP, proc: Path = _PROC_CGROUP) -> int | None:
    """The smallest memory limit less usage among this process's cgroup and the cgroups above
    it (read from ``proc``; v2 under ``root``, else v1 under ``root/memory``), ``None`` without
    a limit. The usage leaves out the inactive page cache (``memory.stat``), which the kernel
    reclaims before it runs out. A cgroup of ``proc`` that ``root`` does not hold (another
    cgroup namespace) is skipped: the root's limit still counts."""
    for v1, limit_file, usage_file, cache_key in (
        (False, "memory.max", "memory.current", "inactive_file"),
        (True, "memory.limit_in_bytes", "memory.usage_in_bytes", "total_inactive_file"),
    ):
        base = root / "memory" if v1 else root
        left = []
        for cgroup in _own_cgroups(proc, v1):
            directory = base / cgroup.relative_to("/")
            limit = _read_int(directory / limit_file)
            if limit is not None and limit < 1 << 60:  # v1 writes a huge number for "no limit"
                usage = _read_int(directory / usage_file) or 0
                # the inactive page cache counts as usage but is given back on demand
                cache = _stat_field(directory / "memory.stat", cache_key) or 0
                left.append(max(limit - max(usage - cache, 0), 0))
        if left:
            return min(left)
    return None


def available_memory(device: torch.device | str = "cpu") -> int | None:
    """Bytes the device can still allocate (see the module docstring); ``None`` where nothing
    can be read (a device that is neither the CPU nor CUDA)."""
    device = torch.device(device)
    if device.type == "cuda":
        return int(torch.cuda.mem_get_info(device)[0])
    if device.type != "cpu":
        return None
    bounds = (_meminfo("MemAvailable"), _address_space_left(), _cgroup_left())
    known = [b for b in bounds if b is not None]  # 0 (a cgroup at its limit) counts
    return min(known) if known else None


def check_memory(need: int, device: torch.device | str, what: str, fix: str) -> None:
    """ValueError (one line) when ``need`` bytes of ``what`` exceed :func:`available_memory`
    of ``device``; ``fix`` says which settings to lower."""
    free = available_memory(device)
    if free is not None and need > free:
        raise ValueError(
            f"{what} need about {need / 2**30:.1f} GiB on {device}, more than the "
            f"{free / 2**30:.1f} GiB available: {fix}"
        )
