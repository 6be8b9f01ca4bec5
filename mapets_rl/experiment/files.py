"""Files a run writes: directories checked before anything is created, atomic writes, and the
lock that makes a process the only writer of a run directory.

Every file a run saves (config, results, checkpoints, plots) is written to a temp file in the
same directory and renamed over its final name, so a crash never leaves a half-written file.

A run (``train``, ``resume``, ``evaluate``) holds :class:`RunDirLock` on its run directory for
its whole life: an exclusive ``flock`` on ``RUN_DIR/.lock``, which the kernel drops when the
process ends however it ends (kill -9 included), so a lock is never left stale. A second writer
is refused with a :class:`RunDirLocked` error naming the pid of the holder before it writes
anything.

Nothing a run writes or deletes lies outside its run directory, even in a run directory that
came from elsewhere (downloaded, shared): ``.lock`` is opened without following a symbolic link
and must be a regular file of this user's own with no other name, and the directories a run
writes and prunes (``checkpoints/``, ``videos/``, ``logs/`` and everything below them) must not
be symbolic links (:func:`check_run_subdirs`). The logs a run appends to are opened the same
way (:func:`open_append`), and one that is a symbolic link is removed, never read or written
through, before a run cuts it back (:func:`read_own_file`).
"""

from __future__ import annotations

import errno
import fcntl
import logging
import os
import stat
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import Any, TextIO

log = logging.getLogger(__name__)

LOCK_FILE = ".lock"
"""Name of the lock file in a run directory (see :class:`RunDirLock`)."""
TRIAL_RECORD = "trial.json"
"""A sweep's record of the trial whose run directory holds it (written before the run)."""
ERROR_FILE = "error.txt"
"""A sweep's record of why the trial whose run directory holds it failed."""
OWN_FILES = (LOCK_FILE, TRIAL_RECORD, ERROR_FILE)
"""What a run directory of ours may hold before its ``run.json``: a new run in a directory
holding anything else is refused (another program's files would be overwritten)."""
RUN_SUBDIRS = ("checkpoints", "videos", "logs")
"""The directories a run writes and prunes below its run directory."""
_PID_WIDTH = 21
"""Bytes of the pid record at the start of ``.lock`` (the pid, padded with spaces, and a
newline): written in place, never truncated."""

__all__ = [
    "ERROR_FILE",
    "LOCK_FILE",
    "OWN_FILES",
    "RunDirLock",
    "RunDirLocked",
    "TRIAL_RECORD",
    "WriteFailed",
    "atomic_savefig",
    "atomic_write",
    "atomic_write_text",
    "check_run_subdirs",
    "check_writable_dir",
    "make_writable_dir",
    "open_append",
    "read_own_file",
    "write_failed",
]


class WriteFailed(ValueError, OSError):
    """A file of a run could not be written (disk full, file size limit, I/O error): one line
    naming the file and the reason. The file's previous version (an atomic write never
    replaces it with a partial one), and every earlier checkpoint, are left as they were.

    A ValueError (the CLI reports it as ``mapets-rl: error: ...``, exit status 2) and an
    OSError (with the errno of the failed write)."""

    def __str__(self) -> str:
        return str(self.args[0]) if self.args else "a file could not be written"


def write_failed(path: str | os.PathLike, err: OSError) -> WriteFailed:
    """The :class:`WriteFailed` of a write of ``path`` that raised ``err``."""
    if isinstance(err, WriteFailed):
        return err
    reason = err.strerror or str(err) or type(err).__name__
    if err.errno == errno.EFBIG:
        reason += " (the file size limit, ulimit -f, was reached)"
    failed = WriteFailed(f"cannot write {str(path)!r}: {reason}")
    failed.errno, failed.strerror, failed.filename = err.errno, err.strerror, str(path)
    return failed


def check_writable_dir(path: str | os.PathLike, what: str = "run_dir") -> None:
    """ValueError (one line naming ``what``) unless ``path`` is, or can be created as, a
    directory this process can write to. Creates nothing."""
    if not os.fspath(path):
        raise ValueError(f"{what} must be a non-empty path, got ''")
    path = Path(path)
    limit = os.pathconf(path.anchor or ".", "PC_NAME_MAX")
    too_long = [part for part in path.parts if len(os.fsencode(part)) > limit]
    if too_long:
        raise ValueError(
            f"{what} cannot be created: the name {too_long[0][:40]!r}... is "
            f"{len(os.fsencode(too_long[0]))} bytes, this file system allows {limit}"
        )
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
    check_writable_dir(path, what)
    path = Path(path)
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
    :func:`~mapets_rl.experiment.checkpoint.remove_stale_files`. A write that fails with an
    OSError (disk full, file size limit) raises :class:`WriteFailed` naming ``path``.
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
    except BaseException as err:
        if os.path.exists(tmp):
            os.unlink(tmp)
        if isinstance(err, OSError):
            raise write_failed(path, err) from None
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


