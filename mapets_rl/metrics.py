"""Episode metrics of the papers.

Figure-eight (MA-PETS paper eqs. 27-28), over CAVs ``i`` with collision step ``t_c(i)`` (the
horizon ``H`` if the CAV never collides):

- Agility ``= mean_i (1 / t_c(i)) * sum_{t < t_c(i)} d_t(i)``: mean distance travelled per step
  before the collision [m/step].
- Safety ``= mean_i t_c(i) / H``.

Freeway (Shapley paper, Table I): average velocity and average comfort of all vehicles.
"""

from __future__ import annotations

import numpy as np


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
        collision_steps: ``[I]`` step ``t_c(i)`` in ``1..T`` at which CAV ``i`` collided (its
            distances from step ``t_c(i)`` on are ignored), or ``>= T`` if it never did.

    Returns:
        Mean over CAVs of the distance travelled per step before the collision [m/step].
    """
    d = _as_array(distances, "distances")
    tc = _as_array(collision_steps, "collision_steps")
    if d.ndim != 2 or tc.shape != (d.shape[1],):
        raise ValueError(
            f"distances must be [T, I] and collision_steps [I], got {d.shape} and {tc.shape}"
        )
    if (tc < 1).any():
        raise ValueError("collision_steps must be >= 1 (steps are counted from 1)")
    horizon = d.shape[0]
    tc = np.minimum(tc, horizon)
    steps = np.arange(1, horizon + 1)[:, None]
    travelled = (d * (steps <= tc[None, :])).sum(axis=0)
    return float(np.mean(travelled / tc))


def safety(collision_steps: object, horizon: int) -> float:
    """Safety (paper eq. 28): mean over CAVs of ``t_c(i) / H``, ``t_c(i) = H`` if no collision.

    Args:
        collision_steps: ``[I]`` collision steps (values ``>= horizon`` mean no collision).
        horizon: episode length ``H`` in steps, >= 1.
    """
    if horizon < 1:
        raise ValueError(f"horizon must be >= 1, got {horizon}")
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
