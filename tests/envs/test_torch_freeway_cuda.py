"""The batched torch freeway on a GPU (skipped without one): the torchrl API, partial resets,
snapshot/restore, the shield, and the same trajectories as the CPU program from the same scene.

The CPU runs these tests' logic through the torch program and the fused kernel
(``test_torch_freeway.py``); here the same program runs on CUDA, whose random generator differs
from the CPU's, so a CPU scene is carried over by snapshot and restore before the two are
compared step by step.
"""

from __future__ import annotations

import pytest
import torch
from torchrl.envs.utils import check_env_specs

from mapets_rl.envs import make_env
from mapets_rl.envs.torch_freeway.simulator import BatchedFreeway

pytestmark = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")

SMALL = {"n_vehicles": 8, "cav_ratio": 0.5, "spawn_length": 200.0}


@pytest.mark.parametrize("name", ["freeway", "freeway-merge"])
def test_specs_and_outputs_live_on_the_gpu(name: str) -> None:
    env = make_env(name, backend="torch", num_envs=3, seed=0, device="cuda", **SMALL)
    check_env_specs(env)
    td = env.rollout(5, break_when_any_done=False)
    assert td.device.type == "cuda"
    assert all(t.device.type == "cuda" for t in td.values(True, True))


def test_partial_reset_on_the_gpu() -> None:
    env = make_env("freeway", backend="torch", num_envs=4, seed=1, device="cuda", **SMALL)
    td = env.reset()
    for _ in range(3):
        td = env.step(env.rand_action(td))["next"]
    reset = torch.tensor([[False], [True], [False], [True]], device="cuda")
    env.reset(td.set("_reset", reset))
    assert env.sim.state["steps"].tolist() == [3, 0, 3, 0]


def _carry_over(cpu: BatchedFreeway, gpu: BatchedFreeway) -> None:
    """Put ``cpu``'s roads into ``gpu`` (its own generator state kept: the two kinds differ)."""
    snap = cpu.snapshot().exclude("rng").to("cuda")
    snap["rng"] = gpu.snapshot().get("rng")
    gpu.restore(snap)


@pytest.mark.parametrize("kernel", ["torch", "native"])
def test_gpu_steps_like_the_cpu_from_the_same_scene(kernel: str) -> None:
    """float64: 32 roads of freeway-merge (30 vehicles, half CAVs) from the same CPU scene; 40
    keep-lane steps give the same rewards (to 1e-4), positions (to 1 cm) and crashes on both
    devices, and 5 steps of random decisions the same observations (later, a last-bit
    difference can decide a crash, as between the CPU kernel and the CPU program)."""
    config = make_env("freeway-merge", backend="torch", cav_ratio=0.5).config
    cpu = BatchedFreeway(config, True, 32, dtype=torch.float64, seed=3, kernel=kernel)
    if kernel == "native" and cpu.kernel is None:
        pytest.skip("the fused CPU kernel cannot be built here")
    gpu = BatchedFreeway(config, True, 32, device="cuda", dtype=torch.float64)
    _carry_over(cpu, gpu)
    keep = torch.zeros(32, cpu.n_cavs, dtype=torch.long)
    for _ in range(40):
        a, b = cpu.step(keep), gpu.step(keep.cuda())
        torch.testing.assert_close(b.reward.cpu(), a.reward, atol=1e-4, rtol=0)
        assert torch.equal(b.alive.cpu(), a.alive)
    x = gpu.state["bodies", "x"].cpu()
    torch.testing.assert_close(x, cpu.state["bodies", "x"], atol=0.01, rtol=0)
    torch.testing.assert_close(
        gpu.episode_metrics()["ramp_stuck"].cpu(), cpu.episode_metrics()["ramp_stuck"]
    )
    cpu.reset(torch.ones(32, dtype=torch.bool))
    _carry_over(cpu, gpu)
    generator = torch.Generator().manual_seed(0)
    for _ in range(5):
        action = torch.randint(0, 4, (32, cpu.n_cavs), generator=generator)
        a, b = cpu.step(action), gpu.step(action.cuda())
        torch.testing.assert_close(b.observation.cpu(), a.observation, atol=1e-5, rtol=0)
        assert torch.equal(b.alive.cpu(), a.alive)


def test_snapshot_restore_is_bit_exact_on_the_gpu() -> None:
    env = make_env("freeway-merge", backend="torch", num_envs=16, seed=2, device="cuda")
    env.reset()
    snap = env.snapshot()
    action = torch.randint(0, 4, (16, env.sim.n_cavs, 1), device="cuda")
    outputs = []
    for _ in range(2):
        env.restore(snap)
        td = env.reset().set(("agents", "action"), torch.nn.functional.one_hot(action[..., 0], 4))
        outputs.append(env.step(td)["next"])
    for key in outputs[0].keys(True, True):
        assert torch.equal(outputs[0][key], outputs[1][key]), key


def test_shield_counts_on_the_gpu() -> None:
    """The shield replaces predicted crashes on CUDA as on the CPU: random decisions crash far
    less with it, and its replacements are counted."""
    crashes = []
    for shield in (False, True):
        env = make_env(
            "freeway-merge", backend="torch", num_envs=64, seed=5, device="cuda",
            categorical_actions=True, shield=shield,
        )  # fmt: skip
        generator = torch.Generator(device="cuda").manual_seed(0)
        env.reset()
        for _ in range(10):
            action = torch.randint(0, 4, (64, env.sim.n_cavs), generator=generator, device="cuda")
            result = env.sim.step(action)
        crashes.append(int((~result.alive).sum()))
        if shield:
            assert int(env.sim.state["shielded"].sum()) > 0
    assert crashes[1] < crashes[0]
