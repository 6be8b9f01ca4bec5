"""The figure-eights on SUMO (``backend="sumo"``, :mod:`mapets_rl.envs.sumo_figure_eight`):
PettingZoo's API and seed tests, torchrl's spec check, known answers of the CAV's speed
control, a rear-end and a crossing collision with their agility and safety, the scene as drawn,
lane changes and the network cache. Skipped where the extra ``mapets-rl[sumo]`` is missing."""

from __future__ import annotations

import threading
import xml.etree.ElementTree as ET

import numpy as np
import pytest

pytest.importorskip("libsumo", reason="the SUMO back end needs pip install 'mapets-rl[sumo]'")
pytest.importorskip("traci", reason="the SUMO back end needs pip install 'mapets-rl[sumo]'")

from pettingzoo.test import parallel_api_test, parallel_seed_test  # noqa: E402
from torchrl.envs.utils import check_env_specs  # noqa: E402

from mapets_rl.envs import make_env  # noqa: E402
from mapets_rl.envs import sumo_figure_eight as sfe  # noqa: E402
from mapets_rl.envs.vehicles import ACC_MAX, ACC_MIN, TargetSpeedVehicle  # noqa: E402

DT = 0.1


def controlled(speed: float, target: float) -> float:
    """The highway-env CAV's speed after one 0.1 s step towards ``target``."""
    acc = min(max(TargetSpeedVehicle.KP_A * (target - speed), ACC_MIN), ACC_MAX)
    return max(speed + acc * DT, 0.0)


@pytest.fixture
def envs():
    """Raw SUMO envs built by the test, closed after it."""
    made = []

    def build(**config) -> sfe.SumoFigureEightEnv:
        made.append(sfe.SumoFigureEightEnv(config))
        return made[-1]

    yield build
    for env in made:
        env.close()


@pytest.mark.parametrize("lanes", [1, 2])
def test_pettingzoo_api_and_seed(lanes: int) -> None:
    parallel_api_test(sfe.SumoFigureEightParallelEnv(lanes=lanes, n_hvs=8, horizon=30), 40)
    parallel_seed_test(lambda: sfe.SumoFigureEightParallelEnv(lanes=lanes, n_hvs=8, horizon=30), 40)


@pytest.mark.parametrize(
    ("name", "obs_dim", "act_dim"),
    [("figure-eight", 10, 1), ("figure-eight-multilane", 15, 2)],
)
def test_make_env_specs(name: str, obs_dim: int, act_dim: int) -> None:
    env = make_env(name, backend="sumo", seed=0, horizon=20)
    try:
        check_env_specs(env)
        td = env.rollout(25)
        agents = td["next", "agents"]
        assert td.shape == (20,)  # the horizon ends the episode
        assert agents["observation"].shape[-1] == obs_dim
        assert td["agents", "action"].shape[-1] == act_dim
        assert agents["position"].shape[-1] == 2
        assert set(env.last_episode_metrics) >= {"agility", "safety", "collisions"}
    finally:
        env.close()


def test_second_env_in_a_process_runs_through_traci(envs) -> None:
    first, second = envs(n_hvs=8, horizon=20), envs(n_hvs=8, horizon=20)
    obs_first, _ = first.reset(seed=3)
    obs_second, _ = second.reset(seed=3)
    assert second.connection == "traci"  # libsumo runs one simulation per process
    np.testing.assert_array_equal(obs_first, obs_second)
    action = np.full((8, 1), 12.0, dtype=np.float32)
    for _ in range(10):
        np.testing.assert_array_equal(first.step(action)[0], second.step(action)[0])


def test_scene_as_drawn(envs) -> None:
    """Vehicles start on the 12 m slot grid: every gap is 12 k - 5 m (or nobody within 75 m),
    the positions in ``info`` are the observed ones and the speeds within ``initial_speed``."""
    env = envs(n_hvs=20, initial_speed=(4.0, 8.0))
    obs, info = env.reset(seed=0)
    assert len(env.veh_ids) == 28
    gaps = obs[:, 5:7].ravel()
    off_grid = np.abs((gaps + 5.0 + 6.0) % 12.0 - 6.0)  # distance of gap + 5 from 12 k
    assert ((off_grid < 0.01) | (np.abs(gaps - 75.0) < 1e-6)).all()  # within 1 cm
    np.testing.assert_allclose(info["positions"], obs[:, 1:3], atol=1e-4)
    assert ((obs[:, 0] >= 4.0 - 1e-4) & (obs[:, 0] <= 8.0 + 1e-4)).all()


def test_cav_reaches_its_target_speed(envs) -> None:
    """A lone CAV follows the highway-env speed controller exactly; agility is its distance
    per step and safety 1."""
    env = envs(n_cavs=1, n_hvs=0, initial_speed=(5.0, 5.0), horizon=60)
    env.reset(seed=1)
    speed, travelled = 5.0, 0.0
    for _ in range(60):
        obs, _, _, truncated, info = env.step(np.array([[10.0]], dtype=np.float32))
        speed = controlled(speed, 10.0)
        travelled += speed * DT
        assert obs[0, 0] == pytest.approx(speed, abs=1e-4)
    assert truncated and speed == pytest.approx(10.0, abs=1e-3)
    assert info["episode"]["agility"] == pytest.approx(travelled / 60, rel=1e-6)
    assert info["episode"]["safety"] == 1.0


