"""Atomic, self-verifying, safe-to-load checkpoints of a whole training state.

A checkpoint is a nested dict of tensors and plain Python values (str, int, float, bool, None,
lists, tuples, dicts). :func:`atomic_torch_save` writes it with ``torch.save`` to a temp file in
the checkpoint directory, fsyncs it, writes the file's SHA-256 digest beside it
(``ckpt_<frames>.pt.sha256``, in ``sha256sum`` format), and only then renames the temp file over
the checkpoint's name: a crash mid-write never leaves a truncated file under a checkpoint name,
and every checkpoint that appears has its digest already in place.

:func:`load_checkpoint` verifies the digest before it parses anything and then loads with
``torch.load(weights_only=True)``, so a corrupted, truncated or modified file is refused and a
checkpoint file cannot execute code (a checkpoint of an older version, which has no digest file,
is loaded with a warning; a file without a digest that is not even an archive ``torch.save``
writes is refused). Every refusal is a :class:`CheckpointError` whose one-line message names the
file.

Checkpoints are ranked by what verifies, not by their names alone: :func:`latest_checkpoint` is
the newest checkpoint that verifies, :func:`load_latest_checkpoint` falls back to the newest
checkpoint that verifies and loads, logging one line per file it skipped, and the pruning of
:func:`save_checkpoint` keeps the newest ``keep_last`` checkpoints that verify (a file that does
not, e.g. a stray ``ckpt_999999999999.pt``, is reported in one warning and left alone; it never
counts as one of the kept checkpoints).

RNG states of python, numpy and torch are stored as tensors (:func:`rng_state`).
"""

from __future__ import annotations

import hashlib
import io
import logging
import os
import pickle
import random
import re
import zipfile
from pathlib import Path
from typing import Any

import numpy as np
import torch

from mapets_rl.experiment.files import atomic_write, atomic_write_text, check_run_subdirs

CHECKPOINT_DIR = "checkpoints"
DIGEST_SUFFIX = ".sha256"
_NAME = re.compile(r"^ckpt_(\d+)\.pt$")
_DIGEST_LINE = re.compile(r"^([0-9a-f]{64})  (\S+)\n?$")
_TEMP_NAME = re.compile(r"^\..+\.[a-z0-9_]{8}\.tmp(\.[^.]+)?$")
"""Temp files of :func:`~mapets_rl.experiment.files.atomic_write` (``.<name>.<random>.tmp<ext>``)
and of older checkpoint writes (``.ckpt_<frames>.pt.<random>.tmp``)."""

logger = logging.getLogger(__name__)

_VERIFIED: dict[tuple, str | None] = {}
"""What :func:`checkpoint_problem` found, keyed by the checkpoint's and its digest file's
(path, inode, size, mtime): a file is hashed again only when it changed."""
_VERIFIED_MAX = 1024
_REPORTED: set[tuple | None] = set()
"""Keys (as in ``_VERIFIED``) of the files that pruning has reported as not verifying."""


class CheckpointError(ValueError):
    """A checkpoint file is missing, corrupted, modified or not one this library wrote."""


def rng_state() -> dict[str, Any]:
    """Python, numpy and torch (CPU and CUDA when available) RNG states as tensors."""
    version, mt, gauss = random.getstate()
    np_name, np_keys, np_pos, np_has_gauss, np_gauss = np.random.get_state()
    state: dict[str, Any] = {
        "python": {
            "version": version,
            "state": torch.tensor(mt, dtype=torch.int64),
            "gauss": gauss,
        },
        "numpy": {
            "name": np_name,
            "keys": torch.from_numpy(np_keys.astype(np.int64)),
            "pos": int(np_pos),
            "has_gauss": int(np_has_gauss),
            "cached_gaussian": float(np_gauss),
        },
        "torch": torch.get_rng_state(),
    }
    if torch.cuda.is_available():
        state["cuda"] = torch.cuda.get_rng_state_all()
    return state


def set_rng_state(state: dict[str, Any]) -> None:
    """Restore what :func:`rng_state` returned (its tensors on any device: a checkpoint
    loaded with ``map_location="cuda"`` holds them on the GPU; generators take CPU states)."""
    py = state["python"]
    random.setstate((py["version"], tuple(int(x) for x in py["state"].tolist()), py["gauss"]))
    npy = state["numpy"]
    np.random.set_state(
        (
            npy["name"],
            npy["keys"].cpu().numpy().astype(np.uint32),
            npy["pos"],
            npy["has_gauss"],
            npy["cached_gaussian"],
        )
    )
    torch.set_rng_state(state["torch"].cpu())
    if "cuda" in state and torch.cuda.is_available():
        torch.cuda.set_rng_state_all([s.cpu() for s in state["cuda"]])


