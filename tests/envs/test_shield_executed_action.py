"""Learning from the action that ran (issue 50): under the shield the batched freeway's step
leaves the executed action under ``("agents", "action")`` and the proposed one under
``("agents", "proposed_action")``, as a collector stores them in a replay buffer."""

from __future__ import annotations

import pytest
import torch
from tensordict.nn import TensorDictModule
from torchrl.collectors import Collector
from torchrl.data import LazyTensorStorage, ReplayBuffer
from torchrl.envs.utils import check_env_specs

from mapets_rl.envs import make_env
from mapets_rl.envs.freeway import CL, KL
from mapets_rl.envs.torch_freeway.env import ACTION, PROPOSED_ACTION
from mapets_rl.envs.torch_freeway.geometry import RAMP_SEGMENT
from mapets_rl.experiment.shield_punishment import punish_shielded_moves

SHIELDED = ("next", "agents", "info", "shielded")


def _env(categorical: bool, shield: bool = True, roads: int = 2):
    return make_env("freeway-merge", backend="torch", num_envs=roads, seed=0, shield=shield,
                    categorical_actions=categorical)  # fmt: skip


class ChangeLeft(torch.nn.Module):
    """Every CAV plays Change Left (many such moves crash, so the shield replaces them); one-hot
    actions are float, as MADDPG's actor writes them."""

    def __init__(self, categorical: bool) -> None:
        super().__init__()
        self.categorical = categorical

    def forward(self, observation: torch.Tensor) -> torch.Tensor:
        index = torch.full(observation.shape[:-1], CL)
        return index if self.categorical else torch.nn.functional.one_hot(index, 4).float()


def _index(action: torch.Tensor, categorical: bool) -> torch.Tensor:
    return action if categorical else action.argmax(-1)


@pytest.mark.parametrize("categorical", [False, True])
def test_the_replay_buffer_holds_keep_lane_where_the_shield_replaced_a_move(
    categorical: bool,
) -> None:
    env = _env(categorical)
    check_env_specs(env)
    assert env.full_state_spec[PROPOSED_ACTION] == env.full_action_spec[ACTION]
    policy = TensorDictModule(
        ChangeLeft(categorical), in_keys=[("agents", "observation")], out_keys=[ACTION]
    )
    # one device for policy and env, as the experiment runner's collectors have
    collector = Collector(env, policy, frames_per_batch=6, total_frames=6, device="cpu",
                          auto_register_policy_transforms=False)  # fmt: skip
    buffer = ReplayBuffer(storage=LazyTensorStorage(16))
    for batch in collector:
        buffer.extend(batch.reshape(-1))
    collector.shutdown()
    data = buffer[:]
    assert len(buffer) == 6
    executed = _index(data.get(ACTION), categorical)
    proposed = _index(data.get(PROPOSED_ACTION), categorical)
    replaced = data.get(SHIELDED) > 0
    assert bool((proposed == CL).all())
    assert 0 < int(replaced.sum()) < replaced.numel()
    assert bool((executed[replaced] == KL).all())
    assert torch.equal(executed[~replaced], proposed[~replaced])
    assert data.get(ACTION).shape == data.get(PROPOSED_ACTION).shape
    assert data.get(PROPOSED_ACTION).dtype == env.full_action_spec[ACTION].dtype


def test_the_executed_action_replays_the_shielded_step_without_the_shield() -> None:
    """The stored action is the one that ran: stepping the same roads unshielded with it gives
    the shielded step's observations and rewards. The slanted ramp's Change Left (the scenario
    counts it as Keep Lane) is stored as played."""
    shielded, plain = _env(False, roads=4), _env(False, shield=False, roads=4)
    td = shielded.reset()
    replaced_any = False
    for _ in range(3):
        snapshot = shielded.snapshot()
        sim = shielded.sim
        lane = sim.state["bodies", "lane"].gather(1, sim.state["agents", "slot"])
        on_slanted_ramp = sim.geometry.segment[lane] == RAMP_SEGMENT
        td.set(ACTION, torch.nn.functional.one_hot(torch.full((4, 30), CL), 4))
        td = shielded.step(td)
        replaced = td.get(SHIELDED) > 0
        replaced_any |= bool(replaced.any())
        assert bool((td.get(ACTION).argmax(-1)[on_slanted_ramp & ~replaced] == CL).all())
        assert bool(on_slanted_ramp.any())
        plain.restore(snapshot)
        again = plain.step(td.select(ACTION).clone())
        for key in (("next", "agents", "observation"), ("next", "agents", "reward")):
            assert torch.equal(again.get(key), td.get(key)), key
        td = td.get("next")
    assert replaced_any


def test_without_the_shield_the_action_is_left_as_proposed() -> None:
    env = _env(False, shield=False)
    assert PROPOSED_ACTION not in env.full_state_spec.keys(True, True)
    td = env.reset()
    action = torch.nn.functional.one_hot(torch.full((2, 30), CL), 4)
    td.set(ACTION, action)
    td = env.step(td)
    assert td.get(ACTION) is action and PROPOSED_ACTION not in td.keys(True, True)


@pytest.mark.parametrize("categorical", [False, True])
def test_punished_transitions_hold_the_proposal_and_the_lowered_reward(categorical: bool) -> None:
    """``punish_shielded_moves`` (post-posed shielding with punishment): where the shield
    replaced a move the transition holds the proposal and the reward minus the penalty; the
    other agents' rows, the next state and the input batch are unchanged; a negative penalty
    and a batch without proposals are refused."""
    env = _env(categorical)
    td = env.reset()
    td.set(ACTION, ChangeLeft(categorical)(td.get(("agents", "observation"))))
    batch = env.step(td)
    before = batch.clone()
    out = punish_shielded_moves(batch, 2.5)
    replaced = batch.get(SHIELDED) > 0  # [roads, I]
    assert 0 < int(replaced.sum()) < replaced.numel()
    assert torch.equal(out.get(ACTION), batch.get(PROPOSED_ACTION))
    reward, punished = (
        batch.get(("next", "agents", "reward")),
        out.get(("next", "agents", "reward")),
    )
    torch.testing.assert_close(punished[replaced], reward[replaced] - 2.5)
    assert torch.equal(punished[~replaced], reward[~replaced])
    key = ("next", "agents", "observation")
    assert torch.equal(out.get(key), batch.get(key))
    assert (batch == before).all()
    with pytest.raises(ValueError, match="shield_penalty must be >= 0"):
        punish_shielded_moves(batch, -1.0)
    with pytest.raises(ValueError, match="needs the shield's proposals"):
        punish_shielded_moves(batch.exclude(PROPOSED_ACTION), 1.0)
