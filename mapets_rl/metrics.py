"""Episode metrics of the papers.

Figure-eight (MA-PETS paper eqs. 27-28), over CAVs ``i`` with *lasting time* ``t_c(i)``: the
number of steps CAV ``i`` completed before its collision. A CAV that collides during step ``t``
(steps counted ``1..H``) has ``t_c(i) = t - 1 < H``; ``t_c(i) = H`` only if it never collides, so
an episode with a collision always has safety < 1, even when the collision happens in the last
step.

- Agility ``= mean_i (1 / n_i) * sum_{t < n_i} d_t(i)`` with ``n_i = min(t_c(i) + 1, T)`` the
  steps CAV ``i`` drove (the crashing step included, as eq. 27 sums ``t = 0..t_c``; dividing by
  the number of summed steps instead of ``t_c`` keeps it finite for ``t_c = 0``): mean distance
  travelled per driven step [m/step].
- Safety ``= mean_i t_c(i) / H``.

Freeway (Shapley paper, Table I): average velocity [m/s] and average comfort of all vehicles.
Comfort (eq. 9) is a score per vehicle and step, no physical unit: 3 keeping the lane with
``|acc| < Theta``, 2 keeping it with ``|acc| >= Theta``, 1 changing lanes, 0 emergency stop.

Units: :data:`METRIC_UNITS` names the unit of every metric the recipes record;
:func:`metric_label` writes ``name [unit]`` for tables, plot labels and logs, and
:func:`format_metric` speeds in m/s also in mph (:data:`MPH_PER_MPS`). :data:`TASK_METRICS`
are the metrics of what a policy does (what ``compare`` shows by default);
:data:`METRIC_RANGES` the values a metric can take.
"""

from __future__ import annotations

import math

import numpy as np

MPH_PER_MPS = 3600.0 / 1609.344
"""Miles per hour in one metre per second (2.237)."""

METRIC_UNITS: dict[str, str] = {
    "agility": "m/step",
    "safety": "fraction of H",
    "mean_speed": "m/s",
    "average_velocity": "m/s",
    "velocity": "m/s",
    "traffic_velocity": "m/s",
    "average_comfort": "score 0-3",
    "comfort": "score 0-3",
    "traffic_comfort": "score 0-3",
    "collisions": "CAVs",
    "length": "steps",
    "episode": "episodes",
    "reward": "per CAV-step",
    "return": "per CAV",
    "step_time": "s/step",
    "train_time": "s",
    "transitions_stored": "transitions",
    "transitions_filtered": "transitions",
    "transitions_shared": "transitions",
    "bytes_shared": "bytes",
    "dataset_size": "transitions",
    "frames": "env steps",
}
"""Metric name -> unit (see the module docstring for the definitions). Metrics not listed
(losses, NLLs, counters of recipe internals) carry none."""


TASK_METRICS: frozenset[str] = frozenset(
    {
        "agility",
        "safety",
        "mean_speed",
        "average_velocity",
        "velocity",
        "traffic_velocity",
        "average_comfort",
        "comfort",
        "traffic_comfort",
        "collisions",
        "length",
        "reward",
        "return",
    }
)
"""The metrics of what a policy does in its scenario: the papers' metrics (agility, safety,
velocity, comfort), collisions, episode length, reward and return. ``compare`` shows these by
default; the others, the cost of training (``step_time``, ``train_time``), bookkeeping counters
(``episode``, ``frames``, ``transitions_*``, ``bytes_shared``, ``dataset_size``) and recipe
internals (losses, exploration rates), only when asked for by name."""

TIMING_METRICS: frozenset[str] = frozenset({"step_time", "train_time"})
"""Metrics that are measured wall-clock durations: they differ between any two runs, so a run
keeps them apart from its results and checkpoints (``timings.json``), which are then the same
byte for byte for two identical runs."""

METRIC_RANGES: dict[str, tuple[float, float]] = {
    "agility": (0.0, math.inf),
    "safety": (0.0, 1.0),
    "mean_speed": (0.0, math.inf),
    "average_velocity": (0.0, math.inf),
    "velocity": (0.0, math.inf),
    "traffic_velocity": (0.0, math.inf),
    "average_comfort": (0.0, 3.0),
    "comfort": (0.0, 3.0),
    "traffic_comfort": (0.0, 3.0),
    "collisions": (0.0, math.inf),
    "length": (0.0, math.inf),
    "episode": (0.0, math.inf),
    "step_time": (0.0, math.inf),
    "train_time": (0.0, math.inf),
    "transitions_stored": (0.0, math.inf),
    "transitions_filtered": (0.0, math.inf),
    "transitions_shared": (0.0, math.inf),
    "bytes_shared": (0.0, math.inf),
    "dataset_size": (0.0, math.inf),
    "frames": (0.0, math.inf),
    "clique_cover_number": (0.0, math.inf),
    "ramp_stuck": (0.0, math.inf),
    "ramp_forced_merges": (0.0, math.inf),
    "ramp_mobil_merges": (0.0, math.inf),
    "mainline_changes_near_merge": (0.0, math.inf),
    "mainline_changes_elsewhere": (0.0, math.inf),
    "shielded": (0.0, math.inf),
    "nonfinite_rewards": (0.0, math.inf),
    "random": (0.0, 1.0),
}
"""Metric name -> ``(low, high)``, the values it can take: safety is a fraction of ``H``,
comfort a score in ``[0, 3]``, distances, speeds, counts and times are non-negative,
``random`` (whether an episode's actions were random) a fraction. ``compare``'s intervals and
every plotted band (:mod:`mapets_rl.plotting`) are clipped to it. Metrics not listed (reward,
return, losses) are unbounded."""


