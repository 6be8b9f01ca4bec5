"""torch.compile's on-disk cache: a directory of this user's own that only they can write,
decided before torch is imported.

Inductor, the compiler behind ``torch.compile``, keeps generated code and pickled compiled
graphs on disk and loads them again in later processes. Its default place is
``$TMPDIR/torchinductor_<user>``, created with no check of owner or mode: on a shared machine
another user who creates that directory first (or plants a file in it) has their code run by
every compiled MA-PETS planner. Its precompiled C++ headers go there too, whatever
``TORCHINDUCTOR_CACHE_DIR`` says.

:func:`prepare_compile_cache` chooses the cache instead:

- ``TORCHINDUCTOR_CACHE_DIR`` set by the user: that directory (created with mode 0700 if it
  does not exist). Inductor's own default, which it writes into the variable when torch is
  imported first, counts as unset;
- otherwise ``$XDG_CACHE_HOME/mapets_rl/torchinductor`` (``~/.cache/mapets_rl/torchinductor``),
  created with mode 0700; where that cannot be used, a fresh private temporary directory of
  this process (``tempfile.mkdtemp``, removed at exit).

A directory is used only when it is a directory owned by this user that neither its group nor
others may write, below directories owned by this user or root that others may not write
(unless sticky, like ``/tmp``). A ``TORCHINDUCTOR_CACHE_DIR`` that fails this, is a file or
cannot be created is refused with one line naming the variable. Header precompilation is
switched off (``TORCHINDUCTOR_CPP_CACHE_PRECOMPILE_HEADERS=0`` unless the user set it), as its
directory cannot be moved out of the shared temporary directory.

Inductor reads both variables when torch is imported (``import torch._dynamo``, which tensordict
and torchrl do, already creates the cache directory), so the ``mapets-rl`` command calls
:func:`prepare_compile_cache` first thing; :class:`~mapets_rl.planning.compiled.CompiledStep`
calls it again before it compiles (a process that imported torch first: the cache directory is
moved there, before anything is compiled).
"""

from __future__ import annotations

import atexit
import getpass
import os
import re
import shutil
import stat
import tempfile
from collections.abc import MutableMapping
from pathlib import Path

CACHE_ENV = "TORCHINDUCTOR_CACHE_DIR"
"""Inductor's environment variable naming its cache directory."""
HEADERS_ENV = "TORCHINDUCTOR_CPP_CACHE_PRECOMPILE_HEADERS"
"""Inductor's switch for precompiled C++ headers (kept in the shared temporary directory)."""

_chosen: str | None = None
"""The directory :func:`prepare_compile_cache` chose itself (the user's choice left unset), so
that a later call keeps it."""

__all__ = ["CACHE_ENV", "HEADERS_ENV", "cache_dir_problem", "prepare_compile_cache"]


def _inductor_default() -> str:
    """Where inductor puts its cache when ``TORCHINDUCTOR_CACHE_DIR`` is unset (its
    ``default_cache_dir``): ``$TMPDIR/torchinductor_<user>``. Inductor writes this path into
    the variable itself when torch is imported first, so that value is not the user's choice."""
    try:
        user = getpass.getuser()
    except (KeyError, ModuleNotFoundError, OSError):
        user = f"uid_{os.getuid()}"
    user = re.sub(r'[\\/:*?"<>|]', "_", user)
    return os.path.join(tempfile.gettempdir(), f"torchinductor_{user}")


def private_default(environ: MutableMapping[str, str]) -> Path:
    """``$XDG_CACHE_HOME/mapets_rl/torchinductor`` (``~/.cache/...`` when it is unset)."""
    base = environ.get("XDG_CACHE_HOME", "").strip()
    if not base or not os.path.isabs(base):
        base = os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "mapets_rl" / "torchinductor"


