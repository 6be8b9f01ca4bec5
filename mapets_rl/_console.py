"""Keep the console for our own output: silence known chatter of dependencies.

- torchrl logs INFO lines in ANSI colours on stdout for routine events (e.g. every replay-buffer
  storage it allocates); they are dropped unless ``RL_LOGGING_LEVEL`` is set, which is torchrl's
  own switch for its log level (warnings and errors always pass).
- torchrl's PettingZoo wrapper warns that it was tested with another PettingZoo version on every
  scenario env it builds; ``pyproject.toml`` pins the version our tests run with.

The project's own calls that trigger them drop them where they happen
(:func:`torchrl_info_dropped`, :func:`pettingzoo_version_warning_ignored`), so the Python API
prints neither and changes no global state; :func:`quiet_dependencies` drops them for the whole
process (the ``mapets-rl`` command and the example scripts call it).
"""

from __future__ import annotations

import contextlib
import logging
import os
import warnings
from collections.abc import Iterator

PETTINGZOO_VERSION_WARNING = r"PettingZoo in TorchRL is tested"
"""The start of torchrl's PettingZoo version warning (a regular expression)."""


class _WarningsAndAbove(logging.Filter):
    """Passes records of level WARNING and above."""

    def filter(self, record: logging.LogRecord) -> bool:
        return record.levelno >= logging.WARNING


_PROCESS_FILTER = _WarningsAndAbove()


@contextlib.contextmanager
def torchrl_info_dropped() -> Iterator[None]:
    """Drop torchrl's INFO records while the block runs (unless ``RL_LOGGING_LEVEL`` is set);
    the logger is as it was afterwards."""
    if "RL_LOGGING_LEVEL" in os.environ:
        yield
        return
    logger = logging.getLogger("torchrl")
    drop = _WarningsAndAbove()
    logger.addFilter(drop)
    try:
        yield
    finally:
        logger.removeFilter(drop)


@contextlib.contextmanager
def pettingzoo_version_warning_ignored() -> Iterator[None]:
    """Ignore torchrl's PettingZoo version warning while the block runs (the warning filters
    are as they were afterwards)."""
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=PETTINGZOO_VERSION_WARNING, category=UserWarning)
        yield


def quiet_dependencies() -> None:
    """Drop the chatter described in the module docstring for the whole process
    (idempotent)."""
    warnings.filterwarnings("ignore", message=PETTINGZOO_VERSION_WARNING, category=UserWarning)
    if "RL_LOGGING_LEVEL" not in os.environ:
        logging.getLogger("torchrl").addFilter(_PROCESS_FILTER)
