"""The Shapley arm's fast path: the actor loss computes full Shapley values on ``value_states``
states only (the gradient is the same), and Shapley AC's actor can be MADDPG's (own
observation, normalised), so the two arms differ in the critic and the credit only."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch
from tensordict import TensorDict
from torch import nn

from mapets_rl.modules import RunningObsNorm
from mapets_rl.objectives import ShapleyActorCriticLoss
from mapets_rl.recipes.maddpg import MADDPG, MADDPGConfig
from mapets_rl.recipes.shapley_ac import ShapleyAC, ShapleyACConfig
from mapets_rl.shapley import CoalitionCritic, make_coalition_actor

N, OBS, ACT, B = 12, 3, 4, 10  # N > exact_max_agents: the sampled path


def _batch() -> TensorDict:
    g = torch.Generator().manual_seed(0)
    action = torch.nn.functional.one_hot(torch.randint(ACT, (B, N), generator=g), ACT).float()
    return TensorDict(
        {
            ("agents", "observation"): torch.randn(B, N, OBS, generator=g),
            ("agents", "action"): action,
            ("agents", "coalition"): torch.rand(B, N, generator=g) > 0.4,
        },
        [B],
    )


def _actor_loss(value_states: int | None) -> tuple[torch.Tensor, dict, list[torch.Tensor]]:
    torch.manual_seed(0)
    actor = make_coalition_actor(N, OBS, ACT, discrete=True, num_cells=(16,))
    critic = CoalitionCritic(N, OBS, ACT, num_cells=(16,), member_heads=True)
    loss = ShapleyActorCriticLoss(
        actor, critic, num_permutations=8, chunk_states=4, value_states=value_states
    )
    torch.manual_seed(1)  # the same orderings for both
    value, meta = loss.loss_actor(_batch())
    value.backward()
    params = loss.actor_network_params.values(True, True)
    return value, meta, [torch.zeros_like(p) if p.grad is None else p.grad for p in params]


def test_skipping_the_coalitions_without_the_agent_keeps_the_gradient() -> None:
    full, full_meta, full_grads = _actor_loss(None)
    part, part_meta, part_grads = _actor_loss(3)  # chunks of 4: the first 4 states valued
    for a, b in zip(full_grads, part_grads, strict=True):
        assert torch.allclose(a, b, atol=1e-6)
    torch.manual_seed(0)
    actor = make_coalition_actor(N, OBS, ACT, discrete=True, num_cells=(16,))
    critic = CoalitionCritic(N, OBS, ACT, num_cells=(16,), member_heads=True)
    reference = ShapleyActorCriticLoss(actor, critic, num_permutations=8, chunk_states=4)
    torch.manual_seed(1)
    phi, stderr = reference.shapley_values(_batch(), return_stderr=True)
    assert full_meta["shapley_value"] == pytest.approx(phi.mean().item(), abs=1e-6)
    assert part_meta["shapley_value"] == pytest.approx(phi[:4].mean().item(), abs=1e-6)
    assert part_meta["shapley_stderr"] == pytest.approx(stderr[:4].mean().item(), abs=1e-6)
    assert part.item() == pytest.approx(-phi[:4].mean().item() + (full.item() + phi.mean().item()),
                                        abs=1e-5)  # fmt: skip


@pytest.mark.parametrize("bad", [0, -2, True, 1.5])
def test_value_states_is_checked(bad) -> None:
    actor = make_coalition_actor(N, OBS, ACT, discrete=True, num_cells=(16,))
    critic = CoalitionCritic(N, OBS, ACT, num_cells=(16,))
    with pytest.raises(ValueError, match="value_states must be None or an int >= 1"):
        ShapleyActorCriticLoss(actor, critic, value_states=bad)


def _first_linear(module: nn.Module) -> nn.Linear:
    return next(m for m in module.modules() if isinstance(m, nn.Linear))


def test_shapley_acs_own_view_actor_is_maddpgs(tmp_path: Path) -> None:
    common = dict(
        env="freeway-merge",
        env_config={"backend": "torch", "num_envs": 2, "n_vehicles": 6, "cav_ratio": 1.0},
        frames_per_batch=20,
        total_frames=40,
        num_cells=[16, 16],
        progress=False,
        logger="none",
    )
    maddpg = MADDPG(MADDPGConfig(**common), tmp_path / "m")
    shapley = ShapleyAC(
        ShapleyACConfig(**common, actor_view="own", normalize_obs=True, critic_cells=[16]),
        tmp_path / "s",
    )
    paper = ShapleyAC(ShapleyACConfig(**common, critic_cells=[16]), tmp_path / "p")
    widths = [_first_linear(exp.actor).in_features for exp in (maddpg, shapley, paper)]
    assert widths == [24, 24, 6 * (24 + 1)]  # own observation; coalition view with flags
    for exp in (maddpg, shapley):
        assert any(isinstance(m, RunningObsNorm) for m in exp.actor.modules())
    assert not any(isinstance(m, RunningObsNorm) for m in paper.actor.modules())
    assert [type(m) for m in maddpg.actor.modules()] == [type(m) for m in shapley.actor.modules()]
    shapley.train()
    assert shapley.obs_norm.count > 0  # the statistics follow the collected observations


def test_a_shapley_run_made_before_the_actor_options_loads_as_it_trained() -> None:
    data = ShapleyACConfig(env="freeway").to_dict()
    for key in ("actor_view", "normalize_obs", "shapley_value_states"):
        del data[key]
    config = ShapleyACConfig.from_dict(ShapleyACConfig.upgrade_dict(data))
    assert (config.actor_view, config.normalize_obs, config.shapley_value_states) == (
        "coalition",
        False,
        None,
    )
