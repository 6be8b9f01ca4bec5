"""Checks of network constructor arguments (agent counts, feature sizes, hidden sizes), each
raising a one-line ``ValueError`` that names the argument and the allowed values before any
parameter is allocated."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any


def _is_positive_int(value: Any) -> bool:
    return isinstance(value, int) and not isinstance(value, bool) and value >= 1


def require_positive_ints(**arguments: Any) -> None:
    """ValueError naming the first of ``arguments`` (``name=value``) that is not an int >= 1
    (bools are rejected)."""
    for name, value in arguments.items():
        if not _is_positive_int(value):
            raise ValueError(f"{name} must be an int >= 1, got {value!r}")


def hidden_sizes(num_cells: Sequence[int]) -> list[int]:
    """``num_cells`` as a list; ValueError unless it is a non-empty sequence of ints >= 1."""
    cells = list(num_cells)
    if not cells or not all(_is_positive_int(c) for c in cells):
        raise ValueError(f"num_cells must be a non-empty list of ints >= 1, got {cells}")
    return cells
