"""How much memory a planning call and the ensemble will take, and how much there is: MA-PETS
refuses a config that cannot fit before it allocates anything (or writes its run directory).

The estimate follows :func:`~mapets_rl.planning.trajectory_sampling_returns`: with
``R = envs * Q * P`` particle rows per agent, a decision holds every step's actions
``[H, I, R, A]``, a handful of state-sized tensors ``[I, R, S]`` (state, prediction mean and
log-variance, noise-scaled next state, reward intermediates) and the MLP's two activation
buffers ``[I, R, max(hidden)]``; the ensemble holds ``I * B`` MLPs, trained with Adam (two
moment buffers and a gradient per parameter); every CAV's dataset ``D(i)+`` holds
``buffer_size`` transitions. It is an order of magnitude, not a measurement: the refusal fires
only when the estimate exceeds what the device has available
(:func:`~mapets_rl.memory.available_memory`, which counts ``ulimit -v`` and a cgroup's
limit too).
"""

from __future__ import annotations

from collections.abc import Sequence

from mapets_rl.memory import available_memory

__all__ = ["available_memory", "dataset_bytes", "ensemble_bytes", "planner_bytes"]

_STATE_COPIES = 12
"""State-sized ``[I, R, S]`` tensors alive at once during a step (generous)."""


def planner_bytes(
    n_agents: int,
    obs_dim: int,
    action_dim: int,
    hidden: Sequence[int],
    population: int,
    particles: int,
    horizon: int,
    envs: int = 1,
) -> int:
    """Bytes of one planning call's largest tensors (fp32 upper bound)."""
    rows = n_agents * envs * population * particles
    per_row = horizon * action_dim + _STATE_COPIES * obs_dim + 2 * max(hidden, default=0)
    candidates = 4 * n_agents * envs * population * horizon * action_dim
    return 4 * rows * per_row + candidates


def ensemble_bytes(
    n_agents: int, obs_dim: int, action_dim: int, hidden: Sequence[int], ensemble_size: int
) -> int:
    """Bytes of ``n_agents * ensemble_size`` MLPs ``obs + act -> hidden -> 2 * obs`` with a
    gradient and Adam's two moments per parameter (fp32)."""
    sizes = [obs_dim + action_dim, *hidden, 2 * obs_dim]
    params = sum((a + 1) * b for a, b in zip(sizes[:-1], sizes[1:], strict=False))
    return 4 * 4 * n_agents * ensemble_size * params


def dataset_bytes(n_agents: int, obs_dim: int, action_dim: int, buffer_size: int) -> int:
    """Bytes of the CAVs' datasets: ``n_agents * buffer_size`` transition slots (observation,
    action and next observation in fp32, a mask) and their four int64 index entries each."""
    return n_agents * buffer_size * (4 * (2 * obs_dim + action_dim) + 1 + 4 * 8)
