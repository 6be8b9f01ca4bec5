"""A custom scenario: the smallest torchrl env with the multi-agent ``"agents"`` layout.

I agents on a line; each should drive its position x to 0. Per agent: observation (x, t/H)
``[I, 2]``, position (x, 0) ``[I, 2]`` (so ``mapets_rl.comm.CommunicationRange`` can link the
agents), action ``[I, 1]`` in [-1, 1], x' = x + 0.5 a + 0.05 noise, reward -x'^2; the episode is
truncated after H steps.

Make it a scenario of this process with ``register_env("toy", ToyAgentsEnv)``, or of every
process (``mapets-rl resume`` included) with an entry point in your package's
``pyproject.toml``::

    [project.entry-points."mapets_rl.scenarios"]
    toy = "toy_scenario:ToyAgentsEnv"

Run it to see one short rollout with a communication graph:

    python examples/extending/toy_scenario.py [--steps 5]
"""

from __future__ import annotations

import argparse

import torch
from tensordict import TensorDict
from torchrl.data import Bounded, Categorical, Composite, Unbounded
from torchrl.envs import EnvBase


class ToyAgentsEnv(EnvBase):
    """``n_agents`` agents on a line, episodes of ``horizon`` steps (see the module docstring)."""

    def __init__(self, n_agents: int = 3, horizon: int = 10) -> None:
        super().__init__(batch_size=torch.Size([]))
        self.n_agents, self.horizon = n_agents, horizon
        i = n_agents
        self.observation_spec = Composite(
            agents=Composite(observation=Unbounded((i, 2)), position=Unbounded((i, 2)), shape=(i,))
        )
        self.action_spec = Composite(
            agents=Composite(action=Bounded(-1.0, 1.0, (i, 1)), shape=(i,))
        )
        self.reward_spec = Composite(agents=Composite(reward=Unbounded((i, 1)), shape=(i,)))
        flag = Categorical(2, (i, 1), dtype=torch.bool)
        self.done_spec = Composite(
            agents=Composite(done=flag, terminated=flag.clone(), shape=(i,)),
            done=Categorical(2, (1,), dtype=torch.bool),
            terminated=Categorical(2, (1,), dtype=torch.bool),
            truncated=Categorical(2, (1,), dtype=torch.bool),
        )
        self.rng = torch.Generator().manual_seed(0)

    def _set_seed(self, seed: int | None) -> None:
        self.rng.manual_seed(int(seed or 0))

    def _agents(self, done: bool, reward: torch.Tensor | None = None) -> TensorDict:
        t = torch.full((self.n_agents, 1), self.t / self.horizon)
        flags = torch.full((self.n_agents, 1), done)
        agents = {
            "observation": torch.cat([self.x, t], -1),
            "position": torch.cat([self.x, torch.zeros_like(self.x)], -1),
            "done": flags,
            "terminated": torch.zeros_like(flags),
        }
        if reward is not None:
            agents["reward"] = reward
        return TensorDict(agents, [self.n_agents])

    def _reset(self, td=None) -> TensorDict:
        self.t = 0
        self.x = torch.rand(self.n_agents, 1, generator=self.rng) * 4 - 2
        false = torch.zeros(1, dtype=torch.bool)
        return TensorDict(
            {
                "agents": self._agents(False),
                "done": false,
                "terminated": false.clone(),
                "truncated": false.clone(),
            }
        )

    def _step(self, td: TensorDict) -> TensorDict:
        a = td["agents", "action"].clamp(-1, 1)
        self.x = self.x + 0.5 * a + 0.05 * torch.randn(self.x.shape, generator=self.rng)
        self.t += 1
        trunc = torch.tensor([self.t >= self.horizon])
        return TensorDict(
            {
                "agents": self._agents(bool(trunc), reward=-self.x.pow(2)),
                "done": trunc,
                "truncated": trunc.clone(),
                "terminated": torch.zeros(1, dtype=torch.bool),
            }
        )


def main() -> None:
    from torchrl.envs import TransformedEnv
    from torchrl.envs.utils import check_env_specs

    from mapets_rl.comm import CommunicationRange

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=5, help="rollout length")
    args = parser.parse_args()
    env = TransformedEnv(ToyAgentsEnv(n_agents=3), CommunicationRange(1.0))
    check_env_specs(env)
    rollout = env.rollout(args.steps)
    links = rollout["next", "agents", "neighbors"].sum((-1, -2)) // 2
    print(f"positions x at the last step: {rollout['next', 'agents', 'position'][-1, :, 0]}")
    print(f"links within 1.0 per step: {links.tolist()}")
    print(f"return per agent: {rollout['next', 'agents', 'reward'].sum(0).squeeze(-1).tolist()}")


if __name__ == "__main__":
    main()