def cache_dir_problem(path: str | os.PathLike) -> str | None:
    """Why directory ``path`` cannot hold compiled code that this process will load (one
    phrase), or ``None`` when it can: it must be a directory owned by this user that neither
    its group nor others may write, and every directory above it must be owned by this user
    or root and not writable by others unless sticky."""
    real = Path(os.path.realpath(path))
    uid = os.geteuid()
    try:
        st = os.stat(real)
    except OSError as err:
        return f"it cannot be read ({err.strerror or type(err).__name__})"
    if not stat.S_ISDIR(st.st_mode):
        return "it is not a directory"
    if st.st_uid != uid:
        return f"it is owned by another user (uid {st.st_uid}, this process runs as uid {uid})"
    if st.st_mode & (stat.S_IWGRP | stat.S_IWOTH):
        return f"others may write to it (mode {stat.S_IMODE(st.st_mode):04o}; use 0700)"
    for parent in real.parents:
        try:
            pst = os.stat(parent)
        except OSError as err:
            return f"{str(parent)!r} cannot be read ({err.strerror or type(err).__name__})"
        if pst.st_uid not in (0, uid):
            return f"{str(parent)!r} above it is owned by another user (uid {pst.st_uid})"
        writable = pst.st_mode & (stat.S_IWGRP | stat.S_IWOTH)
        if writable and not pst.st_mode & stat.S_ISVTX:
            return (
                f"{str(parent)!r} above it may be written by others "
                f"(mode {stat.S_IMODE(pst.st_mode):04o}, not sticky)"
            )
    return None


def make_private_dir(path: Path) -> str | None:
    """Create ``path`` (mode 0700, parents as usual) unless it exists; then
    :func:`cache_dir_problem` of it. Returns the problem, ``None`` when it is usable."""
    if not os.path.lexists(path):
        blocking = next((p for p in path.parents if os.path.lexists(p)), None)
        if blocking is not None and not os.path.isdir(blocking):
            return f"it cannot be created: {str(blocking)!r} above it is not a directory"
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
        except OSError as err:
            return f"it cannot be created ({err.strerror or type(err).__name__})"
        try:
            os.mkdir(path, 0o700)
        except FileExistsError:
            pass  # created meanwhile: checked below like any existing directory
        except OSError as err:
            return f"it cannot be created ({err.strerror or type(err).__name__})"
    elif not os.path.isdir(path):
        return "it is not a directory"
    return cache_dir_problem(path)


def _process_temp_dir() -> str:
    """A private (0700) temporary directory for this process's compiled code, removed at
    exit."""
    path = tempfile.mkdtemp(prefix="mapets_rl-torchinductor-")
    atexit.register(shutil.rmtree, path, ignore_errors=True)
    return path


def prepare_compile_cache(environ: MutableMapping[str, str] | None = None) -> str:
    """Choose torch.compile's cache directory (see the module docstring), put it in
    ``TORCHINDUCTOR_CACHE_DIR`` and switch header precompilation off unless the user set it.

    ``environ``: environment variables to read and update (default ``os.environ``). Returns
    the directory. Idempotent: a second call keeps the directory of the first (checked again).

    Raises:
        ValueError: the user's ``TORCHINDUCTOR_CACHE_DIR`` is a file, cannot be created, is
            owned by another user or may be written by others (one line naming it).
    """
    global _chosen
    environ = os.environ if environ is None else environ
    environ.setdefault(HEADERS_ENV, "0")
    value = environ.get(CACHE_ENV, "").strip()
    chosen_by_user = (
        bool(value) and value != _chosen and (os.path.abspath(value) != _inductor_default())
    )
    if chosen_by_user:
        path = Path(os.path.abspath(value))
        problem = make_private_dir(path)
        if problem is not None:
            raise ValueError(
                f"{CACHE_ENV}={value!r} cannot be torch.compile's cache: {problem}; point it "
                "at a directory of your own that only you may write (mode 0700), or unset it"
            )
        environ[CACHE_ENV] = str(path)
        return str(path)
    if value and value == _chosen and cache_dir_problem(value) is None:
        chosen = value
    else:
        default = private_default(environ)
        chosen = str(default) if make_private_dir(default) is None else _process_temp_dir()
        _chosen = chosen
    environ[CACHE_ENV] = chosen
    return chosen
