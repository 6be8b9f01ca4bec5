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
    "StepFn",
    "particle_layout_error",
    "expected_trajectory",
    "propagate_step",
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


#: ``step(model, state, action, eps, perm, returns, alive, finite_steps, reward_fn,
#: termination_fn, propagation, dtype) -> (next_state, returns, alive, finite_steps)``: one
#: model step of every particle (:func:`propagate_step` or a compiled version of it).
StepFn = Callable[..., tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]]


def propagate_step(
    model: DynamicsModel,
    state: torch.Tensor,
    action: torch.Tensor,
    eps: torch.Tensor | None,
    perm: torch.Tensor | None,
    returns: torch.Tensor,
    alive: torch.Tensor,
    finite_steps: torch.Tensor,
    reward_fn: RewardFn,
    termination_fn: TerminationFn | None,
    propagation: str,
    dtype: torch.dtype,
    schedule: torch.Tensor | None = None,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """One model step of every particle and its reward: a pure tensor function (no random
    draws, no host syncs), what :class:`~mapets_rl.planning.compiled.CompiledStep` compiles.

    Args:
        model: the agents' dynamics (:class:`DynamicsModel`, ``B`` members).
        state: ``[I, R, S]`` particle states in the particle-major layout (``R = P * C`` rows,
            ``C`` candidates; row block ``p`` is particle ``p``, member ``p mod B``).
        action: ``[I, R, A]`` this step's actions.
        eps: ``[P, 1, S]`` standard-normal noise of the step (common to the candidates);
            ``None`` for ``expectation``.
        perm: ``[R]`` the rows' member re-draw of ``ts1`` (``None`` otherwise).
        returns: ``[I, R]`` summed rewards so far; alive: ``[I, R]`` bool, particles not yet
            terminated; finite_steps: ``[I, R]`` long, steps with a finite counted reward.
        reward_fn / termination_fn: the known reward and termination.
        propagation: ``ts_inf``, ``ts1`` or ``expectation``; dtype: the MLP's compute dtype.
        schedule: optional ``[I, R, S]`` known values of the next state's features (NaN: the
            model's prediction stands), e.g. a neighbour's speed from its broadcast plan; they
            replace the prediction before the reward and termination read it.

    Returns:
        ``next_state [I, R, S]``, ``returns``, ``alive`` and ``finite_steps`` after the step.
    """
    n_agents, rows, obs_dim = state.shape
    members = model.ensemble_size
    if propagation == "expectation":
        mean, _ = model.predict(state.unsqueeze(1), action.unsqueeze(1), dtype=dtype)
        next_state = state + mean.mean(1)  # [I, B, R, S] -> members' mean
    else:
        particles = eps.shape[0]
        if perm is not None:
            inv = torch.argsort(perm)
            s_in, a_in = state[:, perm], action[:, perm]
        else:
            s_in, a_in = state, action
        s_in = s_in.reshape(n_agents, members, rows // members, -1)
        a_in = a_in.reshape(n_agents, members, rows // members, -1)
        mean, logvar = model.predict(s_in, a_in, dtype=dtype)
        mean = mean.reshape(n_agents, rows, obs_dim)
        std = torch.exp(logvar.mul(0.5)).reshape(n_agents, rows, obs_dim)
        if perm is not None:
            mean, std = mean[:, inv], std[:, inv]
        shape = (n_agents, particles, rows // particles, obs_dim)
        # Common random numbers: one draw per particle [P, 1, S], shared by all candidates.
        next_state = torch.addcmul(state.view(shape) + mean.view(shape), std.view(shape), eps)
        next_state = next_state.reshape(n_agents, rows, obs_dim)
    if schedule is not None:
        next_state = torch.where(torch.isnan(schedule), next_state, schedule)
    reward = reward_fn(state, action, next_state)
    if reward.shape != returns.shape:
        raise ValueError(
            f"reward_fn must return shape {tuple(returns.shape)} for inputs shaped "
            f"{tuple(state.shape)}, got {tuple(reward.shape)}."
        )
    counted = torch.where(alive, reward, 0.0)  # finite wherever the particle has ended
    returns = returns + counted
    finite_steps = finite_steps + torch.isfinite(counted)
    if termination_fn is not None:
        alive = alive & ~termination_fn(state, action, next_state)
    return next_state, returns, alive, finite_steps


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
    step: StepFn = propagate_step,
    schedule: torch.Tensor | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Mean over particles of the summed predicted reward of every candidate (eq. 10).

    Propagation: ``ts_inf`` (particle ``p`` always uses member ``p mod B``), ``ts1`` (members
    re-drawn at every step) or ``expectation`` (one trajectory through the members' mean). The
    particles' Gaussian noise is common to all candidates (and agents and envs): particle
    ``p`` draws the same standard-normal noise whichever candidate it follows, so candidates are
    compared under common random numbers. With ``termination_fn`` a particle's sum stops after
    the step at which it predicts a termination (that step's reward counts, later ones do not,
    as in mbrl-lib's ``ModelEnv``).

    Each step's random numbers are drawn here and passed in, so the step itself is a pure
    function (:func:`propagate_step`, or a compiled version of it passed as ``step``).

    Args:
        model: the agents' dynamics (:class:`DynamicsModel`).
        obs: ``[I, M, S]`` start states (``M`` envs).
        candidates: ``[I, M, Q, H, A]`` action sequences.
        reward_fn / termination_fn: known reward and termination, vectorised.
        propagation, particles, dtype, generator: see above and
            :class:`~mapets_rl.planning.PlannerConfig` (trusted here).
        step: the step function (default :func:`propagate_step`).
        schedule: optional ``[I, M, H, S]`` known feature values of the state after each step
            (index ``t``: the state after step ``t``), NaN where the model predicts; the same
            for every candidate and particle of an env (see :func:`propagate_step`).

    Returns:
        ``[I, M, Q]`` scores (``-inf`` where a rollout produced NaN) and ``[I]`` long, the
        number of non-finite rewards of particles still alive, per agent.
    """
    n_agents, envs, pop, horizon = candidates.shape[:4]
    cands = envs * pop
    device = obs.device
    if propagation == "expectation":
        particles = 1
    # Particle-major layout [I, P, M*Q, obs] == [I, B, P/B * M*Q, obs] (member per block).
    rows = particles * cands
    obs_dim = obs.shape[-1]
    state = obs.repeat_interleave(pop, dim=1).unsqueeze(1).expand(-1, particles, -1, -1)
    state = state.reshape(n_agents, rows, obs_dim)
    # Every step's model-input actions [H, I, rows, act], built once (not once per step).
    actions = candidates.reshape(n_agents, cands, horizon, -1).permute(2, 0, 1, 3).unsqueeze(2)
    step_actions = actions.expand(-1, -1, particles, -1, -1).reshape(horizon, n_agents, rows, -1)
    step_schedule = None
    if schedule is not None:  # [I, M, H, S] -> [H, I, rows, S] in the particle-major layout
        known = schedule.permute(2, 0, 1, 3).repeat_interleave(pop, dim=2).unsqueeze(2)
        step_schedule = known.expand(-1, -1, particles, -1, -1).reshape(
            horizon, n_agents, rows, obs_dim
        )
    returns = torch.zeros(n_agents, rows, device=device)
    alive = torch.ones(n_agents, rows, dtype=torch.bool, device=device)
    finite_steps = torch.zeros(n_agents, rows, dtype=torch.long, device=device)
    for t in range(horizon):
        perm = eps = None
        if propagation == "ts1":
            perm = torch.randperm(rows, generator=generator, device=device)
        if propagation != "expectation":
            eps = torch.randn((particles, 1, obs_dim), generator=generator, device=device)
        state, returns, alive, finite_steps = step(
            model,
            state,
            step_actions[t],
            eps,
            perm,
            returns,
            alive,
            finite_steps,
            reward_fn,
            termination_fn,
            propagation,
            dtype,
            None if step_schedule is None else step_schedule[t],
        )
    nonfinite = (horizon - finite_steps).sum(-1)
    scores = returns.reshape(n_agents, particles, envs, pop).mean(1)
    return torch.where(torch.isnan(scores), float("-inf"), scores), nonfinite


def expected_trajectory(
    model: DynamicsModel,
    obs: torch.Tensor,
    actions: torch.Tensor,
    *,
    dtype: torch.dtype = torch.float32,
    schedule: torch.Tensor | None = None,
) -> torch.Tensor:
    """The states that ``actions`` lead to through the members' mean (no noise): what an agent
    expects of its own plan, e.g. to broadcast it.

    Args:
        model: the agents' dynamics (:class:`DynamicsModel`).
        obs: ``[I, M, S]`` start states.
        actions: ``[I, M, H, A]`` one action sequence per agent and env.
        dtype: the MLP's compute dtype.
        schedule: optional ``[I, M, H, S]`` known feature values (NaN: predicted), as in
            :func:`trajectory_sampling_returns`.

    Returns:
        ``[I, M, H, S]``: index ``t`` is the state after step ``t``.
    """
    state, states = obs, []
    for t in range(actions.shape[2]):
        mean, _ = model.predict(state.unsqueeze(1), actions[:, :, t].unsqueeze(1), dtype=dtype)
        state = state + mean.mean(1).to(state.dtype)
        if schedule is not None:
            state = torch.where(torch.isnan(schedule[:, :, t]), state, schedule[:, :, t])
        states.append(state)
    return torch.stack(states, dim=2)