def seed_everything(seed: int) -> None:
    """Seed python, numpy and torch RNGs."""
    if seed < 0:
        raise ValueError(f"seed must be >= 0, got {seed}")
    random.seed(seed)
    np.random.seed(seed % 2**32)
    torch.manual_seed(seed)


def digest_path(path: str | os.PathLike) -> Path:
    """Where the SHA-256 digest of checkpoint ``path`` lives: ``<path>.sha256``."""
    path = Path(path)
    return path.with_name(path.name + DIGEST_SUFFIX)


def file_sha256(path: str | os.PathLike) -> str:
    """Hex SHA-256 digest of the file at ``path``."""
    digest = hashlib.sha256()
    with open(path, "rb") as fh:
        for chunk in iter(lambda: fh.read(1 << 20), b""):
            digest.update(chunk)
    return digest.hexdigest()


def _fsync_dir(directory: Path) -> None:
    fd = os.open(directory, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def atomic_torch_save(obj: Any, path: str | os.PathLike) -> Path:
    """``torch.save(obj)`` to ``path`` atomically, with its digest written first.

    Order: temp file (``torch.save`` to memory, written, fsync) -> ``<path>.sha256`` (atomic)
    -> rename of the temp file to ``path`` -> fsync of the directory. Files get the
    permissions of any other file the run writes (see
    :func:`~mapets_rl.experiment.files.atomic_write`). A write that fails (disk full, file
    size limit) raises :class:`~mapets_rl.experiment.files.WriteFailed`
    naming the file and leaves ``path``, its digest and every other checkpoint as they were.
    """
    path = Path(path)

    def write(tmp: str) -> None:
        with open(tmp, "wb") as fh:
            # serialised in memory first: a write that fails (disk full, file size limit) is
            # then an OSError of a plain file write (WriteFailed naming the file), not torch's
            # archive writer's "unexpected pos" RuntimeError
            buffer = io.BytesIO()
            torch.save(obj, buffer)
            fh.write(buffer.getbuffer())
            fh.flush()
            os.fsync(fh.fileno())
        atomic_write_text(digest_path(path), f"{file_sha256(tmp)}  {path.name}\n")

    atomic_write(path, write)
    _fsync_dir(path.parent)
    key = _verification_key(path)
    if key is not None:  # written and digested just now: it verifies
        _remember(key, None)
    return path


def list_checkpoints(run_dir: str | os.PathLike) -> list[Path]:
    """Files named like checkpoints (``ckpt_<frames>.pt``) in ``run_dir``, oldest first by the
    step in their names, whether they verify or not (temp and digest files are ignored; see
    :func:`verified_checkpoints` for the ones that verify)."""
    ckpt_dir = Path(run_dir) / CHECKPOINT_DIR
    if not ckpt_dir.is_dir():
        return []
    found = [(int(m.group(1)), p) for p in ckpt_dir.iterdir() if (m := _NAME.match(p.name))]
    return [p for _, p in sorted(found)]


def checkpoint_frames(path: str | os.PathLike) -> int:
    """The frames a checkpoint was saved at, read from its name (``ckpt_<frames>.pt``) without
    opening the file; ValueError naming a file that is not named like a checkpoint."""
    match = _NAME.match(Path(path).name)
    if match is None:
        raise ValueError(f"{str(path)!r} is not named like a checkpoint (ckpt_<frames>.pt)")
    return int(match.group(1))


def verified_checkpoints(run_dir: str | os.PathLike) -> list[Path]:
    """The checkpoints of ``run_dir`` that verify (see :func:`checkpoint_problem`), oldest
    first; files that do not are left out silently."""
    return [p for p in list_checkpoints(run_dir) if checkpoint_problem(p) is None]


def latest_checkpoint(run_dir: str | os.PathLike) -> Path | None:
    """The newest checkpoint of ``run_dir`` that verifies (see :func:`checkpoint_problem`),
    ``None`` if there is none. Newer files that do not verify are passed over silently
    (:func:`load_latest_checkpoint` reports them)."""
    for path in reversed(list_checkpoints(run_dir)):
        if checkpoint_problem(path) is None:
            return path
    return None


def checkpoint_problem(path: str | os.PathLike) -> str | None:
    """What is wrong with checkpoint file ``path``, in one line naming it, or ``None`` when it
    verifies: its digest file matches it, or (a checkpoint written before checkpoints carried
    digests) it has no digest file but is an archive ``torch.save`` writes.

    The file is not unpickled (that is :func:`load_checkpoint`'s business), and the answer is
    remembered until the file or its digest file changes, so asking again costs no hashing.
    """
    path = Path(path)
    key = _verification_key(path)
    if key is not None and key in _VERIFIED:
        return _VERIFIED[key]
    try:
        problem = None if verify_checkpoint(path) or _is_torch_archive(path) else _not_torch(path)
    except CheckpointError as err:
        problem = str(err)
    if key is not None:
        _remember(key, problem)
    return problem


def _verification_key(path: Path) -> tuple | None:
    """(path, inode, size, mtime) of ``path`` and of its digest file (``None`` for a digest file
    that does not exist); ``None`` when ``path`` cannot be stat-ed."""

    def identity(p: Path) -> tuple[int, int, int] | None:
        try:
            st = p.stat()
        except OSError:
            return None
        return st.st_ino, st.st_size, st.st_mtime_ns

    own = identity(path)
    return None if own is None else (str(path), own, identity(digest_path(path)))


def _remember(key: tuple, problem: str | None) -> None:
    if len(_VERIFIED) >= _VERIFIED_MAX:
        _VERIFIED.clear()
    _VERIFIED[key] = problem


def _is_torch_archive(path: Path) -> bool:
    """Whether ``path`` is a zip archive holding the ``data.pkl`` record ``torch.save``
    writes (reads the archive's directory only)."""
    try:
        with zipfile.ZipFile(path) as archive:
            return any(
                name == "data.pkl" or name.endswith("/data.pkl") for name in archive.namelist()
            )
    except (OSError, zipfile.BadZipFile, ValueError):
        return False


def _not_torch(path: Path) -> str:
    """The one-line problem of a file without digest that ``torch.save`` did not write."""
    return (
        f"checkpoint {str(path)!r} has no digest file {digest_path(path).name} and is not an "
        "archive torch.save writes (not a checkpoint this library wrote)"
    )


def save_checkpoint(
    state: dict[str, Any], run_dir: str | os.PathLike, step: int, keep_last: int = 2
) -> Path:
    """Write ``state`` as ``run_dir/checkpoints/ckpt_<step>.pt`` (+ digest) atomically; keep the
    newest ``keep_last`` checkpoints that verify and delete older ones (only after the new one
    is in place). A ``checkpoints/`` that is a symbolic link is refused (ValueError): pruning
    never deletes outside ``run_dir``.

    A file named like a checkpoint that does not verify (:func:`checkpoint_problem`) is not
    counted among the kept ones and is not deleted: it is reported in one logged warning
    (once per process while it stays the same) and left for its owner to inspect.
    """
    if step < 0:
        raise ValueError(f"step must be >= 0, got {step}")
    if keep_last < 1:
        raise ValueError(f"keep_last must be >= 1, got {keep_last}")
    check_run_subdirs(run_dir, (CHECKPOINT_DIR,))
    path = atomic_torch_save(state, Path(run_dir) / CHECKPOINT_DIR / f"ckpt_{step:012d}.pt")
    verified = []
    for candidate in list_checkpoints(run_dir):
        problem = checkpoint_problem(candidate)
        if problem is None:
            verified.append(candidate)
            continue
        key = _verification_key(candidate)
        if key not in _REPORTED:
            if len(_REPORTED) >= _VERIFIED_MAX:
                _REPORTED.clear()
            _REPORTED.add(key)
            logger.warning("%s; not counted as a checkpoint to keep, left in place", problem)
    for old in verified[:-keep_last]:
        old.unlink(missing_ok=True)
        digest_path(old).unlink(missing_ok=True)
    return path


def verify_checkpoint(path: str | os.PathLike) -> bool:
    """Check ``path`` against the digest in ``<path>.sha256``.

    Returns:
        True when the digest matches; False when there is no digest file (a checkpoint written
        before checkpoints carried digests: it cannot be verified).

    Raises:
        CheckpointError: the file is missing, the digest file is malformed, or the file does not
            match its digest.
    """
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"checkpoint {str(path)!r} does not exist")
    digest_file = digest_path(path)
    if not digest_file.exists():
        return False
    try:
        match = _DIGEST_LINE.match(digest_file.read_text())
    except (OSError, UnicodeDecodeError):
        match = None
    if match is None or match.group(2) != path.name:
        raise CheckpointError(
            f"digest file {str(digest_file)!r} does not hold the SHA-256 digest of {path.name}"
        )
    if file_sha256(path) != match.group(1):
        raise CheckpointError(
            f"checkpoint {str(path)!r} does not match its SHA-256 digest (the "
            "file is corrupted or was modified)"
        )
    return True