def metric_range(name: str) -> tuple[float, float]:
    """``(low, high)`` of metric ``name`` (:data:`METRIC_RANGES`; ``(-inf, inf)`` when it
    declares none); ``"train/safety"`` and ``"safety"`` alike."""
    return METRIC_RANGES.get(name.rsplit("/", 1)[-1], (-math.inf, math.inf))


def is_timing_metric(name: str) -> bool:
    """Whether ``name`` (``"train/step_time"`` and ``"step_time"`` alike) is one of
    :data:`TIMING_METRICS`."""
    return name.rsplit("/", 1)[-1] in TIMING_METRICS


def is_task_metric(name: str) -> bool:
    """Whether ``name`` (``"train/safety"`` and ``"safety"`` alike) is one of
    :data:`TASK_METRICS`."""
    return name.rsplit("/", 1)[-1] in TASK_METRICS


def metric_unit(name: str) -> str:
    """The unit of metric ``name`` (``""`` when it has none); ``"train/agility"`` and
    ``"agility"`` alike."""
    return METRIC_UNITS.get(name.rsplit("/", 1)[-1], "")


def metric_label(name: str) -> str:
    """``name [unit]`` (``name`` alone without a unit): ``"average_velocity [m/s]"`` (the
    tables give speeds in mph beside, the plots on a second axis)."""
    unit = metric_unit(name)
    return f"{name} [{unit}]" if unit else name


def format_metric(name: str, value: float, precision: int = 4) -> str:
    """``value`` with its unit: ``"0.97 m/step"``, speeds as ``"27.1 m/s (60.6 mph)"``."""
    unit = metric_unit(name)
    text = f"{value:.{precision}g}"
    if unit == "m/s":
        return f"{text} m/s ({value * MPH_PER_MPS:.{precision}g} mph)"
    return f"{text} {unit}" if unit else text


def _as_array(x: object, name: str) -> np.ndarray:
    try:
        import torch

        if isinstance(x, torch.Tensor):
            x = x.detach().cpu().numpy()
    except ImportError:  # pragma: no cover - torch is a dependency
        pass
    arr = np.asarray(x, dtype=np.float64)
    if not np.isfinite(arr).all():
        raise ValueError(f"{name} must be finite")
    return arr


def agility(distances: object, collision_steps: object) -> float:
    """Agility (paper eq. 27).

    Args:
        distances: ``[T, I]`` distance travelled by each CAV in each step [m].
        collision_steps: ``[I]`` lasting times ``t_c(i)`` (steps completed before the
            collision, ``0 <= t_c < T``; ``>= T`` if CAV ``i`` never collided). The distances of
            steps ``0..t_c(i)`` count (the crashing step included), later ones are ignored.

    Returns:
        Mean over CAVs of the distance travelled per driven step [m/step].
    """
    d = _as_array(distances, "distances")
    tc = _as_array(collision_steps, "collision_steps")
    if d.ndim != 2 or tc.shape != (d.shape[1],):
        raise ValueError(
            f"distances must be [T, I] and collision_steps [I], got {d.shape} and {tc.shape}"
        )
    if d.shape[0] < 1:
        raise ValueError("distances must hold at least one step")
    if (tc < 0).any():
        raise ValueError("collision_steps must be >= 0 (steps completed before the collision)")
    driven = np.minimum(tc + 1, d.shape[0])
    steps = np.arange(d.shape[0])[:, None]
    travelled = (d * (steps < driven[None, :])).sum(axis=0)
    return float(np.mean(travelled / driven))


def safety(collision_steps: object, horizon: int) -> float:
    """Safety (paper eq. 28): mean over CAVs of ``t_c(i) / H``.

    Args:
        collision_steps: ``[I]`` lasting times ``t_c(i)``: steps completed before the collision
            (a collision in step ``t = 1..H`` gives ``t - 1``), ``>= horizon`` if none.
        horizon: episode length ``H`` in steps, >= 1.
    """
    if isinstance(horizon, bool) or not isinstance(horizon, int | np.integer) or horizon < 1:
        raise ValueError(f"horizon must be an integer >= 1, got {horizon!r}")
    tc = _as_array(collision_steps, "collision_steps")
    if (tc < 0).any():
        raise ValueError("collision_steps must be >= 0")
    return float(np.mean(np.minimum(tc, horizon) / horizon))


def average_velocity(speeds: object) -> float:
    """Average velocity [m/s] over all vehicles and steps; ``speeds`` is ``[T, N]``."""
    return float(np.mean(_as_array(speeds, "speeds")))


def average_comfort(comforts: object) -> float:
    """Average comfort (Shapley paper eq. 9) over all vehicles and steps; ``[T, N]``."""
    return float(np.mean(_as_array(comforts, "comforts")))