def test_rear_end_collision_known_step(envs) -> None:
    """A CAV driving at the limit into a braking CAV crashes in the step the kinematics
    predict (SUMO moves a vehicle by its new speed); both leave the road, safety is
    ``(t - 1) / H`` and each gets the collision reward."""
    env = envs(n_cavs=2, n_hvs=0, horizon=100, observation="paper")
    for seed in range(50):
        obs, info = env.reset(seed=seed)
        follower = int(np.argmin(obs[:, 5]))
        if obs[follower, 5] < 40 and info["neighbour_cav"][follower, 0] == 1 - follower:
            break
    leader = 1 - follower
    gap, v_f, v_l = float(obs[follower, 5]), float(obs[follower, 0]), float(obs[leader, 0])
    predicted = 0
    while gap >= 0:
        v_f, v_l = controlled(v_f, 13.89), controlled(v_l, 0.0)
        gap += (v_l - v_f) * DT
        predicted += 1
    action = np.zeros((2, 1), dtype=np.float32)
    action[follower] = 13.89
    step, collided = 0, False
    while not collided and step < 100:
        obs, _, terminated, _, info = env.step(action)
        step, collided = step + 1, info["collided"].any()
    assert step == predicted
    assert info["collided"].all() and terminated and len(env.veh_ids) == 0
    assert info["episode"]["safety"] == pytest.approx((predicted - 1) / 100)
    expected = obs[:, 0] + obs[:, 3] + obs[:, 4] - 10.0
    np.testing.assert_allclose(info["agent_rewards"], expected, rtol=1e-6)


def test_crossing_collision(envs) -> None:
    """Two CAVs on the two branches, as far from the crossing at the same speed, meet on the
    junction: SUMO reports the collision there."""
    env = envs(n_cavs=2, n_hvs=0, horizon=100, initial_speed=(8.0, 8.0))
    for seed in range(300):
        obs, _ = env.reset(seed=seed)
        branches = env._observed_ids[:, 2]
        if branches[0] != branches[1] and abs(obs[0, 7] - obs[1, 7]) < 0.5 and 10 < obs[0, 7] < 60:
            break
    for _ in range(100):
        obs, _, _, _, info = env.step(np.full((2, 1), 8.0, dtype=np.float32))
        if info["collided"].any():
            break
    assert info["collided"].all()
    assert (np.linalg.norm(info["positions"], axis=1) < 8.0).all()  # at the crossing


def test_lane_change_is_continuous(envs) -> None:
    """A lane-change request moves the CAV's lane feature from 1 to 0 over 2 s; a request
    during the change does not turn it back."""
    env = envs(n_cavs=1, n_hvs=0, lanes=2, initial_speed=(8.0, 8.0), horizon=40)
    obs, _ = env.reset(seed=3)
    start = round(float(obs[0, 10]))
    lanes = []
    for step in range(30):
        flag = 1.0 if step in (0, 5) else 0.0
        obs, *_ = env.step(np.array([[8.0, flag]], dtype=np.float32))
        lanes.append(float(obs[0, 10]))
    assert lanes[-1] == pytest.approx(1 - start, abs=1e-6)
    steps = np.abs(np.diff([start, *lanes]))
    assert steps.max() <= 0.05 + 1e-6  # 20 steps of a 4 m change: 0.05 lane widths each


def test_network_cache_reused_and_atomic(tmp_path, monkeypatch) -> None:
    results: list = []

    def build() -> None:
        results.append(sfe.network_file(300.0, 2, root=tmp_path))

    threads = [threading.Thread(target=build) for _ in range(3)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    assert len(set(results)) == 1 and len(results) == 3
    net = results[0]
    assert [p.name for p in tmp_path.iterdir()] == [net.parent.name]  # no temporary left
    edges = {e.get("id") for e in ET.parse(net).getroot().iter("edge")}
    assert set(sfe.ROUTE_EDGES) <= edges
    mtime = net.stat().st_mtime_ns

    def no_build(*args, **kwargs):
        raise AssertionError("netconvert ran although the network is cached")

    monkeypatch.setattr(sfe.subprocess, "run", no_build)
    assert sfe.network_file(300.0, 2, root=tmp_path) == net
    assert net.stat().st_mtime_ns == mtime


def test_failed_build_leaves_nothing(tmp_path, monkeypatch) -> None:
    class Failed:
        returncode, stderr = 1, "Error: no network"

    monkeypatch.setattr(sfe.subprocess, "run", lambda *args, **kwargs: Failed())
    with pytest.raises(RuntimeError, match="netconvert failed"):
        sfe.network_file(310.0, 1, root=tmp_path)
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize(
    ("name", "config", "match"),
    [
        ("freeway", {}, "backend='sumo' simulates"),
        ("figure-eight", {"render_mode": "rgb_array"}, "does not render"),
        ("figure-eight", {"stock_neighbour_search": True}, "does not implement"),
        ("figure-eight", {"num_envs": 2}, "num_envs, dtype and kernel need backend='torch'"),
        ("figure-eight", {"lanes": 3}, "lanes must be 1 or 2"),
    ],
)
def test_refusals(name: str, config: dict, match: str) -> None:
    with pytest.raises(ValueError, match=match):
        make_env(name, backend="sumo", **config)


def test_action_checked(envs) -> None:
    env = envs(n_hvs=8)
    env.reset(seed=0)
    with pytest.raises(ValueError, match="target speed must be in"):
        env.step(np.full((8, 1), 20.0, dtype=np.float32))
    with pytest.raises(ValueError, match="shape"):
        env.step(np.zeros((8, 2), dtype=np.float32))