def load_checkpoint(path: str | os.PathLike, map_location: str | torch.device = "cpu") -> dict:
    """Verify ``path`` against its digest, then load it with ``torch.load(weights_only=True)``.

    A checkpoint without a digest file (written by an older version) is loaded with a logged
    warning; weights-only loading still refuses anything but tensors and plain values.

    Raises:
        CheckpointError: one line naming the file: missing, digest mismatch or malformed
            digest file, unreadable, or holding pickled objects other than tensors and plain
            values (such a file is never unpickled).
    """
    path = Path(path)
    if not verify_checkpoint(path):
        if not _is_torch_archive(path):
            raise CheckpointError(_not_torch(path))
        logger.warning(
            "checkpoint %r has no digest file %s (written before checkpoints carried "
            "digests); loading it without an integrity check",
            str(path),
            digest_path(path).name,
        )
    try:
        state = torch.load(path, map_location=map_location, weights_only=True)
    except pickle.UnpicklingError:
        raise CheckpointError(
            f"{str(path)!r} is not a checkpoint this library wrote (it holds pickled Python "
            "objects, not only tensors and plain values) and will not be loaded"
        ) from None
    except Exception as err:  # noqa: BLE001 - torch raises many types for unreadable files
        raise CheckpointError(
            f"checkpoint {str(path)!r} cannot be read: {first_line(err)}"
        ) from None
    if not isinstance(state, dict):
        raise CheckpointError(
            f"checkpoint {str(path)!r} does not hold a state dict (got {type(state).__name__})"
        )
    return state


