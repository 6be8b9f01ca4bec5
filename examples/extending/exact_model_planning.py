"""A custom planner model: MA-PETS's CEM planner on a hand-written, exact dynamics model.

:class:`mapets_rl.planning.TrajectorySamplingCEM` plans through any
:class:`mapets_rl.planning.DynamicsModel`, not only a learned ensemble: an object with
``n_agents``, ``obs_dim``, ``action_dim``, ``ensemble_size`` and ``predict(obs, action, dtype)``
returning the mean and log-variance of the next-state delta, shapes ``[I, B, N, S]``. Here
each agent is a point mass (obs = position, velocity; action = acceleration) whose model is
exact (one member, log-variance -60: no noise). The known reward and termination are plain
vectorised functions of ``(obs, action, next_obs)``.

Run it to plan one action per agent and step the exact model forward:

    python examples/extending/exact_model_planning.py [--steps 10]
"""

from __future__ import annotations

import argparse

import torch

from mapets_rl.planning import DynamicsModel, TrajectorySamplingCEM

DT = 0.1  # seconds per step
WALL = 3.0  # |position| beyond this ends the trajectory (a crash)


class ExactPointMass:
    """``n_agents`` point masses: position' = position + dt velocity, velocity' = velocity +
    dt acceleration; exact, so a single member (``ensemble_size = 1``) with ~zero variance."""

    obs_dim, action_dim, ensemble_size = 2, 1, 1

    def __init__(self, n_agents: int) -> None:
        self.n_agents = n_agents

    def predict(self, obs, action, dtype=torch.float32):
        mean = torch.cat([DT * obs[..., 1:2], DT * action], dim=-1)
        return mean, torch.full_like(mean, -60.0)


def reward_fn(obs, action, next_obs):
    """Stay near position 0, slowly and gently: -(position^2 + 0.1 velocity^2 + 0.01 a^2)."""
    pos, vel = next_obs[..., 0], next_obs[..., 1]
    return -(pos.pow(2) + 0.1 * vel.pow(2) + 0.01 * action.pow(2).sum(-1))


def termination_fn(obs, action, next_obs):
    """A particle that leaves [-WALL, WALL] has crashed: its later rewards do not count."""
    return next_obs[..., 0].abs() > WALL


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=10, help="planning steps to execute")
    args = parser.parse_args()
    model = ExactPointMass(n_agents=2)
    assert isinstance(model, DynamicsModel)  # a structural check: no base class needed
    planner = TrajectorySamplingCEM(
        model,
        reward_fn,
        action_low=-2.0,
        action_high=2.0,
        termination_fn=termination_fn,
        horizon=10,
        population=200,
        elites=20,
        iterations=5,
        particles=1,
        seed=0,
    )
    obs = torch.tensor([[2.0, 0.0], [-1.0, 1.0]])  # agent 0 far right, agent 1 heading away
    for step in range(args.steps):
        action = planner.plan(obs)
        print(f"step {step}: position {obs[:, 0].tolist()} action {action[:, 0].tolist()}")
        delta, _ = model.predict(obs[:, None, None], action[:, None, None])
        obs = obs + delta[:, 0, 0]
    print(f"final position {obs[:, 0].tolist()} velocity {obs[:, 1].tolist()}")


if __name__ == "__main__":
    main()
