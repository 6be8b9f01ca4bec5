"""make_advantage_q_critic: Q_i(o, a) = V_i(o) + A_i(o_i, a_i) - A_i(o_i, b)."""

import pytest
import torch
from tensordict import TensorDict
from torchrl.data import Bounded, OneHot

from mapets_rl.modules import AgentGroupSpec
from mapets_rl.modules.advantage_critic import ADVANTAGE, make_advantage_q_critic
from mapets_rl.modules.critic_probe import critic_advantages
from mapets_rl.modules.keys import ACTION, OBS, Q_VALUE, VALUE

AGENTS, OBS_DIM, N = 3, 5, 4


def _spec(discrete: bool = True) -> AgentGroupSpec:
    action = (OneHot(N, shape=(AGENTS, N)) if discrete
              else Bounded(-1.0, 1.0, shape=(AGENTS, 1)))  # fmt: skip
    return AgentGroupSpec(AGENTS, OBS_DIM, action, discrete, N if discrete else 1)


def _td(observation: torch.Tensor, index: torch.Tensor) -> TensorDict:
    action = torch.nn.functional.one_hot(index, N).float()
    return TensorDict({OBS: observation, ACTION: action}, batch_size=observation.shape[:1])


@pytest.mark.parametrize("centralized", [True, False])
@pytest.mark.parametrize("share", [True, False])
def test_the_baseline_action_scores_the_value_and_a_move_only_its_own_advantage(
    centralized: bool, share: bool
) -> None:
    torch.manual_seed(0)
    critic = make_advantage_q_critic(_spec(), [16], centralized=centralized,
                                     share_params=share, baseline_action=2)  # fmt: skip
    observation = torch.randn(6, AGENTS, OBS_DIM)
    baseline = critic(_td(observation, torch.full((6, AGENTS), 2)))
    torch.testing.assert_close(baseline.get(Q_VALUE), baseline.get(VALUE))
    assert torch.equal(baseline.get(ADVANTAGE)[..., 2], torch.zeros(6, AGENTS))
    index = torch.randint(N, (6, AGENTS))
    moved = critic(_td(observation, index))
    want = (
        baseline.get(VALUE)[..., 0] + baseline.get(ADVANTAGE).gather(-1, index[..., None])[..., 0]
    )
    torch.testing.assert_close(moved.get(Q_VALUE)[..., 0], want)


def test_an_agents_q_ignores_the_other_agents_actions_and_the_probe_reads_its_advantage() -> None:
    torch.manual_seed(1)
    critic = make_advantage_q_critic(_spec(), [16], centralized=True, share_params=False,
                                     baseline_action=0)  # fmt: skip
    observation = torch.randn(2, AGENTS, OBS_DIM)
    played = torch.zeros(2, AGENTS, dtype=torch.long)
    others = played.clone()
    others[:, 1:] = 3
    q_played = critic(_td(observation, played)).get(Q_VALUE)[:, 0]
    q_others = critic(_td(observation, others)).get(Q_VALUE)[:, 0]
    torch.testing.assert_close(q_played, q_others)
    road, agent, move = torch.tensor([0, 1]), torch.tensor([0, 2]), torch.tensor([1, 3])
    got = critic_advantages(critic, observation, played, road, agent, move, N)
    advantage = critic(_td(observation, played)).get(ADVANTAGE)
    torch.testing.assert_close(got, advantage[road, agent, move])


def test_bad_input_is_refused() -> None:
    with pytest.raises(ValueError, match="baseline_action must be in \\[0, 4\\)"):
        make_advantage_q_critic(_spec(), [8], centralized=True, share_params=True,
                                baseline_action=4)  # fmt: skip
    with pytest.raises(ValueError, match="discrete"):
        make_advantage_q_critic(_spec(False), [8], centralized=True, share_params=True,
                                baseline_action=0)  # fmt: skip
