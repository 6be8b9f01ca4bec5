"""The planner's compiled rollout step (``PlannerConfig.compile``): equal to eager planning within
a stated tolerance, compiled once per shape, eager with a warning where it cannot compile."""

import logging

import pytest
import torch
from tensordict import TensorDict

from mapets_rl.envs.figure_eight import FigureEightPlannerReward
from mapets_rl.models import ProbabilisticEnsemble
from mapets_rl.planning import TrajectorySamplingCEM, compiled
from mapets_rl.planning.compiled import CompiledStep
from mapets_rl.planning.trajectory_sampling import propagate_step
from mapets_rl.recipes.mapets import MAPETS, MAPETSConfig

needs_compiler = pytest.mark.skipif(
    compiled.compiler_unavailable() is not None, reason="no C++ compiler for inductor"
)

# The fused loops reassociate float32 sums: states, rewards and counts agree to this.
ATOL, RTOL = 1e-4, 1e-5

OBS_DIM = 10  # the figure-eight's crossing observation
PLAN = dict(horizon=6, population=16, elites=4, iterations=2, particles=5, dtype="fp32")


def trained_looking_ensemble(n_agents: int = 3) -> ProbabilisticEnsemble:
    torch.manual_seed(0)
    model = ProbabilisticEnsemble(OBS_DIM, 1, n_agents, 5, (32, 32))
    model.output_std.fill_(0.3)  # deltas of a few tenths, as a fitted model predicts
    return model


PLANNER_REWARD = FigureEightPlannerReward()


def observations(n_agents: int, envs: int = 1) -> torch.Tensor:
    """``[envs, I, 10]``: speeds 5-12 m/s, gaps 10-40 m, crossing distances 20-60 m."""
    gen = torch.Generator().manual_seed(1)
    obs = torch.rand(envs, n_agents, OBS_DIM, generator=gen)
    obs[..., [0, 3, 4]] = 5 + 7 * obs[..., [0, 3, 4]]
    obs[..., [5, 6]] = 10 + 30 * obs[..., [5, 6]]
    obs[..., 7:9] = 20 + 40 * obs[..., 7:9]
    return obs


def planner(model: ProbabilisticEnsemble, **settings) -> TrajectorySamplingCEM:
    return TrajectorySamplingCEM(
        model,
        PLANNER_REWARD.reward,
        -3.0,
        3.0,
        termination_fn=PLANNER_REWARD.collision,
        seed=0,
        **{**PLAN, **settings},
    )


def step_inputs(propagation: str) -> tuple:
    model = trained_looking_ensemble()
    gen = torch.Generator().manual_seed(2)
    particles, cands = 5, 8
    rows = particles * cands
    state = observations(3).reshape(3, 1, OBS_DIM).expand(-1, rows, -1).contiguous()
    action = torch.rand(3, rows, 1, generator=gen) * 6 - 3
    eps = (
        None if propagation == "expectation" else torch.randn(particles, 1, OBS_DIM, generator=gen)
    )
    perm = torch.randperm(rows, generator=gen) if propagation == "ts1" else None
    returns = torch.rand(3, rows, generator=gen)
    alive = torch.rand(3, rows, generator=gen) > 0.2
    finite = torch.randint(0, 3, (3, rows), generator=gen)
    return (model, state, action, eps, perm, returns, alive, finite) + (
        PLANNER_REWARD.reward,
        PLANNER_REWARD.collision,
        propagation,
        torch.float32,
    )


@needs_compiler
@pytest.mark.parametrize("propagation", ["ts_inf", "ts1", "expectation"])
def test_compiled_step_equals_the_eager_step(propagation):
    args = step_inputs(propagation)
    with torch.no_grad():
        want = propagate_step(*args)
        got = CompiledStep()(*args)
    for g, w in zip(got, want, strict=True):
        assert g.dtype == w.dtype and g.shape == w.shape
        if g.dtype == torch.bool or g.dtype == torch.long:
            assert torch.equal(g, w)
        else:
            torch.testing.assert_close(g, w, atol=ATOL, rtol=RTOL)


