"""critic_advantages: a critic's Q of one agent's move against the joint action as played."""

import pytest
import torch
from tensordict.nn import TensorDictModule

from mapets_rl.modules.critic_probe import critic_advantages
from mapets_rl.modules.keys import ACTION, OBS, Q_VALUE

ACTION_WORTH = torch.tensor([0.0, 2.0, -1.0, 5.0])


def joint_worth(observation: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
    """Q_i = (1 + i) * (sum_j worth(a_j) + sum of o_i): ``[*, I, obs], [*, I, 4] -> [*, I, 1]``."""
    worth = (action * ACTION_WORTH).sum((-1, -2))
    scale = torch.arange(1, observation.shape[-2] + 1, dtype=observation.dtype)
    return (scale * (worth[..., None] + observation.sum(-1)))[..., None]


CRITIC = TensorDictModule(joint_worth, in_keys=[OBS, ACTION], out_keys=[Q_VALUE])


def test_known_answer_per_question():
    observation = torch.randn(3, 4, 5)
    action = torch.tensor([[0, 0, 1, 2], [3, 0, 0, 0], [2, 2, 2, 2]])
    road = torch.tensor([0, 0, 1, 2, 2])
    agent = torch.tensor([0, 2, 0, 3, 1])
    replacement = torch.tensor([1, 3, 1, 0, 2])
    got = critic_advantages(CRITIC, observation, action, road, agent, replacement, 4)
    # (1 + agent) * (worth(new) - worth(old)); the observation term cancels
    want = torch.tensor([1 * 2.0, 3 * (5.0 - 2.0), 1 * (2.0 - 5.0), 4 * (0.0 + 1.0), 0.0])
    torch.testing.assert_close(got, want)


def test_replacing_by_the_played_action_is_zero():
    observation = torch.randn(2, 3, 4)
    action = torch.tensor([[1, 0, 3], [2, 2, 0]])
    road, agent = torch.tensor([0, 1, 1]), torch.tensor([2, 0, 1])
    got = critic_advantages(CRITIC, observation, action, road, agent, action[road, agent], 4)
    assert torch.equal(got, torch.zeros(3))


def test_mismatched_questions_are_refused():
    with pytest.raises(ValueError, match="road, agent and replacement"):
        critic_advantages(
            CRITIC, torch.zeros(1, 2, 3), torch.zeros(1, 2, dtype=torch.long),
            torch.zeros(2, dtype=torch.long), torch.zeros(1, dtype=torch.long),
            torch.zeros(2, dtype=torch.long), 4,
        )  # fmt: skip
    with pytest.raises(ValueError, match=r"action \[R, I\]"):
        critic_advantages(
            CRITIC, torch.zeros(1, 2, 3), torch.zeros(2, 2, dtype=torch.long),
            torch.zeros(1, dtype=torch.long), torch.zeros(1, dtype=torch.long),
            torch.zeros(1, dtype=torch.long), 4,
        )  # fmt: skip
