"""Keep the console for our own output: silence known chatter of dependencies.

- torchrl logs INFO lines in ANSI colours for routine events (e.g. every replay-buffer storage
  it allocates); they are dropped unless ``RL_LOGGING_LEVEL`` is set, which is torchrl's own
  switch for its log level (warnings and errors always pass).
- torchrl's PettingZoo wrapper warns that it was tested with another PettingZoo version on every
  scenario env it builds; ``pyproject.toml`` pins the version our tests run with.
"""

from __future__ import annotations

import logging
import os
import warnings


def _warnings_and_above(record: logging.LogRecord) -> bool:
    return record.levelno >= logging.WARNING


def quiet_dependencies() -> None:
    """Install the filters described in the module docstring (idempotent)."""
    warnings.filterwarnings(
        "ignore", message=r"PettingZoo in TorchRL is tested", category=UserWarning
    )
    if "RL_LOGGING_LEVEL" not in os.environ:
        logging.getLogger("torchrl").addFilter(_warnings_and_above)
