"""Trajectory-sampling returns of candidate action sequences (PETS; MA-PETS eq. 10).

``trajectory_sampling_returns`` propagates ``P`` particles per candidate through a dynamics
model and sums a known reward along them; a known termination ends a particle. Any model that
satisfies :class:`DynamicsModel` works (a :class:`~mapets_rl.models.ProbabilisticEnsemble`,
an exact simulator wrapped to that interface, ...).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Protocol, runtime_checkable

import torch

__all__ = [
    "DynamicsModel",
    "RewardFn",
    "TerminationFn",
    "PROPAGATIONS",
    "particle_layout_error",
    "trajectory_sampling_returns",
]

PROPAGATIONS = ("ts_inf", "ts1", "expectation")


def particle_layout_error(
    propagation: str, particles: int, population: int, members: int
) -> str | None:
    """Why ``particles`` particles of ``population`` candidates cannot be split over
    ``members`` ensemble members under ``propagation`` (one line), or ``None`` when they can:
    ``ts_inf`` gives particle ``p`` member ``p mod B`` (``particles`` a multiple of ``B``),
    ``ts1`` re-draws members over all ``particles * population`` rows per agent (a multiple of
    ``B``)."""
    if propagation == "ts_inf" and particles % members:
        return (
            f"particles ({particles}) must be divisible by the ensemble size ({members}) "
            "for propagation='ts_inf'"
        )
    if propagation == "ts1" and (particles * population) % members:
        return (
            f"particles * population ({particles * population}) must be divisible by the "
            f"ensemble size ({members}) for propagation='ts1'"
        )
    return None


#: ``reward_fn(obs [..., obs], action [..., act], next_obs [..., obs]) -> reward [...]``.
RewardFn = Callable[[torch.Tensor, torch.Tensor, torch.Tensor], torch.Tensor]
#: ``termination_fn(obs [..., obs], action [..., act], next_obs [..., obs]) -> done [...]`` bool.
TerminationFn = Callable[[torch.Tensor, torch.Tensor, torch.Tensor], torch.Tensor]


@runtime_checkable
class DynamicsModel(Protocol):
    """What the planner needs of a model: per-agent members predicting next-state deltas.

    Attributes:
        n_agents: ``I``; obs_dim: ``S``; action_dim: ``A``; ensemble_size: members ``B``
            (1 for a single model).
    """

    n_agents: int
    obs_dim: int
    action_dim: int
    ensemble_size: int

    def predict(
        self, obs: torch.Tensor, action: torch.Tensor, dtype: torch.dtype = torch.float32
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Delta mean and log-variance ``[I, B, N, S]`` from ``obs [I, B, N, S]`` and
        ``action [I, B, N, A]`` (member ``b`` predicts rows ``[:, b]``).

        A model may also offer ``frozen_parameters(dtype)``, a context manager within which
        its parameters are prepared once for many ``predict`` calls (``TrajectorySamplingCEM``
        opens it around each ``plan``; ``ProbabilisticEnsemble`` has one)."""
        ...


