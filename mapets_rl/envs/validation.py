"""Checks of scenario config values, each raising a one-line ``ValueError`` that names the key
and the allowed values (used by the scenarios' ``validate_config``)."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import torch

from mapets_rl.config import MAX_SEED

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


def check_seed(seed: object, name: str = "seed") -> int | None:
    """``seed`` as an int (numpy integers included), or None; ValueError naming ``name`` unless
    it is None or an integer in ``[0, MAX_SEED]`` (a bool is no seed)."""
    if seed is None:
        return None
    if not (is_integer(seed) and 0 <= seed <= MAX_SEED):
        raise ValueError(f"{name} must be None or an integer in [0, 2**62 - 1], got {seed!r}")
    return int(seed)


def check_flag(value: object, name: str) -> bool:
    """``value`` as a bool; ValueError naming ``name`` unless it is True or False (``"no"``
    would read as true)."""
    if not isinstance(value, bool | np.bool_):
        raise ValueError(f"{name} must be True or False, got {value!r}")
    return bool(value)


def check_device(device: object) -> torch.device:
    """``device`` as a ``torch.device``; ValueError (one line, naming ``device``) unless it is
    the CPU, a CUDA device this machine has (``"cuda"`` / ``"cuda:N"``) or ``"mps"`` where
    torch has it: ``"meta"`` and the other device types hold no data the envs can step."""
    if isinstance(device, bool) or not isinstance(device, str | torch.device):
        raise ValueError(f"device must be a device name such as 'cpu' or 'cuda:0', got {device!r}")
    try:
        parsed = torch.device(device)
    except RuntimeError:
        parsed = None
    if parsed is None or parsed.type not in ("cpu", "cuda", "mps"):
        raise ValueError(f"device must be 'cpu', 'cuda', 'cuda:N' or 'mps', got {device!r}")
    if parsed.type == "cuda" and (
        not torch.cuda.is_available() or (parsed.index or 0) >= torch.cuda.device_count()
    ):
        raise ValueError(
            f"device={device!r}: no such CUDA device here ({torch.cuda.device_count()} GPUs)"
        )
    mps = getattr(torch.backends, "mps", None)
    if parsed.type == "mps" and not (mps is not None and mps.is_available()):
        raise ValueError(f"device={device!r}: this machine has no MPS device")
    return parsed


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


RENDERING_FLAGS = (
    "offscreen_rendering",
    "real_time_rendering",
    "render_agent",
    "show_trajectories",
    "stock_neighbour_search",
)
"""Config keys of every traffic scenario that must be booleans (``"no"`` would read as true)."""
MAX_SCREEN_PIXELS = 4096
"""The largest ``screen_width`` / ``screen_height`` a scenario draws [px]: a frame of 4096 x
4096 RGB pixels is 48 MiB, and a video keeps one per step."""


def require_rendering(config: dict) -> None:
    """ValueError naming the first rendering key of ``config`` (highway-env's, present in every
    traffic scenario) that is not valid: the flags of :data:`RENDERING_FLAGS` must be booleans,
    ``screen_width`` / ``screen_height`` integers in ``[1, MAX_SCREEN_PIXELS]``, ``scaling`` a
    finite number > 0 (pixels per metre) and ``centering_position`` a pair of numbers in
    ``[0, 1]`` (the ego vehicle's place on the screen, as fractions of its size)."""
    for key in RENDERING_FLAGS:
        if key in config and not isinstance(config[key], bool | np.bool_):
            raise ValueError(f"{key} must be true or false, got {config[key]!r}")
    for key in ("screen_width", "screen_height"):
        value = config.get(key)
        if key in config and not (is_integer(value) and 1 <= value <= MAX_SCREEN_PIXELS):
            raise ValueError(
                f"{key} must be an integer in [1, {MAX_SCREEN_PIXELS}] [px], got {value!r}"
            )
    if "scaling" in config:
        require_number(config, "scaling", 0.0, 1000.0, low_open=True, unit="px/m")
    if "centering_position" in config:
        value = config["centering_position"]
        ok = (
            isinstance(value, list | tuple | np.ndarray)
            and len(value) == 2
            and all(is_real(v) and 0 <= v <= 1 for v in value)
        )
        if not ok:
            raise ValueError(
                "centering_position must be a pair [x, y] of numbers in [0, 1] (fractions of "
                f"the screen), got {value!r}"
            )


ONE_HOT_TOLERANCE = 1e-4
"""How far an entry of a one-hot action may be from 0 or 1: straight-through estimators
(hard + soft - soft.detach()) give 0.99999994 where they mean 1."""


def check_one_hot(action: torch.Tensor) -> None:
    """ValueError unless every CAV's action ``[..., I, A]`` is one-hot (within
    :data:`ONE_HOT_TOLERANCE`), naming the first CAV whose action is not (and its road, for a
    batch of roads)."""
    tol = ONE_HOT_TOLERANCE
    if action.dtype == torch.bool:  # a one-hot of bools is one too (``abs`` has no bool kernel)
        action = action.to(torch.int8)
    near_binary = ((action.abs() <= tol) | ((action - 1).abs() <= tol)).all(-1)
    valid = near_binary & ((action.sum(-1) - 1).abs() <= tol)
    if bool(valid.all()):
        return
    where = [int(i) for i in (~valid).nonzero()[0]]
    road = f" of road {where[0]}" if len(where) > 1 else ""
    raise ValueError(
        "('agents', 'action') must be one-hot per CAV (exactly one 1, zeros elsewhere, over "
        f"{action.shape[-1]} actions), got {action[tuple(where)].tolist()} for CAV "
        f"{where[-1]}{road}"
    )
