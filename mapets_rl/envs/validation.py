"""Checks of scenario config values, each raising a one-line ``ValueError`` that names the key
and the allowed values (used by the scenarios' ``validate_config``)."""

from __future__ import annotations

import math
from typing import Any

import numpy as np

PHYSICAL_MAX_SPEED = 60.0
"""The highest speed limit a scenario accepts [m/s] (216 km/h): anything above is a typo."""


def is_real(value: Any) -> bool:
    """True for a finite int or float (numpy scalars included), False for bools and others."""
    return (
        isinstance(value, int | float | np.integer | np.floating)
        and not isinstance(value, bool | np.bool_)
        and math.isfinite(value)
    )


def is_integer(value: Any) -> bool:
    """True for an int (numpy integers included), False for bools and others."""
    return isinstance(value, int | np.integer) and not isinstance(value, bool | np.bool_)


def _bounds(low: float | None, high: float | None, low_open: bool) -> str:
    parts = []
    if low is not None:
        parts.append(f"{'>' if low_open else '>='} {low:g}")
    if high is not None:
        parts.append(f"<= {high:g}")
    return " and ".join(parts)


def require_number(
    config: dict,
    key: str,
    low: float | None = None,
    high: float | None = None,
    low_open: bool = False,
    unit: str = "",
) -> None:
    """ValueError unless ``config[key]`` is a finite number within ``[low, high]`` (``(low,``
    when ``low_open``)."""
    value = config[key]
    ok = is_real(value)
    if ok and low is not None:
        ok = value > low if low_open else value >= low
    if ok and high is not None:
        ok = value <= high
    if not ok:
        bounds = _bounds(low, high, low_open)
        unit = f" [{unit}]" if unit else ""
        raise ValueError(
            f"{key} must be a finite number{' ' + bounds if bounds else ''}{unit}, got {value!r}"
        )


def require_range(
    config: dict, key: str, low: float | None = None, high: float | None = None, unit: str = ""
) -> None:
    """ValueError unless ``config[key]`` is a pair ``(lo, hi)`` of finite numbers with
    ``low <= lo <= hi <= high``."""
    value = config[key]
    pair = (
        isinstance(value, list | tuple | np.ndarray)
        and len(value) == 2
        and all(is_real(v) for v in value)
    )
    ok = pair and value[0] <= value[1]
    if ok and low is not None:
        ok = value[0] >= low
    if ok and high is not None:
        ok = value[1] <= high
    if not ok:
        lo = f"{low:g} <= " if low is not None else ""
        hi = f" <= {high:g}" if high is not None else ""
        unit = f" [{unit}]" if unit else ""
        raise ValueError(
            f"{key} must be a range (lo, hi) of finite numbers with {lo}lo <= hi"
            f"{hi}{unit}, got {value!r}"
        )