def check_run_subdirs(run_dir: str | os.PathLike, names: tuple[str, ...] = RUN_SUBDIRS) -> None:
    """ValueError (one line naming it) when one of the directories ``names`` of ``run_dir``,
    or a directory anywhere below them, is a symbolic link, not a directory or another
    user's: a run writes, truncates and deletes files there, and must never do so outside
    its run directory or in another user's files."""
    run_dir = Path(run_dir)
    for name in names:
        top = run_dir / name
        if not os.path.lexists(top):
            continue
        problem = _subdir_problem(top)
        if problem is None:
            for parent, dirs, _ in os.walk(top):
                problem = next(
                    (p for p in (_subdir_problem(Path(parent, d)) for d in dirs) if p), None
                )
                if problem is not None:
                    break
        if problem is not None:
            raise ValueError(
                f"run_dir {str(run_dir)!r} cannot be used: {problem}; a run writes and deletes "
                "files there, and never outside its run directory (replace it with a plain "
                "directory of your own)"
            )


def _subdir_problem(path: Path) -> str | None:
    """Why directory ``path`` of a run directory cannot be written to (one phrase naming it),
    or ``None``."""
    st = os.lstat(path)
    if stat.S_ISLNK(st.st_mode):
        return f"{str(path)!r} is a symbolic link"
    if not stat.S_ISDIR(st.st_mode):
        return f"{str(path)!r} is not a directory"
    if st.st_uid != os.geteuid():
        return f"{str(path)!r} belongs to another user (uid {st.st_uid})"
    return None


def open_append(path: str | os.PathLike) -> TextIO:
    """``path`` opened for appending text (created ``0666 & ~umask`` when missing), without
    following a symbolic link: a run appends only to a regular file of its own with no other
    name, never to a file outside its run directory.

    Raises:
        WriteFailed: one line naming ``path`` when it is a symbolic link (dangling or not), not
            a regular file, another user's or has other names (a hard link; a run that cuts its
            logs back first replaces such a file, :func:`read_own_file`), or when it cannot be
            opened (permission denied, disk full).
    """
    flags = os.O_WRONLY | os.O_APPEND | os.O_CREAT | os.O_CLOEXEC | os.O_NOFOLLOW | os.O_NONBLOCK
    try:
        fd = os.open(path, flags, 0o666)
    except OSError as err:
        if err.errno not in (errno.ELOOP, errno.ENXIO):  # ENXIO: a FIFO nobody reads
            raise write_failed(path, err) from None
        problem = "is a symbolic link" if err.errno == errno.ELOOP else "is not a regular file"
    else:
        problem = _lock_file_problem(os.fstat(fd))
        if problem is None:
            return os.fdopen(fd, "a", encoding="utf-8")
        os.close(fd)
    raise WriteFailed(
        f"cannot append to {str(path)!r}: it {problem}; a run appends only to a regular file "
        "of its own inside its run directory (remove it)"
    )


def read_own_file(path: Path) -> tuple[str, bool] | None:
    """The text of ``path``, a file a run appends to, read back before the run cuts it: ``None``
    when there is none, when it is not a regular file (left for :func:`open_append` to refuse)
    or when it is a symbolic link, which is removed (dangling or not; its target is neither
    read nor written, and a warning names it). Else ``(text, own)``: ``own`` is false for a
    file that has other names (a hard link) or belongs to another user, which the caller must
    replace (an atomic rewrite makes a new file of its own) even when its text is kept."""
    try:
        st = os.lstat(path)
    except FileNotFoundError:
        return None
    if stat.S_ISLNK(st.st_mode):
        log.warning("removed %r: it was a symbolic link, not a file of the run", str(path))
        path.unlink()
        return None
    if not stat.S_ISREG(st.st_mode):
        return None
    try:
        fd = os.open(path, os.O_RDONLY | os.O_CLOEXEC | os.O_NOFOLLOW | os.O_NONBLOCK)
    except OSError as err:
        raise ValueError(
            f"cannot read {str(path)!r}: {err.strerror or type(err).__name__}"
        ) from None
    with os.fdopen(fd, encoding="utf-8", errors="replace") as fh:
        return fh.read(), _lock_file_problem(os.fstat(fh.fileno())) is None


class RunDirLocked(ValueError):
    """Another process (or another object of this process) holds the lock of a run
    directory."""


