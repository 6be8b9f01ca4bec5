"""Files a run writes: directories checked before anything is created, atomic writes.

Every file a run saves (config, results, checkpoints, plots) is written to a temp file in the
same directory and renamed over its final name, so a crash never leaves a half-written file.
"""

from __future__ import annotations

import os
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

__all__ = [
    "atomic_savefig",
    "atomic_write",
    "atomic_write_text",
    "check_writable_dir",
    "make_writable_dir",
]


def check_writable_dir(path: str | os.PathLike, what: str = "run_dir") -> None:
    """ValueError (one line naming ``what``) unless ``path`` is, or can be created as, a
    directory this process can write to. Creates nothing."""
    path = Path(path)
    probe = path
    while not probe.exists() and probe.parent != probe:
        probe = probe.parent
    if not probe.is_dir():
        raise ValueError(
            f"{what} {str(path)!r} cannot be created: {str(probe)!r} is not a directory"
        )
    if not os.access(probe, os.W_OK | os.X_OK):
        raise ValueError(
            f"{what} {str(path)!r} cannot be written: {str(probe)!r} is not "
            "writable (permission denied or a read-only file system)"
        )


def make_writable_dir(path: str | os.PathLike, what: str = "run_dir") -> Path:
    """Create directory ``path`` (and parents) and prove it writable with a probe file;
    ValueError (one line naming ``what``) otherwise."""
    path = Path(path)
    check_writable_dir(path, what)
    try:
        path.mkdir(parents=True, exist_ok=True)
        fd, probe = tempfile.mkstemp(dir=path, prefix=".write-probe.", suffix=".tmp")
        os.close(fd)
        os.unlink(probe)
    except OSError as err:
        raise ValueError(
            f"{what} {str(path)!r} cannot be written: {err.strerror or type(err).__name__}"
        ) from None
    return path


def atomic_write(path: str | os.PathLike, write: Callable[[str], None]) -> None:
    """Create ``path`` by ``write(tmp)`` on a temp file in the same directory + ``os.replace``.

    The temp file, ``.<name>.<random>.tmp<suffix>``, keeps ``path``'s suffix (so writers that
    infer a format from it work) and gets the permissions of a normally created file
    (``mkstemp`` makes it private): every file a run writes, checkpoints included, is created
    ``0666 & ~umask``. It is removed if ``write`` fails, and ``path`` is then left as it was; a
    process killed mid-write leaves it behind for
    :func:`~mapets_rl.experiment.checkpoint.remove_stale_files`.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(
        dir=path.parent, prefix=f".{path.name}.", suffix=f".tmp{path.suffix}"
    )
    os.close(fd)
    umask = os.umask(0)
    os.umask(umask)
    try:
        os.chmod(tmp, 0o666 & ~umask)
        write(tmp)
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def atomic_write_text(path: str | os.PathLike, text: str) -> None:
    """Write ``text`` to ``path`` atomically (see :func:`atomic_write`), fsynced."""

    def write(tmp: str) -> None:
        with open(tmp, "w") as fh:
            fh.write(text)
            fh.flush()
            os.fsync(fh.fileno())

    atomic_write(path, write)


def atomic_savefig(fig: Any, path: str | os.PathLike, **savefig_kwargs: Any) -> None:
    """Save the matplotlib figure ``fig`` to ``path`` atomically (see :func:`atomic_write`)."""
    atomic_write(path, lambda tmp: fig.savefig(tmp, **savefig_kwargs))