def trajectory_sampling_returns(
    model: DynamicsModel,
    obs: torch.Tensor,
    candidates: torch.Tensor,
    reward_fn: RewardFn,
    *,
    termination_fn: TerminationFn | None = None,
    propagation: str = "ts_inf",
    particles: int = 20,
    dtype: torch.dtype = torch.float32,
    generator: torch.Generator | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Mean over particles of the summed predicted reward of every candidate (eq. 10).

    Propagation: ``ts_inf`` (particle ``p`` always uses member ``p mod B``), ``ts1`` (members
    re-drawn at every step) or ``expectation`` (one trajectory through the members' mean). The
    particles' Gaussian noise is common to all candidates (and agents and envs): particle
    ``p`` draws the same standard-normal noise whichever candidate it follows, so candidates are
    compared under common random numbers. With ``termination_fn`` a particle's sum stops after
    the step at which it predicts a termination (that step's reward counts, later ones do not,
    as in mbrl-lib's ``ModelEnv``).

    Args:
        model: the agents' dynamics (:class:`DynamicsModel`).
        obs: ``[I, M, S]`` start states (``M`` envs).
        candidates: ``[I, M, Q, H, A]`` action sequences.
        reward_fn / termination_fn: known reward and termination, vectorised.
        propagation, particles, dtype, generator: see above and
            :class:`~mapets_rl.planning.PlannerConfig` (trusted here).

    Returns:
        ``[I, M, Q]`` scores (``-inf`` where a rollout produced NaN) and ``[I]`` long, the
        number of non-finite rewards of particles still alive, per agent.
    """
    n_agents, envs, pop, horizon = candidates.shape[:4]
    members = model.ensemble_size
    cands = envs * pop
    device = obs.device
    # Per-step actions [H, I, 1, M*Q, act]; particles broadcast over dim 2.
    actions = candidates.reshape(n_agents, cands, horizon, -1).permute(2, 0, 1, 3).unsqueeze(2)
    if propagation == "expectation":
        particles = 1
    # Particle-major layout [I, P, M*Q, obs] == [I, B, P/B * M*Q, obs] (member per block).
    rows = particles * cands
    obs_dim = obs.shape[-1]
    state = obs.repeat_interleave(pop, dim=1).unsqueeze(1).expand(-1, particles, -1, -1)
    state = state.reshape(n_agents, rows, obs_dim)
    # Every step's model-input actions [H, I, rows, act], built once (not once per step).
    step_actions = actions.expand(-1, -1, particles, -1, -1).reshape(horizon, n_agents, rows, -1)
    returns = torch.zeros(n_agents, rows, device=device)
    alive = torch.ones(n_agents, rows, dtype=torch.bool, device=device)
    finite_steps = torch.zeros(n_agents, rows, dtype=torch.long, device=device)
    for t in range(horizon):
        action = step_actions[t]
        if propagation == "expectation":
            mean, _ = model.predict(state.unsqueeze(1), action.unsqueeze(1), dtype=dtype)
            next_state = state + mean.mean(1)  # [I, B, rows, obs] -> members' mean
        else:
            if propagation == "ts1":
                perm = torch.randperm(rows, generator=generator, device=device)
                inv = torch.argsort(perm)
                s_in, a_in = state[:, perm], action[:, perm]
            else:
                s_in, a_in = state, action
            s_in = s_in.view(n_agents, members, rows // members, -1)
            a_in = a_in.view(n_agents, members, rows // members, -1)
            mean, logvar = model.predict(s_in, a_in, dtype=dtype)
            mean = mean.reshape(n_agents, particles, cands, obs_dim)
            std = torch.exp(logvar.mul(0.5)).reshape(n_agents, particles, cands, obs_dim)
            if propagation == "ts1":
                mean = mean.view(n_agents, rows, obs_dim)[:, inv].view_as(std)
                std = std.view(n_agents, rows, obs_dim)[:, inv].view_as(mean)
            # Common random numbers: one draw per particle [P, 1, obs], shared by all
            # candidates (broadcast over the M*Q candidates of the particle-major layout).
            eps = torch.randn((particles, 1, obs_dim), generator=generator, device=device)
            next_state = torch.addcmul(state.view_as(mean) + mean, std, eps)
            next_state = next_state.reshape(n_agents, rows, obs_dim)
        reward = reward_fn(state, action, next_state)
        if reward.shape != returns.shape:
            raise ValueError(
                f"reward_fn must return shape {tuple(returns.shape)} for inputs shaped "
                f"{tuple(state.shape)}, got {tuple(reward.shape)}."
            )
        counted = torch.where(alive, reward, 0.0)  # finite wherever the particle has ended
        returns.add_(counted)
        finite_steps.add_(torch.isfinite(counted))
        if termination_fn is not None:
            alive &= ~termination_fn(state, action, next_state)
        state = next_state
    nonfinite = (horizon - finite_steps).sum(-1)
    scores = returns.reshape(n_agents, particles, envs, pop).mean(1)
    return torch.where(torch.isnan(scores), float("-inf"), scores), nonfinite
