"""benchmarks/shapley_credit_at_merge.py (issue 32): the critic's credit for one CAV's move is
the difference of exact Shapley values, it collapses to the own effect in an additive game,
and a trained Shapley run is read end to end (a run of another recipe refused before any
work)."""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path
from types import ModuleType, SimpleNamespace

import numpy as np
import pytest
import torch

from mapets_rl.shapley import CoalitionCritic, exact_shapley

ROOT = Path(__file__).resolve().parents[2]
N, OBS_DIM, ACTIONS = 4, 3, 4


@pytest.fixture
def credit(load_script: Callable[[str], ModuleType], monkeypatch) -> ModuleType:
    monkeypatch.syspath_prepend(str(ROOT / "benchmarks"))  # cooperation_control & co.
    return load_script("benchmarks/shapley_credit_at_merge.py")


def scene(seed: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Two states of ``N`` CAVs: observations, greedy decisions (Keep Lane), the movers and
    their moves (Change Left, Change Right)."""
    generator = torch.Generator().manual_seed(seed)
    observation = torch.randn(2, N, OBS_DIM, generator=generator)
    greedy = torch.zeros(2, N, dtype=torch.long)
    return observation, greedy, torch.tensor([1, 3]), torch.tensor([1, 2])


def test_the_critics_credit_is_the_difference_of_exact_shapley_values(
    credit: ModuleType,
) -> None:
    torch.manual_seed(0)
    critic = CoalitionCritic(N, OBS_DIM, ACTIONS, num_cells=[16, 16])
    exp = SimpleNamespace(critic=critic, config=SimpleNamespace(reward_scale=2.0))
    observation, greedy, cav, move = scene(1)
    out = credit.critic_deltas(exp, observation, greedy, cav, move, permutations=4000)
    keep = torch.nn.functional.one_hot(greedy, ACTIONS).float()
    moved = keep.clone()
    moved[torch.arange(2), cav] = torch.nn.functional.one_hot(move, ACTIONS).float()
    with torch.no_grad():
        phi = {
            name: exact_shapley(critic.all_coalition_values(observation, action), N) / 2.0
            for name, action in (("keep", keep), ("move", moved))
        }
        grand = torch.ones(2, 1, N, dtype=torch.bool)
        v_grand = critic.coalition_values(observation, keep, grand)[:, 0] / 2.0
    exact = (phi["move"] - phi["keep"])[torch.arange(2), cav]
    torch.testing.assert_close(out["critic_credit"], exact, atol=0.02 * exact.abs().max(), rtol=0)
    torch.testing.assert_close(out["critic_v_grand"], v_grand)
    # a game that is not additive: one CAV's effect depends on who else is in the coalition
    assert not torch.allclose(out["critic_own"], out["critic_system"], atol=1e-4)


def test_an_additive_critic_credits_the_own_effect(credit: ModuleType) -> None:
    """Every hidden unit active (ReLU = identity): ``v(C)`` is affine in the members'
    embeddings, so a move changes ``v({i})``, ``phi_i`` and ``v(N)`` alike."""
    torch.manual_seed(0)
    critic = CoalitionCritic(N, OBS_DIM, ACTIONS, num_cells=[8])
    with torch.no_grad():
        for layer in critic.head.modules():
            if isinstance(layer, torch.nn.Linear):
                layer.bias.fill_(100.0)
        critic.bias.fill_(100.0)
    exp = SimpleNamespace(critic=critic, config=SimpleNamespace(reward_scale=1.0))
    out = credit.critic_deltas(exp, *scene(2), permutations=8)
    assert out["critic_own"].abs().min() > 1e-3
    torch.testing.assert_close(out["critic_credit"], out["critic_own"], atol=1e-4, rtol=1e-4)
    torch.testing.assert_close(out["critic_system"], out["critic_own"], atol=1e-4, rtol=1e-4)


def test_a_trained_shapley_run_is_read_and_another_recipe_refused(
    credit: ModuleType, load_script: Callable[[str], ModuleType], tmp_path: Path, monkeypatch
) -> None:
    """Read end to end, with the Shapley run's greedy decisions replaced by Keep Lane (a
    40-frame policy rarely keeps its lane where the rule moves): the rule's moves are found,
    replayed, and their credit reference is the mean of own and system effects."""
    from freeway_headroom import CooperativeMerge  # benchmarks/, on the path via the fixture

    real = credit.deciding

    def keep_lane_unless_rule(policy):
        if isinstance(policy, CooperativeMerge):
            return real(policy)
        return lambda observation: torch.zeros(observation.shape[:-1], dtype=torch.long)

    monkeypatch.setattr(credit, "deciding", keep_lane_unless_rule)
    control = load_script("benchmarks/cooperation_control.py")
    tiny = ["--seeds", "0", "--frames", "40", "--train-roads", "4", "--eval-roads", "2"]
    for variant in ("shapley_shield_w1", "maddpg_shield_w1"):
        control.main(["--variants", variant, *tiny, "--n-vehicles", "8", "--out", str(tmp_path)])
    runs = tmp_path / "runs"
    out = tmp_path / "credit"
    with pytest.raises(SystemExit):
        credit.main(["--runs", str(runs / "maddpg_shield_w1_seed0"), "--out", str(out)])
    assert not out.exists()  # refused before any work
    argv = ["--runs", str(runs / "shapley_shield_w1_seed0"), "--roads", "8", "--out", str(out)]
    table = credit.main([*argv, "--maddpg", str(runs / "maddpg_shield_w1_seed0")])
    assert "| shapley_shield_w1_seed0 |" in table
    assert (out / "credit_8roads.md").read_text() == table + "\n"
    path = out / "shapley_shield_w1_seed0_8roads_vs_maddpg_shield_w1_seed0.json"
    data = {k: np.asarray(v) for k, v in json.loads(path.read_text()).items()}
    assert data["moved"].any() and len({v.size for v in data.values()}) == 1
    np.testing.assert_allclose(data["reference_credit"], (data["own"] + data["system"]) / 2)
    assert np.isfinite(data["maddpg_own"]).all() and np.isfinite(data["critic_credit"]).all()
    assert ((data["move_prob"] > 0) & (data["move_prob"] < 1)).all()