@needs_compiler
def test_compiled_planner_decides_like_the_eager_one_and_compiles_once():
    model = trained_looking_ensemble()
    eager, fast = planner(model), planner(model, compile=True)
    assert eager.compiled_step is None and fast.compiled_step.fallback_reason is None
    for obs in observations(3, envs=4):  # consecutive decisions: warm start and shift
        td = TensorDict({("agents", "observation"): obs})
        want = eager(td.clone())["agents", "action"]
        got = fast(td.clone())["agents", "action"]
        torch.testing.assert_close(got, want, atol=ATOL, rtol=RTOL)
    step = fast.compiled_step
    assert step.compiles == 1 and step.compile_seconds > 0
    fast(TensorDict({("agents", "observation"): observations(3, envs=2)}, batch_size=[2]))
    assert step.compiles == 2  # a new batch shape is a new graph


@needs_compiler
def test_a_reward_of_the_wrong_shape_still_fails_clearly_when_compiled():
    args = list(step_inputs("ts_inf"))
    args[8] = lambda obs, action, next_obs: next_obs[..., 0:2]  # [I, R, 2], not [I, R]
    with pytest.raises(ValueError, match="reward_fn must return shape"):
        CompiledStep()(*args)


def test_without_a_compiler_the_planner_runs_eagerly_and_says_why(monkeypatch, caplog):
    monkeypatch.setattr(compiled, "compiler_unavailable", lambda: "no C++ compiler (test)")
    model = trained_looking_ensemble()
    with caplog.at_level(logging.WARNING, logger="mapets_rl.planning.compiled"):
        fast = planner(model, compile=True)
    assert "runs eagerly: no C++ compiler (test)" in caplog.text
    assert fast.compiled_step.fallback_reason == "no C++ compiler (test)"
    td = TensorDict({("agents", "observation"): observations(3)[0]})
    want = planner(model)(td.clone())["agents", "action"]
    assert torch.equal(fast(td.clone())["agents", "action"], want)


def test_a_failing_compilation_falls_back_to_the_eager_step(monkeypatch, caplog):
    def broken(fn, **kwargs):
        def run(*args):
            raise RuntimeError("inductor exploded\nsecond line")

        return run

    monkeypatch.setattr(compiled, "compiler_unavailable", lambda: None)
    monkeypatch.setattr(torch, "compile", broken)
    args = step_inputs("ts_inf")
    step = CompiledStep()
    with caplog.at_level(logging.WARNING, logger="mapets_rl.planning.compiled"):
        got = step(*args)
    assert step.fallback_reason == "torch.compile failed: RuntimeError: inductor exploded"
    assert "runs eagerly" in caplog.text
    for g, w in zip(got, propagate_step(*args), strict=True):
        assert torch.equal(g, w)


def test_the_fallback_reason_names_the_root_cause(monkeypatch):
    def broken(fn, **kwargs):
        def run(*args):
            raise RuntimeError("backend='inductor' raised:") from OSError("File too large")

        return run

    monkeypatch.setattr(compiled, "compiler_unavailable", lambda: None)
    monkeypatch.setattr(torch, "compile", broken)
    step = CompiledStep()
    step(*step_inputs("ts_inf"))
    assert step.fallback_reason == "torch.compile failed: OSError: File too large"


def test_compile_is_a_planner_setting_of_the_recipe(tmp_path, monkeypatch):
    monkeypatch.setattr(compiled, "compiler_unavailable", lambda: "skipped in this test")
    config = MAPETSConfig(
        env_config={"n_cavs": 2, "n_hvs": 0, "horizon": 5},
        planner={"horizon": 2, "population": 4, "elites": 2, "iterations": 1, "compile": True},
        model={"hidden": [8]},
        progress=False,
    )
    exp = MAPETS(config, tmp_path / "run")
    assert exp.planner.compiled_step is not None
    with pytest.raises(ValueError, match="compile"):
        MAPETSConfig(planner={"compile": "yes"})


@needs_compiler
def test_a_compiled_run_compiles_once_across_episodes_and_model_refits(tmp_path):
    """The cpu preset compiles; refitting the ensembles between episodes (in-place updates) and
    starting new episodes reuse the first graph."""
    config = MAPETSConfig(
        preset="cpu",
        episodes=3,
        seed=1,
        env_config={"n_cavs": 3, "n_hvs": 1, "horizon": 15},
        planner={"horizon": 4, "population": 8},
        model={"hidden": [16], "buffer_size": 64, "epochs": 2},
        num_threads=1,
        progress=False,
    )
    assert config.planner.compile
    exp = MAPETS(config, tmp_path / "run")
    exp.train()
    step = exp.planner.compiled_step
    assert step.fallback_reason is None and step.compiles == 1
    metrics = exp.results.train[-1]["metrics"]
    assert 0.0 <= metrics["safety"] <= 1.0 and metrics["random"] == 0.0
