"""cuda_graph=True: a decision captured once and replayed decides what eager planning decides.

The CUDA tests are skipped on machines without a GPU; the refusals run everywhere.
"""

import pytest
import torch

from mapets_rl.config import ConfigError
from mapets_rl.envs import FigureEightPlannerReward
from mapets_rl.models import ProbabilisticEnsemble
from mapets_rl.planning import CPU_PRESET, TrajectorySamplingCEM
from mapets_rl.planning.cuda_graph import GraphedStep
from tests.planning.test_planner import (
    PLAN,
    linear_ensemble,
    lq_optimal_first_action,
    point_mass_matrix,
    quadratic_reward,
)

needs_cuda = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")


def test_cuda_graph_is_refused_off_cuda():
    model = linear_ensemble([point_mass_matrix()])
    with pytest.raises(ValueError, match="cuda_graph=True needs the model on a CUDA device"):
        TrajectorySamplingCEM(model, quadratic_reward, -20.0, 20.0, cuda_graph=True, **PLAN)
    with pytest.raises(ValueError, match="needs a CUDA device"):
        GraphedStep(torch.device("cpu"))


def test_mapets_config_refuses_cuda_graph_on_the_cpu():
    from mapets_rl.recipes.mapets import MAPETSConfig

    with pytest.raises(ConfigError, match=r"planner.cuda_graph must be False with device='cpu'"):
        MAPETSConfig(preset="cpu", planner={"cuda_graph": True})


def figure_eight_planners(dtype: str, n_agents: int = 3, seed: int = 0):
    """An eager and a graphed cpu-preset planner over one random-weight CUDA ensemble."""
    torch.manual_seed(seed)
    model = ProbabilisticEnsemble(7, 1, n_agents, ensemble_size=5, hidden=[32, 32]).cuda()
    planners = [
        TrajectorySamplingCEM(
            model,
            FigureEightPlannerReward().reward,
            0.0,
            13.89,
            CPU_PRESET.planner,
            seed=1,
            termination_fn=FigureEightPlannerReward().collision,
            dtype=dtype,
            cuda_graph=graph,
        )
        for graph in (False, True)
    ]
    return model, planners


def random_states(n: int, n_agents: int) -> list[torch.Tensor]:
    gen = torch.Generator().manual_seed(3)
    scale = torch.tensor([20.0, 14.0, 20.0, 14.0, 50.0, 14.0, 1.0])
    return [(torch.rand(n_agents, 7, generator=gen) * scale).cuda() for _ in range(n)]


@needs_cuda
@pytest.mark.parametrize("dtype", ["fp32", "bf16"])
def test_graphed_decisions_equal_eager_ones_with_one_capture(dtype):
    """Five consecutive decisions (warm starts, anchors, keep-best, termination): the graphed
    planner's actions and warm starts equal the eager planner's with the same seed (up to
    1e-4 of the action range), from one capture."""
    _, (eager, graphed) = figure_eight_planners(dtype)
    for obs in random_states(5, 3):
        a, b = eager.plan(obs), graphed.plan(obs)
        assert torch.allclose(a, b, atol=1e-4 * 13.89), (a, b)
        assert torch.allclose(eager.warm_start_mean, graphed.warm_start_mean, atol=1e-3)
    assert graphed.graph_captures == 1 and eager.graph_captures == 0
    assert graphed.last_iterations == eager.last_iterations


@needs_cuda
def test_graph_sees_in_place_training_and_recaptures_on_new_tensors():
    """An in-place weight update (an optimiser step) is planned with at the next replay without
    a recapture; a new batch shape or a replaced parameter recaptures."""
    model, (eager, graphed) = figure_eight_planners("fp32")
    states = random_states(3, 3)
    eager.plan(states[0]), graphed.plan(states[0])
    with torch.no_grad():
        for w in model.weights:
            w.mul_(1.5)
    a, b = eager.plan(states[1]), graphed.plan(states[1])
    assert torch.allclose(a, b, atol=1e-4 * 13.89) and graphed.graph_captures == 1
    batched = torch.stack(states[:2])  # [2 envs, I, obs]: a new shape
    assert torch.allclose(eager.plan(batched), graphed.plan(batched), atol=1e-4 * 13.89)
    assert graphed.graph_captures == 2
    model.weights[0] = torch.nn.Parameter(model.weights[0].detach().clone())
    assert torch.allclose(eager.plan(batched), graphed.plan(batched), atol=1e-4 * 13.89)
    assert graphed.graph_captures == 3


@needs_cuda
def test_graphed_planner_finds_the_lq_optimum():
    gains = [1.0, 2.0]
    model = linear_ensemble([point_mass_matrix(g) for g in gains]).cuda()
    obs = torch.tensor([[1.0, 0.5], [-2.0, 1.0]])
    planner = TrajectorySamplingCEM(
        model, quadratic_reward, -20.0, 20.0, seed=0, dtype="fp32", cuda_graph=True, **PLAN
    )
    action = planner.plan(obs.cuda())
    for i, gain in enumerate(gains):
        best = lq_optimal_first_action(obs[i], gain, PLAN["horizon"])
        assert action[i, 0].item() == pytest.approx(best, abs=0.06 * abs(best) + 0.05)
