"""The batched torch freeway: torchrl API, partial resets, snapshot/restore, and its calibration
against highway-env on constructed and recorded scenes."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from highway_env.vehicle.behavior import IDMVehicle
from torchrl.envs.utils import check_env_specs

from mapets_rl.envs import FreewayEnv, FreewayMergeEnv, make_env
from mapets_rl.envs.freeway import CL, KL
from mapets_rl.envs.torch_freeway.dynamics import idm_acceleration
from mapets_rl.envs.torch_freeway.highway_state import lane_id, load_scene
from mapets_rl.envs.torch_freeway.native import kernel_unavailable, load_kernel
from mapets_rl.envs.torch_freeway.simulator import BatchedFreeway

SMALL = {"n_vehicles": 8, "cav_ratio": 0.5, "spawn_length": 200.0}


@pytest.mark.parametrize("name", ["freeway", "freeway-merge"])
@pytest.mark.parametrize("num_envs", [None, 3])
def test_specs(name: str, num_envs: int | None) -> None:
    config = dict(SMALL, ramp_fraction=0.25) if name == "freeway-merge" else SMALL
    env = make_env(name, backend="torch", num_envs=num_envs, seed=0, **config)
    check_env_specs(env)
    batch = [] if num_envs is None else [num_envs]
    assert list(env.batch_size) == batch
    obs_dim = 24 if name == "freeway-merge" else 22
    assert env.observation_spec["agents", "observation"].shape == (*batch, 4, obs_dim)


def test_same_keys_as_highway_env() -> None:
    torch_env = make_env("freeway-merge", backend="torch", **SMALL)
    highway = make_env("freeway-merge", **SMALL)
    for spec in ("observation_spec", "full_action_spec", "full_reward_spec", "full_done_spec"):
        ours, theirs = getattr(torch_env, spec), getattr(highway, spec)
        assert set(ours.keys(True, True)) == set(theirs.keys(True, True)), spec
        for key in theirs.keys(True, True):
            assert ours[key].shape == theirs[key].shape, key
            assert ours[key].dtype == theirs[key].dtype, key


def test_partial_reset_keeps_other_roads() -> None:
    env = make_env("freeway", backend="torch", num_envs=8, seed=1, **SMALL)
    td = env.reset()
    for _ in range(5):
        td = env.rand_step(td)
        td = (
            td["next"]
            .exclude("agents", "done", "terminated", "truncated")
            .update(td["next"].select("agents", "done", "terminated", "truncated"))
        )
    before = env.sim.state.clone()
    reset = torch.zeros(8, 1, dtype=torch.bool)
    reset[[1, 6]] = True
    out = env.reset(td.set("_reset", reset))
    steps = env.sim.state["steps"]
    assert steps.tolist() == [5, 0, 5, 5, 5, 5, 0, 5]
    keep = ~reset.squeeze(-1)
    for key in ("x", "speed", "lane"):
        assert torch.equal(env.sim.state["bodies", key][keep], before["bodies", key][keep])
        assert not torch.equal(env.sim.state["bodies", key][~keep], before["bodies", key][~keep])
    assert not out["done"].any()


def test_rollout_resets_finished_roads_inside_the_batch() -> None:
    env = make_env("freeway", backend="torch", num_envs=4, seed=2, horizon=3, **SMALL)
    rollout = env.rollout(7, break_when_any_done=False)
    done = rollout["next", "done"].squeeze(-1)
    assert done[:, 2].all() and done[:, 5].all() and not done[:, [0, 1, 3, 4, 6]].any()
    assert len(env.pop_finished_episodes()) == 8
    assert set(env.last_episode_metrics) == {"average_velocity", "average_comfort", "collisions"}


@pytest.mark.parametrize("name", ["freeway", "freeway-merge"])
def test_snapshot_restore_is_bit_exact(name: str) -> None:
    env = make_env(name, backend="torch", num_envs=5, seed=3, categorical_actions=True)
    env.reset()
    gen = torch.Generator().manual_seed(0)
    actions = [torch.randint(0, 4, (5, env.sim.n_cavs), generator=gen) for _ in range(6)]
    snapshot = env.snapshot()

    def play() -> tuple[torch.Tensor, ...]:
        rewards = []
        for action in actions:
            rewards.append(env.sim.step(action).reward)
        env.sim.reset(torch.ones(5, dtype=torch.bool))  # draws from the generator
        return torch.stack(rewards), env.sim.state["bodies", "x"].clone()

    first = play()
    state_after = env.sim.state.clone()
    env.restore(snapshot)
    second = play()
    assert all(torch.equal(a, b) for a, b in zip(first, second, strict=True))
    for key in state_after.keys(True, True):
        assert torch.equal(state_after[key], env.sim.state[key]), key


def test_restore_refuses_a_foreign_snapshot() -> None:
    one = make_env("freeway", backend="torch", num_envs=2, **SMALL)
    other = make_env("freeway", backend="torch", num_envs=3, **SMALL)
    with pytest.raises(ValueError, match="snapshot does not fit"):
        one.restore(other.snapshot())


@pytest.mark.parametrize(
    ("speed", "front_speed", "gap", "target"),
    [(25.0, 20.0, 30.0, 30.0), (10.0, 10.0, 12.0, 28.0), (30.0, 0.0, 60.0, 31.0),
     (0.0, 5.0, 8.0, 25.0), (20.0, 20.0, 200.0, 20.0)],
)  # fmt: skip
def test_idm_matches_highway_env(
    speed: float, front_speed: float, gap: float, target: float
) -> None:
    env = FreewayEnv({"n_vehicles": 2, "cav_ratio": 0.5})
    env.reset(seed=0)
    ego, front = env.vehicles_all
    ego.position[:] = (100.0, 4.0)
    front.position[:] = (100.0 + gap, 4.0)
    ego.speed, front.speed, ego.target_speed = speed, front_speed, target
    ego.heading = front.heading = 0.0
    env.road.refresh()
    expected = IDMVehicle.acceleration(ego, ego, front)
    ours = idm_acceleration(
        *(torch.tensor([v], dtype=torch.float64) for v in (speed, target, 0.0, ego.DELTA)),
        env.config["speed_limit"],
        torch.tensor([True]),
        *(torch.tensor([v], dtype=torch.float64) for v in (gap, front_speed, 0.0)),
    )
    assert float(ours) == pytest.approx(expected, abs=1e-5)


def _scene(positions: list[tuple[int, float, float]], target: float = 31.0) -> FreewayEnv:
    """A freeway scene: vehicles ``(lane, x, speed)``; the first is the deciding human."""
    env = FreewayEnv({"n_vehicles": len(positions), "cav_ratio": 1 / len(positions)})
    env.reset(seed=0)
    humans = [v for v in env.vehicles_all if v not in env.cavs]
    order = humans + list(env.cavs)
    for vehicle, (lane, x, speed) in zip(order, positions, strict=True):
        vehicle.position[:] = (x, 4.0 * lane)
        vehicle.heading, vehicle.speed, vehicle.target_speed = 0.0, speed, target
        vehicle.lane_index = vehicle.target_lane_index = ("0", "1", lane)
        vehicle.lane = env.road.network.get_lane(vehicle.lane_index)
        vehicle.timer = 0.95  # MOBIL decides in the second simulation step
    env.road.refresh()
    return env


@pytest.mark.parametrize(
    ("scene", "changes"),
    [
        ([(1, 100.0, 30.0), (1, 120.0, 20.0), (2, 300.0, 25.0)], True),  # slow leader, free lane
        ([(1, 100.0, 30.0), (1, 120.0, 20.0), (0, 95.0, 31.0), (2, 96.0, 31.0)], False),  # no room
        ([(1, 100.0, 25.0), (1, 400.0, 25.0), (2, 300.0, 25.0)], False),  # no gain
    ],
)
def test_mobil_decisions_match_highway_env(scene: list, changes: bool) -> None:
    env = _scene(scene)
    sim = BatchedFreeway(dict(env.config), False, 1, dtype=torch.float64)
    load_scene(sim, 0, env)
    human = next(v for v in env.vehicles_all if v not in env.cavs)
    k = env.vehicles_all.index(human)
    bodies = dict(sim.state["bodies"].items())
    front, rear = sim.physics.neighbours(bodies)
    for _ in range(3):  # three simulation steps of both simulators
        env.road.act()
        env.road.step(0.1)
        bodies, front, rear = sim.physics.substep(bodies, front, rear)
        assert int(bodies["target"][0, k]) == lane_id(human.target_lane_index, 3)
        accel = float(bodies["acc"][0, k])
        assert accel == pytest.approx(human.action["acceleration"], abs=1e-5)
    assert (human.target_lane_index != ("0", "1", 1)) is changes


def native_or_skip() -> None:
    """Skip where the fused CPU kernel cannot be built (no C++ compiler or ninja)."""
    if load_kernel() is None:
        pytest.skip(f"fused CPU kernel unavailable: {kernel_unavailable()}")


@pytest.mark.parametrize("kernel", ["native", "torch"])
@pytest.mark.parametrize(("name", "ratio", "seed"), [("freeway", 0.5, 0), ("freeway", 1.0, 1),
                                                      ("freeway-merge", 0.5, 2),
                                                      ("freeway-merge", 1.0, 0)])  # fmt: skip
def test_trajectories_follow_highway_env(name: str, ratio: float, seed: int, kernel: str) -> None:
    """From a recorded highway-env scene, 40 steps of random decisions (crashes included) give
    the same positions, rewards, observations and episode metrics in both simulators, with
    the fused CPU kernel (to rounding) and with the torch program (to centimetres)."""
    if kernel == "native":
        native_or_skip()
    cls = FreewayMergeEnv if name == "freeway-merge" else FreewayEnv
    env = cls({"n_vehicles": 30, "cav_ratio": ratio})
    env.reset(seed=seed)
    merge = name == "freeway-merge"
    sim = BatchedFreeway(dict(env.config), merge, 1, dtype=torch.float64, kernel=kernel)
    load_scene(sim, 0, env)
    rng = np.random.default_rng(seed)
    worst = 0.0
    for _ in range(40):
        action = rng.choice([KL, KL, CL, 2, 3], size=env.config["n_cavs"])
        obs, _, terminated, truncated, info = env.step(action)
        result = sim.step(torch.as_tensor(action)[None])
        ours = torch.stack([sim.state["bodies", "x"], sim.state["bodies", "y"]], -1)[0, :30]
        theirs = np.array([v.position for v in env.vehicles_all])
        worst = max(worst, float(np.abs(ours.numpy() - theirs).max()))
        # the torch program's vectorised sin / cos differ from libm's in the last bit on the
        # slanted ramp, and such differences can grow to centimetres in an episode
        tolerance = 1e-3 if kernel == "native" else 0.5
        np.testing.assert_allclose(result.reward[0].numpy(), info["agent_rewards"], atol=tolerance)
        np.testing.assert_allclose(result.observation[0].numpy(), obs, atol=tolerance)
        if terminated or truncated:
            break
    assert worst < 0.5
    expected = env.episode_metrics()
    for key, value in sim.episode_metrics().items():
        assert float(value[0]) == pytest.approx(expected[key], rel=1e-3, abs=1e-6), key


def test_bad_input_is_refused() -> None:
    with pytest.raises(ValueError, match="backend must be one of"):
        make_env("freeway", backend="jax")
    with pytest.raises(ValueError, match="num_envs, dtype and kernel need backend='torch'"):
        make_env("freeway", num_envs=4)
    with pytest.raises(ValueError, match="backend='torch' simulates"):
        make_env("figure-eight", backend="torch")
    with pytest.raises(ValueError, match="num_envs must be an integer >= 1"):
        make_env("freeway", backend="torch", num_envs=0)
    with pytest.raises(ValueError, match="unknown config key"):
        make_env("freeway", backend="torch", lane_count=3)
    with pytest.raises(ValueError, match="stock_neighbour_search"):
        make_env("freeway", backend="torch", stock_neighbour_search=True)
    with pytest.raises(ValueError, match="dtype must be one of"):
        make_env("freeway", backend="torch", dtype="float16")
    with pytest.raises(ValueError, match="cav_ratio must be"):
        make_env("freeway", backend="torch", cav_ratio=2.0)
    env = make_env("freeway", backend="torch", num_envs=2, **SMALL)
    td = env.reset()
    bad = torch.zeros(2, 4, 4, dtype=torch.long)
    with pytest.raises(ValueError, match="one-hot per CAV"):
        env.step(td.set(("agents", "action"), bad))


def test_render_draws_road_zero() -> None:
    env = make_env("freeway-merge", backend="torch", num_envs=2, render_mode="rgb_array", **SMALL,
                   ramp_fraction=0.25)  # fmt: skip
    env.rollout(2)
    frame = env.render()
    assert frame.ndim == 3 and frame.shape[-1] == 3 and frame.std() > 0


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_kernel_and_torch_program_agree(dtype: torch.dtype) -> None:
    """The fused CPU kernel and the torch program step 16 roads of random decisions alike: the
    same observations and rewards (to rounding, for the first steps: random lane changes crash
    CAVs, and a last-bit difference can decide a crash later) and the same crashes."""
    native_or_skip()
    config = make_env("freeway-merge", backend="torch", cav_ratio=0.5).config
    sims = [BatchedFreeway(config, True, 16, dtype=dtype, seed=4, kernel=k)
            for k in ("native", "torch")]  # fmt: skip
    gen = torch.Generator().manual_seed(1)
    for _ in range(5):
        action = torch.randint(0, 4, (16, sims[0].n_cavs), generator=gen)
        native, ours = (sim.step(action) for sim in sims)
        torch.testing.assert_close(native.observation, ours.observation, atol=0.01, rtol=0)
        torch.testing.assert_close(native.reward, ours.reward, atol=0.01, rtol=0)
        assert torch.equal(native.alive, ours.alive)


def test_float32_keeps_highway_env_decisions() -> None:
    """float32 state gives highway-env's episodes too: the lane-change timer and the
    lateral controller run in float64 (in float32 the timer decided one step early and
    stopped vehicles steered the wrong way: ramp vehicles stayed stuck more often)."""
    envs = []
    for seed in range(6):
        env = FreewayMergeEnv({"n_vehicles": 30, "cav_ratio": 0.5})
        env.reset(seed=seed)
        envs.append(env)
    stuck = []
    for dtype in (torch.float64, torch.float32):
        sim = BatchedFreeway(dict(envs[0].config), True, 6, dtype=dtype, kernel="torch")
        for road, env in enumerate(envs):
            load_scene(sim, road, env)
        for _ in range(40):
            sim.step(torch.zeros(6, sim.n_cavs, dtype=torch.long))
        stuck.append(sim.episode_metrics()["ramp_stuck"])
    assert torch.equal(stuck[0], stuck[1])


def test_kernel_build_directory_must_be_private(tmp_path, monkeypatch) -> None:
    """The kernel is never loaded from a directory that others may write to."""
    from mapets_rl.envs.torch_freeway.native import build_directory

    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    path = build_directory()
    assert path.is_relative_to(tmp_path) and (path.stat().st_mode & 0o077) == 0
    path.chmod(0o777)
    with pytest.raises(OSError, match="others may write"):
        build_directory()


def test_a_build_killed_half_way_does_not_leave_the_next_one_waiting(tmp_path) -> None:
    """torch's build lock file outlives a killed builder and made every later process wait for
    ever (seen: a run killed while it rebuilt the kernel hung the next runs and the tests).
    The build now holds a flock, which dies with its holder, and clears torch's stale lock."""
    import signal
    import subprocess
    import sys
    import textwrap
    import time

    from mapets_rl.envs.torch_freeway.native import TORCH_BATON, build_exclusively

    baton = tmp_path / TORCH_BATON
    builder = textwrap.dedent(f"""
        import time
        from pathlib import Path
        from mapets_rl.envs.torch_freeway.native import build_exclusively
        def build():
            Path({str(baton)!r}).touch()  # as torch does while it compiles
            time.sleep(600)
        build_exclusively(Path({str(tmp_path)!r}), build)
    """)
    child = subprocess.Popen([sys.executable, "-c", builder])
    try:
        deadline = time.monotonic() + 60
        while not baton.exists():
            assert child.poll() is None and time.monotonic() < deadline, "the builder never began"
            time.sleep(0.05)
    finally:
        child.kill()
        child.wait()
    assert baton.exists()  # what the killed build left behind
    previous = signal.signal(signal.SIGALRM, lambda *_: pytest.fail("the next build waited"))
    signal.alarm(30)
    try:
        built = build_exclusively(tmp_path, lambda: "module")
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, previous)
    assert built == "module" and not baton.exists()


@pytest.mark.parametrize("backend", ["highway-env", "torch"])
def test_devices_and_lengths_are_checked_first(backend: str) -> None:
    """Devices that do not exist and absurd road lengths get one clear error, on both
    backends (issue 34: they gave tracebacks or numpy overflows)."""
    for device in ("bogus", 5, True):
        with pytest.raises(ValueError, match="device"):
            make_env("freeway", backend=backend, device=device)
    if not torch.cuda.is_available():
        with pytest.raises(ValueError, match="no such CUDA device"):
            make_env("freeway", backend=backend, device="cuda")
    with pytest.raises(ValueError, match="road_length"):
        make_env("freeway", backend=backend, road_length=1e300)
