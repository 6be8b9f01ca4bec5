"""What the bad-input tests share: the check that a call is refused with a one-line error, and
the bad values they give (non-finite numbers, a CUDA device this machine does not have)."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import pytest
import torch

INF, NAN = float("inf"), float("nan")
NO_CUDA_DEVICE = "cuda" if not torch.cuda.is_available() else f"cuda:{torch.cuda.device_count()}"
"""A CUDA device this machine does not have."""


def refused(call: Callable[[], Any], match: str, error: type[Exception] = ValueError) -> str:
    """Run ``call``; it must raise ``error`` whose one-line message matches ``match``."""
    with pytest.raises(error, match=match) as err:
        call()
    message = str(err.value)
    assert "\n" not in message, message
    return message