class RunDirLock:
    """Exclusive advisory lock on a run directory: ``flock(LOCK_EX)`` on ``RUN_DIR/.lock``.

    The lock belongs to the open file, so it conflicts with every other holder, another
    object of the same process included, and the kernel releases it when the file is closed:
    at :meth:`release`, when this object is garbage collected, or when the process dies (kill
    -9 included), so there is never a stale lock to clean up. The holder writes its pid into
    the file so that a refused writer can name it; the file itself stays (deleting it would let
    two processes lock two different files of the same name).

    Use :meth:`acquire`; ``with RunDirLock.acquire(run_dir): ...`` releases at the end.

    Why ``fcntl`` and not ``filelock`` (installed with torch; issue 52 asked): on Unix
    ``filelock.FileLock`` takes this same ``flock`` on a file it keeps, so it would add a layer,
    not a guarantee, and the lock needs what its API does not expose: the descriptor itself,
    opened with ``O_NOFOLLOW`` and checked before it is locked or written (a regular file of
    this user's own with one link: a ``.lock`` planted in a shared run directory must not make
    the pid record write into another file), and the holder's pid written into and read back
    from the locked file, so that a refused writer is told who holds the directory (a
    ``filelock.Timeout`` names only the path). The project runs on Linux and macOS (``flock``
    there); ``flock`` on NFS is emulated with ``fcntl`` byte-range locks by Linux >= 2.6.12, as
    for ``filelock``.
    """

    def __init__(self, run_dir: Path, fd: int) -> None:
        """Wraps ``fd``, an open descriptor of ``run_dir/.lock`` that is already locked; use
        :meth:`acquire`."""
        self.run_dir = run_dir
        self.path = run_dir / LOCK_FILE
        self._fd: int | None = fd

    @classmethod
    def acquire(cls, run_dir: str | os.PathLike, what: str = "run_dir") -> RunDirLock:
        """Lock the existing directory ``run_dir`` without waiting.

        Raises:
            RunDirLocked: another holder has it: one line naming ``run_dir`` and the holder's
                pid.
            ValueError: the lock file cannot be created or locked (one line naming ``what``).
        """
        run_dir = Path(run_dir)
        path = run_dir / LOCK_FILE
        umask = os.umask(0)
        os.umask(umask)
        flags = os.O_RDWR | os.O_CREAT | os.O_CLOEXEC | os.O_NOFOLLOW | os.O_NONBLOCK
        try:
            fd = os.open(path, flags, 0o666 & ~umask)
        except OSError as err:
            reason = (
                "it is a symbolic link"
                if err.errno == errno.ELOOP
                else err.strerror or type(err).__name__
            )
            raise ValueError(
                f"{what} {str(run_dir)!r} cannot be locked: {str(path)!r} cannot be "
                f"opened ({reason})"
            ) from None
        problem = _lock_file_problem(os.fstat(fd))
        if problem is not None:
            os.close(fd)
            raise ValueError(
                f"{what} {str(run_dir)!r} cannot be locked: {str(path)!r} {problem} (a run "
                "directory's lock must be a regular file of your own); remove it"
            )
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as err:
            holder = _read_pid(fd)
            os.close(fd)
            if err.errno not in (errno.EWOULDBLOCK, errno.EAGAIN, errno.EACCES):
                raise ValueError(
                    f"{what} {str(run_dir)!r} cannot be locked: "
                    f"{err.strerror or type(err).__name__}"
                ) from None
            who = "an unknown pid" if holder is None else f"pid {holder}"
            if holder == os.getpid():
                who += " (this process: another experiment on the same directory)"
            raise RunDirLocked(
                f"{what} {str(run_dir)!r} is in use by another writer ({who} holds "
                f"{LOCK_FILE}); wait for it to finish or choose another {what}"
            ) from None
        _write_pid(fd, str(os.getpid()))
        return cls(run_dir, fd)

    @property
    def held(self) -> bool:
        """Whether this object still holds the lock."""
        return self._fd is not None

    def release(self) -> None:
        """Drop the lock (idempotent): clear the pid and close the file."""
        fd, self._fd = self._fd, None
        if fd is None:
            return
        try:
            _write_pid(fd, "")
        finally:
            os.close(fd)  # closing the last descriptor of the open file unlocks it

    def __enter__(self) -> RunDirLock:
        return self

    def __exit__(self, *exc: object) -> None:
        self.release()

    def __del__(self) -> None:
        try:
            self.release()
        except Exception:  # noqa: BLE001 - nothing to report to at garbage collection
            pass

    def __repr__(self) -> str:
        state = "held" if self.held else "released"
        return f"{type(self).__name__}({str(self.run_dir)!r}, {state})"


def _lock_file_problem(st: os.stat_result) -> str | None:
    """What makes the opened ``.lock`` (or a log a run appends to, :func:`open_append`) with
    status ``st`` unfit to be written (one phrase), or ``None``: it must be a regular file of
    this user's own with no other name (a hard link to another file would let the pid record,
    or the appended rows, overwrite or grow that file)."""
    if not stat.S_ISREG(st.st_mode):
        return "is not a regular file"
    if st.st_uid != os.geteuid():
        return f"belongs to another user (uid {st.st_uid})"
    if st.st_nlink != 1:
        return f"has {st.st_nlink} names (a hard link to another file)"
    return None


def _write_pid(fd: int, pid: str) -> None:
    """Write ``pid`` (``""`` to clear it) as the fixed-width record at the start of the open
    lock file, in place: the file is never truncated."""
    try:
        os.pwrite(fd, f"{pid:<{_PID_WIDTH - 1}}\n".encode(), 0)
    except OSError:
        pass  # the pid is only informative: the lock is held either way


def _read_pid(fd: int) -> int | None:
    """The pid written in an open lock file, ``None`` when it holds none."""
    try:
        text = os.pread(fd, _PID_WIDTH, 0).decode("ascii", "replace").strip()
    except OSError:
        return None
    return int(text) if text.isdigit() else None