def load_latest_checkpoint(
    run_dir: str | os.PathLike, map_location: str | torch.device = "cpu"
) -> tuple[Path, dict]:
    """The newest checkpoint of ``run_dir`` that verifies and loads, and its state.

    Each newer file named like a checkpoint that fails (does not verify, see
    :func:`checkpoint_problem`, or does not load) is skipped with one logged warning naming the
    file and the reason.

    Raises:
        CheckpointError: when ``run_dir`` has no checkpoint, or none of them verifies.
    """
    candidates = list_checkpoints(run_dir)
    if not candidates:
        raise CheckpointError(f"run_dir {str(run_dir)!r} has no checkpoint to load")
    for path in reversed(candidates):
        try:
            return path, load_checkpoint(path, map_location)
        except CheckpointError as err:
            logger.warning("%s; skipped", err)
    raise CheckpointError(
        f"none of the {len(candidates)} checkpoints of {str(run_dir)!r} "
        "verifies (see the warnings above); the run cannot be restored"
    )


def remove_stale_files(run_dir: str | os.PathLike) -> list[Path]:
    """Delete what interrupted writes left in ``run_dir``: temp files of atomic writes (in the
    run dir, ``checkpoints/`` and ``videos/``) and digest files whose checkpoint is gone.

    Call it only when no other process writes to ``run_dir``. Returns the removed paths.
    A ``checkpoints/`` or ``videos/`` that is a symbolic link is refused (ValueError): nothing
    outside ``run_dir`` is deleted.
    """
    run_dir = Path(run_dir)
    check_run_subdirs(run_dir, (CHECKPOINT_DIR, "videos"))
    ckpt_dir = run_dir / CHECKPOINT_DIR
    stale = [
        path
        for directory in (run_dir, ckpt_dir, run_dir / "videos")
        if directory.is_dir()
        for path in directory.iterdir()
        if path.is_file() and _TEMP_NAME.match(path.name)
    ]
    if ckpt_dir.is_dir():
        stale += [
            path
            for path in ckpt_dir.glob(f"ckpt_*.pt{DIGEST_SUFFIX}")
            if not path.with_name(path.name.removesuffix(DIGEST_SUFFIX)).exists()
        ]
    for path in stale:
        path.unlink(missing_ok=True)
    return stale


def first_line(err: BaseException) -> str:
    """The first non-empty line of ``str(err)`` (or the exception's type name)."""
    lines = [line.strip() for line in str(err).splitlines() if line.strip()]
    return lines[0] if lines else type(err).__name__
