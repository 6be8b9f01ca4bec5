"""Scenes moved between highway-env and the batched freeway.

:func:`load_scene` copies the scene of a highway-env :class:`~mapets_rl.envs.FreewayEnv` (or
``FreewayMergeEnv``) into one road of a :class:`BatchedFreeway`: positions, headings, speeds,
lanes and target lanes, target speeds, IDM exponents, lane-change timers, last commands,
crashes, pending impacts, CAV decisions and the episode's bookkeeping (its behaviour counts
included). From such a scene both
simulators step the same vehicles (the calibration of ``benchmarks/freeway_calibration.py``
and ``tests/envs/test_torch_freeway.py``). :func:`draw_scene` does the reverse for rendering:
it puts one road's vehicles on a highway-env road, whose viewer then draws it.
"""

from __future__ import annotations

import numpy as np
import torch
from highway_env.vehicle.kinematics import Vehicle

from mapets_rl.envs.freeway import KL, FreewayEnv
from mapets_rl.envs.freeway_merge import BEHAVIOUR_COUNTS, RAMP_ROAD, FreewayMergeEnv
from mapets_rl.envs.torch_freeway.simulator import BatchedFreeway
from mapets_rl.envs.vehicles import HumanVehicle


def lane_id(lane_index: tuple, lanes: int) -> int:
    """The simulator's lane id of a highway-env lane index (see
    :mod:`~mapets_rl.envs.torch_freeway.geometry`)."""
    return lanes + 1 if tuple(lane_index[:2]) == RAMP_ROAD else int(lane_index[2])


def lane_index(lane: int, lanes: int) -> tuple:
    """The highway-env lane index of a simulator lane id."""
    return (*RAMP_ROAD, 0) if lane == lanes + 1 else ("0", "1", int(lane))


def _check_fits(sim: BatchedFreeway, env: FreewayEnv) -> None:
    merge = isinstance(env, FreewayMergeEnv)
    if merge != sim.merge or env.config["n_vehicles"] != sim.n_vehicles:
        raise ValueError(
            f"the highway-env scene ({type(env).__name__}, {env.config['n_vehicles']} vehicles) "
            f"does not fit the simulator (merge={sim.merge}, {sim.n_vehicles} vehicles)"
        )
    if env.config["n_cavs"] != sim.n_cavs or env.config["lanes"] != sim.geometry.lanes:
        raise ValueError("the highway-env scene has another number of CAVs or lanes")


def load_scene(sim: BatchedFreeway, road: int, env: FreewayEnv) -> None:
    """Make road ``road`` of ``sim`` the current scene of highway-env ``env`` (same scenario,
    same config); its vehicles keep highway-env's order (``env.vehicles_all``), so the
    obstacle-last body layout and the CAV order match."""
    _check_fits(sim, env)
    lanes = sim.geometry.lanes
    vehicles = list(env.vehicles_all)
    on_road = {id(v) for v in env.road.vehicles}
    cav_ids = {id(c): k for k, c in enumerate(env.cavs)}
    rows: dict[str, list] = {key: [] for key in sim.state["bodies"].keys()}
    for v in vehicles:
        impact = v.impact if v.impact is not None else np.zeros(2)
        row = {
            "x": v.position[0],
            "y": v.position[1],
            "heading": v.heading,
            "speed": v.speed,
            "target_speed": v.target_speed,
            "delta": v.DELTA,
            "timer": v.timer,
            "acc": float(v.action["acceleration"]),
            "steer": float(v.action["steering"]),
            "impact_x": impact[0],
            "impact_y": impact[1],
            "lane": lane_id(v.lane_index, lanes),
            "target": lane_id(v.target_lane_index, lanes),
            "decision": getattr(v, "decision", KL) if id(v) in cav_ids else KL,
            "crashed": v.crashed,
            "present": id(v) in on_road,
            "has_impact": v.impact is not None,
            "cav": id(v) in cav_ids,
        }
        for key, value in row.items():
            rows[key].append(value)
    if sim.merge:  # the obstacle
        rows["x"].append(sim.geometry.merge_end)
        rows["y"].append(lanes * 4.0)
        rows["lane"].append(lanes)
        rows["target"].append(lanes)
        rows["present"].append(True)
        for values in rows.values():
            if len(values) < sim.n_bodies:
                values.append(0)
    bodies = sim.state["bodies"]
    for key, values in rows.items():
        column = bodies.get(key)
        column[road] = torch.tensor(values, dtype=column.dtype, device=column.device)
    index = {id(v): k for k, v in enumerate(vehicles)}
    agents = sim.state["agents"]
    agents.get("slot")[road] = torch.tensor([index[id(c)] for c in env.cavs])
    agents.get("alive")[road] = torch.as_tensor(env.alive.copy())
    sim.state.get("steps")[road] = env.steps_taken
    speeds = np.array(env._speeds) if env._speeds else np.zeros((0, 1))
    comforts = np.array(env._comforts) if env._comforts else np.zeros((0, 1))
    sim.state.get("speed_sum")[road] = float(np.nansum(speeds))
    sim.state.get("comfort_sum")[road] = float(np.nansum(comforts))
    sim.state.get("samples")[road] = float((~np.isnan(speeds)).sum())
    if sim.merge:
        agents.get("forcing")[road] = torch.as_tensor(env.forcing.copy())
        for key in BEHAVIOUR_COUNTS:
            sim.state.get(key)[road] = env.behaviour[key]


def draw_scene(sim: BatchedFreeway, road: int, env: FreewayEnv) -> None:
    """Replace the vehicles of highway-env ``env`` (reset once, same config) by those of road
    ``road`` of ``sim``, so that ``env.render()`` draws that road."""
    _check_fits(sim, env)
    lanes = sim.geometry.lanes
    state = sim.state[road].cpu()
    bodies = state.get("bodies")
    env.road.vehicles = []
    made: list[Vehicle | None] = []
    for k in range(sim.n_vehicles):
        if not bool(bodies.get("present")[k]):
            made.append(None)
            continue
        cls = env.cav_class if bool(bodies.get("cav")[k]) else HumanVehicle
        lane = lane_index(int(bodies.get("lane")[k]), lanes)
        vehicle = cls(
            road=env.road,
            position=[float(bodies.get("x")[k]), float(bodies.get("y")[k])],
            heading=float(bodies.get("heading")[k]),
            speed=float(bodies.get("speed")[k]),
            target_lane_index=lane_index(int(bodies.get("target")[k]), lanes),
            target_speed=float(bodies.get("target_speed")[k]),
        )
        vehicle.lane_index, vehicle.lane = lane, env.road.network.get_lane(lane)
        env.road.vehicles.append(vehicle)
        made.append(vehicle)
    slots = state.get("agents").get("slot").tolist()
    alive = state.get("agents").get("alive").numpy().copy()
    env.cavs = [made[s] or _ghost(bodies, s) for s in slots]
    env.alive = alive
    env.time = int(state.get("steps")) / env.config["policy_frequency"]


def _ghost(bodies: object, k: int) -> Vehicle:
    """A vehicle off the road standing for a crashed CAV (its last position)."""
    return Vehicle(None, [float(bodies.get("x")[k]), float(bodies.get("y")[k])])
