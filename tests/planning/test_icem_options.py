"""The CEM's iCEM options (anchor candidates, keep the best), the kinematic oracle model and the
time-headway collision margin."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from mapets_rl.envs import FigureEightPlannerReward
from mapets_rl.envs.figure_eight import FigureEightEnv
from mapets_rl.envs.figure_eight_kinematics import FigureEightKinematicModel
from mapets_rl.planning import CPU_PRESET, PAPER_PRESET, TrajectorySamplingCEM
from mapets_rl.planning.cem import ICEMOptimizer


def distance_to_low(candidates: torch.Tensor) -> torch.Tensor:
    """Score ``-sum (a - 0)^2``: the optimum is the constant sequence at the lower bound 0."""
    return -candidates.pow(2).sum(dim=(-1, -2))


def run_cem(anchors: bool, keep_best: bool, seed: int = 0) -> torch.Tensor:
    generator = torch.Generator().manual_seed(seed)
    cem = ICEMOptimizer(8, 2, 2, 1e-6, 0.1, generator, keep_best=keep_best)
    low, high = torch.zeros(1, 1, 1, 1), torch.ones(1, 1, 1, 1)
    mean = torch.full((1, 1, 10, 1), 0.5)
    fixed = low.expand(1, 1, 10, 1).unsqueeze(2) if anchors else None
    return cem.optimize(distance_to_low, mean, low, high, anchors=fixed)


def test_anchor_candidates_and_keep_best_return_an_optimum_the_samples_miss() -> None:
    exact = run_cem(anchors=True, keep_best=True)
    torch.testing.assert_close(exact, torch.zeros_like(exact))
    for anchors, keep_best in ((False, False), (False, True), (True, False)):
        assert distance_to_low(run_cem(anchors, keep_best)).item() < -1e-3


def test_keep_best_returns_the_best_scored_candidate() -> None:
    seen: list[tuple[torch.Tensor, torch.Tensor]] = []

    def score(candidates: torch.Tensor) -> torch.Tensor:
        scores = -(candidates - 0.3).abs().sum(dim=(-1, -2))
        seen.append((candidates, scores))
        return scores

    cem = ICEMOptimizer(16, 4, 3, 1e-6, 0.1, torch.Generator().manual_seed(1), keep_best=True)
    low, high = torch.zeros(1, 1, 1, 2), torch.ones(1, 1, 1, 2)
    best = cem.optimize(score, torch.full((1, 1, 5, 2), 0.5), low, high)
    candidates = torch.cat([c for c, _ in seen], dim=2)[0, 0]
    scores = torch.cat([s for _, s in seen], dim=2)[0, 0]
    torch.testing.assert_close(best[0, 0], candidates[scores.argmax()])


def test_cpu_preset_uses_the_icem_options_and_the_paper_preset_does_not() -> None:
    assert CPU_PRESET.planner.anchor_candidates and CPU_PRESET.planner.keep_best
    assert not PAPER_PRESET.planner.anchor_candidates and not PAPER_PRESET.planner.keep_best


def test_planner_with_anchors_finds_the_stop_when_every_sampled_plan_crashes() -> None:
    """A standing car 11.5 m ahead of a CAV at 10 m/s (stopping takes ~10.2 m): only braking
    at the limit from the first step keeps the 1 m margin."""
    model = FigureEightKinematicModel(n_agents=1, obs_dim=7, action_dim=1)
    obs = torch.tensor([[10.0, 0, 0, 0.0, 0, 11.5, 75]])  # a standing car 11.5 m ahead

    def crash(o, a, n):
        return n[..., 5] < 1.0

    def reward(o, a, n):
        return n[..., 0] - 100.0 * crash(o, a, n).float()

    kwargs = dict(horizon=25, population=8, elites=2, iterations=1, particles=1)
    kwargs["propagation"] = "expectation"
    planners = {
        icem: TrajectorySamplingCEM(
            model,
            reward,
            0.0,
            13.89,
            termination_fn=crash,
            seed=0,
            optimizer="icem" if icem else "cem",
            anchor_candidates=icem,
            keep_best=icem,
            **kwargs,
        )
        for icem in (False, True)
    }
    assert planners[True].plan(obs).item() == 0.0
    assert planners[False].plan(obs).item() > 1.0


def test_kinematic_model_predicts_the_cavs_own_motion_exactly() -> None:
    env = FigureEightEnv({"n_cavs": 1, "n_hvs": 0, "horizon": 60})
    obs, _ = env.reset(seed=3)
    model = FigureEightKinematicModel(1, 10, 1)
    rng = np.random.default_rng(0)
    for _ in range(50):
        action = rng.uniform(0, 13.89, size=(1, 1)).astype(np.float32)
        delta, logvar = model.predict(
            torch.from_numpy(obs)[:, None, None], torch.from_numpy(action)[:, None, None]
        )
        next_obs, *_ = env.step(action)
        predicted = obs + delta[:, 0, 0].numpy()
        np.testing.assert_allclose(predicted[0, 0], next_obs[0, 0], atol=1e-4)  # speed
        if 0 < obs[0, 7] < 70:  # crossing distance while approaching
            np.testing.assert_allclose(predicted[0, 7], next_obs[0, 7], atol=1e-3)
        assert (logvar == -30.0).all()
        obs = next_obs


def test_kinematic_model_gaps_follow_constant_speed_neighbours() -> None:
    model = FigureEightKinematicModel(1, 15, 2)
    obs = torch.tensor([[10.0, 0, 0, 12, 8, 20, 30, 75, 75, 0, 0, 9, 11, 40, 75]])
    delta, _ = model.predict(obs[:, None, None], torch.tensor([[[[10.0, 0.0]]]]))
    delta = delta[0, 0, 0]
    # leader 2 m/s faster: +0.2 m; follower 2 m/s slower: +0.2 m; other lane leader 1 m/s
    # slower: -0.1 m; nobody behind in the other lane and no crossing in range: unchanged
    torch.testing.assert_close(delta[5:9], torch.tensor([0.2, 0.2, 0.0, 0.0]))
    torch.testing.assert_close(delta[13:], torch.tensor([-0.1, 0.0]))
    with pytest.raises(ValueError, match="obs_dim"):
        FigureEightKinematicModel(1, 9, 1)


def test_headway_margin_counts_closing_not_opening() -> None:
    # speed 10 m/s, headway 0.5 s: margin 2 + 5 = 7 m
    rows = torch.tensor([[10.0, 0, 0, 8, 8, gap, 30] for gap in (8.0, 6.0, 6.0, 1.5)])
    before = torch.tensor([[10.0, 0, 0, 8, 8, gap, 30] for gap in (8.5, 6.5, 5.5, 1.0)])
    collided = FigureEightPlannerReward(headway=0.5).collision(before, torch.zeros(4, 1), rows)
    # outside the margin; closing inside it; opening inside it; below the 2 m floor
    assert collided.tolist() == [False, True, False, True]
    fixed = FigureEightPlannerReward(headway=0.0)
    assert fixed.collision(before, torch.zeros(4, 1), rows).tolist() == [
        False,
        False,
        False,
        True,
    ]
