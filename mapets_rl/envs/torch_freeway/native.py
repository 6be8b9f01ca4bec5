"""The fused CPU kernel of the batched freeway (``native_step.cpp``), built on first use.

On a CPU the simulation step is a few hundred small tensor operations per simulation step,
mostly gathers over ``[B, N]`` tensors; their dispatch and memory traffic dominate, and
``torch.compile`` does not fuse the gathers well. ``native_step.cpp`` computes the same policy
step as :meth:`~mapets_rl.envs.torch_freeway.physics.RoadPhysics.substep` (repeated for the
simulation steps, with their bookkeeping) in one loop per road, vehicle by vehicle in
highway-env's order. It is compiled with ``torch.utils.cpp_extension`` (a C++ compiler and
``ninja`` are needed) into a private build directory (:func:`build_directory`; a shared one
would let another user plant the module that every run loads). A process about to build it
logs one warning saying so and how long it may take (35 s to 6 minutes on a loaded machine; the
``mapets-rl`` command prints it); where it cannot be built, :func:`load_kernel` logs one warning
saying why and that the simulator runs its torch program instead.
"""

from __future__ import annotations

import fcntl
import logging
import os
import time
from collections.abc import Callable
from pathlib import Path
from types import ModuleType

import torch

from mapets_rl._compile_cache import cache_dir_problem, private_default

log = logging.getLogger(__name__)

SOURCE = Path(__file__).with_name("native_step.cpp")
NAME = "mapets_rl_freeway_step"
"""The module's name, and the stem of the shared library built in :func:`build_directory`."""
_KERNEL: ModuleType | None = None
_FAILURE: str | None = None


def build_directory() -> Path:
    """The private directory the kernel is built in: ``torch_extensions/<torch version>`` beside
    torch.compile's private cache (``$XDG_CACHE_HOME/mapets_rl``, ``~/.cache/mapets_rl``),
    created with mode 0700 and checked as that cache is (:mod:`mapets_rl._compile_cache`)."""
    root = private_default(os.environ).parent
    path = root / "torch_extensions" / torch.__version__.replace("+", "_")
    path.mkdir(mode=0o700, parents=True, exist_ok=True)
    problem = cache_dir_problem(path)
    if problem is not None:
        raise OSError(f"the kernel's build directory {path} {problem}")
    return path


TORCH_BATON = "lock"
"""The file torch's ``cpp_extension.load`` creates in the build directory while it builds and
deletes when done; other processes wait for it to go away, for ever if its builder was killed."""


def build_exclusively(directory: Path, build: Callable[[], ModuleType]) -> ModuleType:
    """``build()`` while holding an exclusive ``flock`` on ``directory/build.flock``.

    The operating system releases a ``flock`` when its holder dies, so a build killed half way
    (Ctrl-C, ``kill -9``, a job's time limit) does not leave the next process waiting. Every
    build of this kernel takes this lock first, so torch's own lock file (:data:`TORCH_BATON`)
    found while holding it was left by a killed build, and is removed before building."""
    with open(directory / "build.flock", "a", encoding="utf-8") as handle:
        fcntl.flock(handle, fcntl.LOCK_EX)
        try:
            (directory / TORCH_BATON).unlink(missing_ok=True)
            return build()
        finally:
            fcntl.flock(handle, fcntl.LOCK_UN)


def needs_build(directory: Path) -> bool:
    """Whether loading the kernel from ``directory`` compiles it: no shared library there, one
    older than :data:`SOURCE`, or one built from another checkout's source (torch's build
    file names the source it compiles)."""
    library = directory / f"{NAME}.so"
    ninja = directory / "build.ninja"
    if not library.is_file() or not ninja.is_file():
        return True
    built_from_here = str(SOURCE) in ninja.read_text(encoding="utf-8", errors="replace")
    return not built_from_here or library.stat().st_mtime < SOURCE.stat().st_mtime


def load_kernel() -> ModuleType | None:
    """The compiled kernel module, or None (and :func:`kernel_unavailable` says why) where it
    cannot be built (a warning says why). Loaded once per process; the first process of a
    machine, torch version and checkout builds it (35 s to 6 minutes, announced by a warning)
    and later ones load the cached build."""
    global _KERNEL, _FAILURE
    if _KERNEL is not None or _FAILURE is not None:
        return _KERNEL
    try:
        from torch.utils.cpp_extension import load

        directory = build_directory()
        building = needs_build(directory)
        if building:
            log.warning(
                "building the batched freeway's C++ step kernel (%s, into %s): once per machine, "
                "torch version and checkout, 35 s to 6 minutes on a loaded machine",
                SOURCE.name,
                directory,
            )
        start = time.perf_counter()
        _KERNEL = build_exclusively(
            directory,
            lambda: load(
                name=NAME,
                sources=[str(SOURCE)],
                extra_cflags=["-O3", "-fno-math-errno"],
                build_directory=str(directory),
                verbose=False,
            ),
        )
    except Exception as err:  # noqa: BLE001 - no compiler, no ninja, unsafe directory...
        root = err
        while root.__cause__ is not None:
            root = root.__cause__
        _FAILURE = f"{type(root).__name__}: {root}".splitlines()[0]
        log.warning(
            "the batched freeway's C++ step kernel is unavailable (%s); its roads run the torch "
            "program instead (4-5x slower on CPUs)",
            _FAILURE,
        )
        return None
    if building:
        log.info("the freeway's C++ step kernel built in %.0f s", time.perf_counter() - start)
    return _KERNEL


def kernel_unavailable() -> str | None:
    """Why the kernel could not be built (one line), or None when it was (or was not tried)."""
    return _FAILURE
