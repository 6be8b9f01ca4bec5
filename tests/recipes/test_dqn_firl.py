"""The dqn and firl recipes: the double-DQN loss's known answer on a constructed batch, tiny
runs through ``mapets-rl train`` on both figure-eights, exact resume, FIRL's learners equal
after an averaging and its bytes logged, bad input refused."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModule, TensorDictSequential
from torch import nn
from torchrl.data import OneHot

from mapets_rl.experiment import ConfigError
from mapets_rl.modules import ACTION_VALUE, DONE, OBS, REWARD, TERMINATED
from mapets_rl.modules.action_map import ACTION_CHOICE
from mapets_rl.recipes.dqn import CHOSEN_VALUE, DQN, DQNConfig, greedy_choice, make_dqn_loss
from mapets_rl.recipes.firl import FIRL, FIRLConfig
from tests.cli_run import run_cli

TINY = [
    "env_config.n_cavs=3",
    "env_config.n_hvs=2",
    "env_config.horizon=20",
    "total_frames=60",
    "frames_per_batch=20",
    "eval_interval=0",
    "checkpoint_interval=0",
    "logger=none",
    "progress=false",
]
TINY_RECIPE = {
    "dqn": ["batch_size=16", "init_random_frames=20", "updates_per_batch=2"],
    "firl": ["minibatch_size=10", "epochs=2", "averaging_period=3"],
}


def test_double_dqn_target_takes_the_online_argmax_valued_by_the_target_net() -> None:
    """Q(o) = W o with K = 3 actions, 2 agents, one transition. Online W = I; the target net
    swaps actions 0 and 1. Agent 0: o = e_0, a = 0, r = 1, o' = (1, 3, 2), not terminated: the
    online net picks action 1 at o', the target net values it Q_t(o', 1) = o'_0 = 1 (its own
    max would be 3), so y = 1 + 0.9 * 1 = 1.9 against Q(o, 0) = 1. Agent 1: o = (0, 2, 0),
    a = 1, r = 0.5, terminated: y = 0.5 against Q(o, 1) = 2. Loss: mean of squared errors
    (0.81 + 2.25) / 2."""
    linear = nn.Linear(3, 3, bias=False)
    with torch.no_grad():
        linear.weight.copy_(torch.eye(3))
    network = TensorDictSequential(
        TensorDictModule(linear, in_keys=[OBS], out_keys=[ACTION_VALUE]), greedy_choice()
    )
    loss = make_dqn_loss(network, OneHot(3, shape=(2, 3)), gamma=0.9)
    swap = torch.tensor([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    loss.target_value_network_params.get(("module", "0", "module", "weight")).data.copy_(swap)
    batch = TensorDict(
        {
            OBS: torch.tensor([[[1.0, 0.0, 0.0], [0.0, 2.0, 0.0]]]),
            ACTION_CHOICE: torch.tensor([[[1, 0, 0], [0, 1, 0]]]),
            "next": {
                OBS: torch.tensor([[[1.0, 3.0, 2.0], [5.0, 0.0, 0.0]]]),
                REWARD: torch.tensor([[[1.0], [0.5]]]),
                DONE: torch.tensor([[[False], [True]]]),
                TERMINATED: torch.tensor([[[False], [True]]]),
            },
        },
        batch_size=[1],
    )
    assert loss(batch)["loss"].item() == pytest.approx((0.9**2 + 1.5**2) / 2, rel=1e-6)
    # plain DQN's target would be the target net's own max: 1 + 0.9 * 3
    loss.double_dqn = False
    assert loss(batch)["loss"].item() == pytest.approx((2.7**2 + 1.5**2) / 2, rel=1e-6)


@pytest.mark.parametrize("env", ["figure-eight", "figure-eight-multilane"])
@pytest.mark.parametrize("recipe", ["dqn", "firl"])
def test_mapets_rl_train_runs_the_recipe(recipe: str, env: str, tmp_path: Path, capsys) -> None:
    run_dir = tmp_path / "run"
    argv = ["train", recipe, "--env", env, "--run-dir", str(run_dir), *TINY, *TINY_RECIPE[recipe]]
    code, out, err = run_cli(argv, capsys)
    assert code == 0, err
    results = json.loads((run_dir / "results.json").read_text())
    final = results["evaluations"][-1]
    assert final["frames"] == 60
    assert {"agility", "safety", "reward"} <= set(final["metrics"])
    assert all(torch.isfinite(torch.tensor(v)) for v in final["metrics"].values())


def test_dqn_learns_on_one_hot_actions_as_they_are(tmp_path: Path) -> None:
    """On the freeway (one-hot lane changes) the choice is the scenario's action itself."""
    config = DQNConfig(
        env="freeway",
        env_config={"n_vehicles": 4, "cav_ratio": 0.5},
        total_frames=60,
        frames_per_batch=20,
        batch_size=16,
        init_random_frames=20,
        updates_per_batch=2,
        eval_interval=0,
        checkpoint_interval=0,
        progress=False,
        logger="none",
    )
    exp = DQN(config, tmp_path / "run")
    before = _params(exp)
    exp.train()
    assert exp.loss.tensor_keys.action == ("agents", "action")
    assert ACTION_CHOICE not in exp.buffer.sample().keys(True)
    assert not torch.equal(before, _params(exp))


