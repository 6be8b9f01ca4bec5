"""The behaviour counts of ``freeway-merge`` (issue 49): mainline lane changes near the merge and
elsewhere, forced and MOBIL merges from the ramp, the same on both backends: known answers on
constructed scenes, highway-env against the batched freeway from the same scene, and the
per-step definition of ``benchmarks/cooperation_control.py`` on the batched env."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from mapets_rl.envs import FreewayEnv, FreewayMergeEnv, make_env
from mapets_rl.envs.freeway import CL, CR, KL
from mapets_rl.envs.freeway_merge import BEHAVIOUR_COUNTS, NEAR_MERGE
from mapets_rl.envs.torch_freeway.highway_state import load_scene
from mapets_rl.envs.torch_freeway.native import kernel_unavailable, load_kernel
from mapets_rl.envs.torch_freeway.simulator import BatchedFreeway

SCENE = {"merge_start": 800.0, "merge_length": 100.0, "perception": 100.0}
"""Acceleration lane from x = 800 to 900 (y = 12, lane 3): near the merge is x in [700, 900]."""
ACCELERATION = ("0", "1", 3)
KERNELS = ["native", "torch"]


def _kernel(kernel: str) -> str:
    if kernel == "native" and load_kernel() is None:
        pytest.skip(f"fused CPU kernel unavailable: {kernel_unavailable()}")
    return kernel


def _scene(cav_ratio: float, placements: list[tuple[tuple, float, float]]) -> FreewayMergeEnv:
    """A 3-vehicle ``freeway-merge`` (CAVs first in ``placements``: ``env.cavs``, then the human
    drivers) with every vehicle put at ``(lane index, x [m], speed [m/s])``."""
    env = FreewayMergeEnv({"n_vehicles": 3, "cav_ratio": cav_ratio, "ramp_fraction": 1 / 3,
                           **SCENE})  # fmt: skip
    env.reset(seed=0)
    humans = [v for v in env.vehicles_all if v not in env.cavs]
    for vehicle, (lane_index, x, speed) in zip([*env.cavs, *humans], placements, strict=True):
        lane = env.road.network.get_lane(lane_index)
        vehicle.position = lane.position(x - lane.start[0], 0.0)
        vehicle.heading = lane.heading_at(x - lane.start[0])
        vehicle.lane_index = vehicle.target_lane_index = lane_index
        vehicle.lane, vehicle.speed = lane, speed
    env.road.refresh()
    return env


def _counts_on_both(
    env: FreewayMergeEnv, actions: list[list[int]], kernel: str
) -> tuple[dict[str, int], dict[str, int]]:
    """The behaviour counts after stepping ``env`` (highway-env) and a batched road loaded with
    its scene (float64) with the same ``actions`` (one ``[I]`` list per step)."""
    sim = BatchedFreeway(dict(env.config), True, 1, dtype=torch.float64, kernel=kernel)
    load_scene(sim, 0, env)
    for action in actions:
        env.step(np.array(action))
        sim.step(torch.tensor([action]))
    ours = sim.episode_metrics()
    theirs = env.episode_metrics()
    return {k: theirs[k] for k in BEHAVIOUR_COUNTS}, {k: int(ours[k][0]) for k in BEHAVIOUR_COUNTS}


def _expected(**counts: int) -> dict[str, int]:
    return {key: counts.get(key, 0) for key in BEHAVIOUR_COUNTS}


@pytest.mark.parametrize("kernel", KERNELS)
def test_a_change_left_on_the_acceleration_lane_is_one_forced_merge(kernel: str) -> None:
    far = [(("0", "1", 0), 1500.0, 25.0), (("0", "1", 0), 1600.0, 25.0)]
    env = _scene(1.0, [(ACCELERATION, 820.0, 20.0), *far])
    highway, batched = _counts_on_both(env, [[CL, KL, KL]] + [[KL] * 3] * 2, _kernel(kernel))
    assert env.cavs[0].lane_index == ("0", "1", 2)
    assert highway == batched == _expected(ramp_forced_merges=1)


@pytest.mark.parametrize("kernel", KERNELS)
def test_ramp_vehicles_that_keep_their_lane_merge_by_mobil_cavs_and_humans(kernel: str) -> None:
    """A CAV playing Keep Lane and a human driver on the acceleration lane beside a free
    mainline both merge by MOBIL; a mainline CAV's Change Right (refused: the acceleration lane
    is not a lane to drive in) counts nothing."""
    env = _scene(2 / 3, [(ACCELERATION, 820.0, 20.0), (("0", "1", 2), 300.0, 25.0),
                         (ACCELERATION, 805.0, 20.0)])  # fmt: skip
    highway, batched = _counts_on_both(env, [[KL, CR]] * 4, _kernel(kernel))
    assert all(not env.on_ramp(v) for v in env.vehicles_all)
    assert highway == batched == _expected(ramp_mobil_merges=2)


@pytest.mark.parametrize("kernel", KERNELS)
def test_mainline_changes_are_placed_by_where_they_start(kernel: str) -> None:
    """A Change Left from the rightmost lane at x = 760 (within ``NEAR_MERGE`` before the
    acceleration lane) is near the merge; one from the middle lane at x = 300 and one at
    x = 1000 (past the merge point) are elsewhere."""
    assert SCENE["merge_start"] - NEAR_MERGE < 760.0
    env = _scene(1.0, [(("0", "1", 2), 760.0, 25.0), (("0", "1", 1), 300.0, 25.0),
                       (("0", "1", 2), 1000.0, 25.0)])  # fmt: skip
    highway, batched = _counts_on_both(env, [[CL, CL, CL]] + [[KL] * 3] * 2, _kernel(kernel))
    assert [cav.lane_index[2] for cav in env.cavs] == [1, 0, 1]
    expected = _expected(mainline_changes_near_merge=1, mainline_changes_elsewhere=2)
    assert highway == batched == expected


@pytest.mark.parametrize("kernel", KERNELS)
def test_both_backends_count_the_same_on_a_recorded_scene(kernel: str) -> None:
    """From the same highway-env start scene, 40 steps of the same random decisions (Change Left
    drawn often, so that ramp CAVs force their merge) give the same counts on both backends."""
    env = FreewayMergeEnv({"n_vehicles": 30, "cav_ratio": 1.0})
    env.reset(seed=3)
    rng = np.random.default_rng(3)
    actions = [rng.choice([KL, KL, CL, CL, CR], size=30).tolist() for _ in range(40)]
    highway, batched = _counts_on_both(env, actions, _kernel(kernel))
    assert highway == batched
    assert all(highway[key] > 0 for key in BEHAVIOUR_COUNTS), highway


def test_the_counts_are_the_per_step_lane_comparison_of_cooperation_control() -> None:
    """The batched env's counts are ``benchmarks/cooperation_control.py``'s ``score``: each
    CAV's lane id before and after every policy step, a mainline-to-mainline change near the
    merge when its x at the step's start is in ``[merge_start - 100, merge_end]``; a reset road
    starts again from zero."""
    roads = 4
    env = make_env("freeway-merge", backend="torch", num_envs=roads, seed=1)
    sim = env.sim
    td = env.reset()
    generator = torch.Generator().manual_seed(1)
    near = torch.zeros(roads, dtype=torch.long)
    elsewhere = torch.zeros(roads, dtype=torch.long)
    mainline = sim.geometry.table < sim.geometry.ramp_table  # [L]

    def cav_lanes() -> tuple[torch.Tensor, torch.Tensor]:
        slot = sim.state["agents", "slot"]
        return sim.state["bodies", "lane"].gather(1, slot), sim.state["bodies", "x"].gather(1, slot)

    lane, x = cav_lanes()
    for _ in range(40):
        index = torch.multinomial(torch.tensor([3.0, 1.0, 1.0, 0.0]), roads * 30, True,
                                  generator=generator).view(roads, 30)  # fmt: skip
        td.set(("agents", "action"), torch.nn.functional.one_hot(index, 4))
        td = env.step(td).get("next")
        after, x_after = cav_lanes()
        changed = (lane != after) & mainline[lane] & mainline[after]
        by_merge = (x >= sim.geometry.merge_start - NEAR_MERGE) & (x <= sim.geometry.merge_end)
        near += (changed & by_merge).sum(1)
        elsewhere += (changed & ~by_merge).sum(1)
        lane, x = after, x_after
    episodes = env.pop_finished_episodes()
    assert [e["mainline_changes_near_merge"] for e in episodes] == near.tolist()
    assert [e["mainline_changes_elsewhere"] for e in episodes] == elsewhere.tolist()
    assert int(near.sum()) > 0 and all(type(e["ramp_forced_merges"]) is int for e in episodes)
    env.reset()
    assert all(bool((sim.episode_metrics()[key] == 0).all()) for key in BEHAVIOUR_COUNTS)


def test_the_freeway_without_a_ramp_reports_no_behaviour_counts() -> None:
    env = FreewayEnv({"n_vehicles": 6})
    env.reset(seed=0)
    env.step(np.full(6, CL))
    sim = make_env("freeway", backend="torch", num_envs=2, n_vehicles=6).sim
    for metrics in (env.episode_metrics(), sim.episode_metrics()):
        assert not set(BEHAVIOUR_COUNTS) & set(metrics)
