"""Recipes train, checkpoint, resume and evaluate with ``device="cuda"`` (skipped without a GPU).

The environments step on the CPU; policies, models, datasets and generators live on the GPU.
"""

import pytest
import torch

from mapets_rl.recipes.coma import COMA
from mapets_rl.recipes.maddpg import MADDPG
from mapets_rl.recipes.mapets import MAPETS
from mapets_rl.recipes.mappo import MAPPO
from mapets_rl.recipes.sac import SAC
from mapets_rl.recipes.shapley_ac import ShapleyAC
from tests.recipes.test_recipe_mapets import tiny

pytestmark = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")


@pytest.mark.parametrize("cuda_graph", [False, True])
def test_mapets_trains_resumes_and_evaluates_on_cuda(tmp_path, cuda_graph):
    run_dir = tmp_path / "run"
    exp = MAPETS(tiny(episodes=2, device="cuda", planner={"cuda_graph": cuda_graph}), run_dir)
    assert next(exp.model.parameters()).device.type == "cuda"
    exp.train()
    resumed = MAPETS.from_run_dir(run_dir, overrides=["episodes=3"])
    assert resumed.episode == 2 and resumed.planner.cuda_graph == cuda_graph
    entries = resumed.train()
    assert entries[-1]["metrics"]["episode"] == 3.0
    metrics = resumed.evaluate(episodes=1)
    assert 0.0 <= metrics["safety"] <= 1.0


@pytest.mark.parametrize(
    ("recipe", "sizes"),
    [
        (MADDPG, {"batch_size": 16, "init_random_frames": 0}),
        (SAC, {"batch_size": 16, "init_random_frames": 0}),
        (MAPPO, {"minibatch_size": 20}),
        (ShapleyAC, {"env": "freeway", "batch_size": 16, "init_random_frames": 0}),
        (COMA, {"env": "freeway", "minibatch_size": 20}),
    ],
)
def test_model_free_recipes_train_and_evaluate_on_cuda(tmp_path, recipe, sizes):
    """Collector, replay buffer, observation normaliser, losses and evaluation on the GPU:
    every learned parameter moves in training."""
    env_config = (
        {"n_vehicles": 6, "cav_ratio": 0.5}
        if sizes.get("env") == "freeway"
        else {"n_cavs": 3, "n_hvs": 2, "horizon": 20}
    )
    config = recipe.Config(
        env_config=env_config,
        total_frames=80,
        frames_per_batch=40,
        eval_interval=0,
        device="cuda",
        progress=False,
        **sizes,
    )
    exp = recipe(config, tmp_path / "run")
    params = dict(exp.loss.named_parameters())
    assert all(p.device.type == "cuda" for p in params.values())
    before = {k: p.detach().clone() for k, p in params.items()}
    exp.train()
    assert any(not torch.equal(before[k], p) for k, p in exp.loss.named_parameters())
    assert exp.evaluate(episodes=1)["length"] > 0


def gpu_freeway_config(recipe, total_frames: int, **sizes):
    """A tiny run of ``recipe`` on 8 roads of the batched freeway-merge on the GPU (10
    vehicles), its networks and replay there too."""
    return recipe.Config(
        env="freeway-merge",
        env_config={"backend": "torch", "num_envs": 8, "device": "cuda", "n_vehicles": 10},
        total_frames=total_frames,
        frames_per_batch=64,
        eval_interval=0,
        device="cuda",
        progress=False,
        **sizes,
    )


@pytest.mark.parametrize(
    ("recipe", "sizes"),
    [
        (MADDPG, {"batch_size": 32, "init_random_frames": 0}),
        (MAPPO, {"minibatch_size": 32}),
        (ShapleyAC, {"batch_size": 32, "init_random_frames": 0}),
    ],
)
def test_model_free_recipes_train_on_the_gpu_freeway(tmp_path, recipe, sizes):
    """Roads, networks and replay all on the GPU: the batched torch freeway on CUDA (8 roads)
    feeds the collector, every learned parameter moves, and evaluation runs on one GPU road."""
    exp = recipe(gpu_freeway_config(recipe, 128, **sizes), tmp_path / "run")
    assert exp.env.device.type == "cuda"
    before = {k: p.detach().clone() for k, p in exp.loss.named_parameters()}
    exp.train()
    assert any(not torch.equal(before[k], p) for k, p in exp.loss.named_parameters())
    assert exp.evaluate(episodes=1)["length"] > 0


def test_mapets_shares_plans_and_brakes_when_lost_on_cuda(tmp_path):
    """Plan sharing (``comm.share_plans``) and the lost-state brake
    (``planner_reward.brake_when_lost``) with the CUDA-graph planner: two episodes train and the
    run evaluates."""
    config = tiny(
        episodes=2,
        device="cuda",
        planner={"cuda_graph": True},
        comm={"comm_range": 100.0, "share_plans": True},
    ).with_overrides(["planner_reward.brake_when_lost=true"])
    exp = MAPETS(config, tmp_path / "run")
    entries = exp.train()
    assert entries[-1]["metrics"]["episode"] == 2.0
    assert 0.0 <= exp.evaluate(episodes=1)["safety"] <= 1.0
    exp.close()


@pytest.mark.parametrize(
    ("recipe", "overrides"),
    [
        (MADDPG, ["env_config.team_reward=false", "critic_share_params=false"]),
        (ShapleyAC, ["critic_cells=[64, 64]", "num_permutations=8", "shapley_bf16=true"]),
        (
            ShapleyAC,
            [
                "num_permutations=8",
                "shapley_bf16=true",
                "coalition_sizes=uniform",
                "critic_embed_cells=[64]",
                "critic_member_heads=true",
            ],
        ),
    ],
    ids=["maddpg-per-agent-critics", "shapley-paper-critic", "shapley-uniform-embed-member"],
)
def test_the_cooperation_control_stack_trains_on_the_gpu_freeway(tmp_path, recipe, overrides):
    """Issue 32's stack on GPU roads: epsilon exploration without emergency stops, the
    model-predictive shield, w = 1, individual rewards (MADDPG with one critic per CAV; Shapley
    AC with its bf16 Shapley estimate, with the paper's critic and with the arm that finds the
    merge on the CPU: uniform coalition sizes, a per-agent layer, member heads): every learned
    parameter moves and the shield is counted in evaluation."""
    config = gpu_freeway_config(recipe, 256, batch_size=32, init_random_frames=0).with_overrides(
        [
            "exploration=epsilon",
            "exploration_actions=[0, 1, 2]",
            "env_config.shield=true",
            "env_config.velocity_weight=1.0",
            *overrides,
        ]
    )
    exp = recipe(config, tmp_path / "run")
    before = {k: p.detach().clone() for k, p in exp.loss.named_parameters()}
    exp.train()
    assert all(not torch.equal(before[k], p) for k, p in exp.loss.named_parameters())
    metrics = exp.evaluate(episodes=1)
    assert metrics["length"] > 0 and "shielded" in metrics
    exp.close()
