"""Checks of constructor arguments (agent counts, feature sizes, hidden sizes, loss
coefficients, seeds), each raising a one-line ``ValueError`` that names the argument and the
allowed values before any parameter is allocated. Bools are refused where a number is expected
(``True`` is an ``int`` to Python, never a size or a coefficient here). Checks of tensors read at
a module's boundary are in :mod:`mapets_rl.modules.tensor_checks`."""

from __future__ import annotations

import math
import numbers
from collections.abc import Sequence
from typing import Any


def is_positive_int(value: Any) -> bool:
    """``value`` is an int >= 1 (a bool is not)."""
    return isinstance(value, int) and not isinstance(value, bool) and value >= 1


def require_positive_ints(**arguments: Any) -> None:
    """ValueError naming the first of ``arguments`` (``name=value``) that is not an int >= 1
    (bools are rejected)."""
    for name, value in arguments.items():
        if not is_positive_int(value):
            raise ValueError(f"{name} must be an int >= 1, got {value!r}")


def hidden_sizes(num_cells: Sequence[int]) -> list[int]:
    """``num_cells`` as a list; ValueError unless it is a non-empty sequence of ints >= 1."""
    cells = list(num_cells)
    if not cells or not all(is_positive_int(c) for c in cells):
        raise ValueError(f"num_cells must be a non-empty list of ints >= 1, got {cells}")
    return cells


def is_real_number(value: Any) -> bool:
    """``value`` is a real number (int, float, numpy scalar) and not a bool."""
    return isinstance(value, numbers.Real) and not isinstance(value, bool)


def finite_number(
    name: str, value: Any, *, minimum: float | None = None, strict: bool = False
) -> float:
    """``value`` as a float; ValueError unless it is a finite number (bools refused) and, with
    ``minimum``, ``>= minimum`` (``> minimum`` if ``strict``)."""
    bound = "" if minimum is None else f" {'>' if strict else '>='} {minimum:g}"
    ok = is_real_number(value) and math.isfinite(value)
    if ok and minimum is not None:
        ok = value > minimum if strict else value >= minimum
    if not ok:
        raise ValueError(f"{name} must be a finite number{bound}, got {value!r}")
    return float(value)


def seed_value(name: str, value: Any) -> int | None:
    """``value`` as an int seed; ValueError unless it is ``None`` or an int >= 0 (bools, strings
    and floats refused)."""
    if value is None:
        return None
    if not isinstance(value, numbers.Integral) or isinstance(value, bool) or value < 0:
        raise ValueError(f"{name} must be None or an int >= 0, got {value!r}")
    return int(value)