def _params(exp) -> torch.Tensor:
    return torch.cat([p.detach().flatten().clone() for p in exp.loss.parameters()])


@pytest.mark.parametrize(
    "cls, config_cls, extra",
    [
        (DQN, DQNConfig, {"batch_size": 16, "init_random_frames": 20, "updates_per_batch": 2}),
        (FIRL, FIRLConfig, {"minibatch_size": 10, "epochs": 2, "averaging_period": 3,
                            "comm": {"p_fail": 0.3}}),
    ],
)  # fmt: skip
def test_resume_matches_uninterrupted(cls, config_cls, extra, tmp_path: Path) -> None:
    def config(total: int):
        return config_cls(
            env="figure-eight",
            env_config={"n_cavs": 3, "n_hvs": 2, "horizon": 20},
            total_frames=total,
            frames_per_batch=20,
            eval_interval=20,
            checkpoint_interval=40,
            progress=False,
            logger="none",
            **extra,
        )

    full = cls(config(80), tmp_path / "full")
    expected = full.train()
    cls(config(40), tmp_path / "part").train()
    resumed = cls.from_run_dir(tmp_path / "part", overrides=["total_frames=80"])
    assert resumed.train() == expected
    assert torch.equal(_params(resumed), _params(full))


def test_firl_learners_are_equal_after_an_averaging_and_its_bytes_are_logged(
    tmp_path: Path,
) -> None:
    """2 epochs x 2 minibatches = 4 updates per batch, averaging every 4: every batch ends on
    an averaging, so the learners' parameters are equal; the bytes logged are the consensus
    rounds' and one averaging's."""
    config = FIRLConfig(
        env="figure-eight",
        env_config={"n_cavs": 3, "n_hvs": 2, "horizon": 20},
        total_frames=40,
        frames_per_batch=20,
        minibatch_size=10,
        epochs=2,
        averaging_period=4,
        eval_interval=0,
        checkpoint_interval=0,
        progress=False,
        logger="none",
    )
    exp = FIRL(config, tmp_path / "run")
    logs = []
    step = exp.train_step
    exp.train_step = lambda batch: logs.append(step(batch)) or logs[-1]
    exp.train()
    for param in exp.loss.parameters():
        assert param.shape[0] == 3
        assert torch.equal(param, param[:1].expand_as(param))
    message = exp.federation.message_bytes
    for log in logs:
        assert log["bytes_averaging"] == 2 * 3 * message
        assert log["bytes_consensus"] % message == 0  # whole gradients, one per link
        assert log["bytes_shared"] == log["bytes_consensus"] + log["bytes_averaging"]


@pytest.mark.parametrize(
    "config_cls, overrides, match",
    [
        (DQNConfig, ["speed_levels=1"], "speed_levels must be >= 2"),
        (DQNConfig, ["lr_actor=0.1"], "lr_actor must be left out"),
        (DQNConfig, ["epsilon_end=0.5", "epsilon_init=0.2"], r"epsilon_end must be in \[0, "),
        (FIRLConfig, ["share_params=true"], "share_params must be false"),
        (FIRLConfig, ["averaging_period=0"], "averaging_period must be >= 1"),
        (FIRLConfig, ["consensus_rounds=-1"], "consensus_rounds must be >= 0"),
        (FIRLConfig, ["comm.share_plans=true"], "comm.share_plans must be false"),
        (FIRLConfig, ["collector_workers=2"], "collector_workers must be 1 .firl's learner i"),
    ],
)
def test_bad_config_is_refused_naming_the_field(config_cls, overrides, match: str) -> None:
    with pytest.raises(ConfigError, match=match):
        config_cls().with_overrides(overrides)


def test_tied_action_values_choose_one_action_the_first_of_the_best() -> None:
    """torchrl's one-hot QValueModule marks every tied action; the greedy choice here marks
    one, so the figure-eight's action map never sums two target speeds and the chosen value is
    the best value, not a sum."""
    values = torch.tensor([[[1.0, 3.0, 3.0, 0.0], [2.0, 2.0, 2.0, 2.0]]])
    td = greedy_choice()(TensorDict({ACTION_VALUE: values}, batch_size=[1]))
    choice = td.get(ACTION_CHOICE)
    assert torch.equal(choice, torch.tensor([[[0, 1, 0, 0], [1, 0, 0, 0]]]))
    assert torch.equal(td.get(CHOSEN_VALUE), torch.tensor([[[3.0], [2.0]]]))
