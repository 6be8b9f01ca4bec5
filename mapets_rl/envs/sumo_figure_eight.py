"""The figure-eight scenarios on SUMO (``make_env("figure-eight", backend="sumo")``).

The MA-PETS paper runs its experiments on SMARTS, whose human drivers are SUMO's (its SUMO
traffic provider). This back end drives SUMO directly, through ``libsumo`` (one simulation per
process runs in-process; a second one in the same process, e.g. PettingZoo's seed test, runs a
``sumo`` process through ``traci``): the same scenario names, config keys, observation, action,
reward (paper eq. 26), metrics (agility eq. 27, safety eq. 28) and interfaces as the highway-env
figure-eight (:mod:`mapets_rl.envs.figure_eight`), on a road network SUMO's ``netconvert``
builds from our own figure-eight geometry (:class:`~mapets_rl.envs.figure_eight_road.
FigureEightGeometry`: the lobes, the straights, the crossing at the origin, one or two lanes)
at first use, into a private cache (:func:`network_file`).

What SUMO does and what we do:

- human drivers: SUMO's Krauss car-following (SMARTS's traffic actor defaults: accel 2.6,
  decel 4.5 m/s^2, tau 1 s, sigma 0.5, min gap 2.5 m) and, on two lanes, LC2013 lane changes;
  each one's desired speed is drawn from ``hv_target_speed`` (its ``speedFactor`` on the
  ``max_speed`` limit). The crossing is a ``right_before_left`` junction (the straight arriving
  from the right has the way; SUMO's junction model, not the highway-env scenario's
  first-come-first-served rule).
- CAVs: commanded every simulation step with ``setSpeed`` to the speed the highway-env CAV's
  controller reaches, ``v + clip(KP_A (u - v), ACC_MIN, ACC_MAX) dt`` for target speed ``u``,
  with SUMO's safety checks off (speed mode 0, lane-change mode 0): like the highway-env CAVs
  they can drive into others. A lane-change flag ``> 0.5`` of a CAV settled within 0.5 m of its
  lane's centre requests ``changeLane`` to the other lane (SUMO's continuous lane change over
  ``LANE_CHANGE_DURATION`` seconds).
- collisions: SUMO's (on lanes, bumper to bumper, and on the crossing's junction); a vehicle
  that collided leaves the road at the end of the step (the highway-env convention), a CAV then
  has ``alive=False`` and a zero observation row.

Vehicles start at the highway-env scenario's slots (evenly spaced ``min_spacing`` apart, clear
of the crossing) with speeds from ``initial_speed``; SUMO's insertion checks are off so the
scene is the one drawn. Every reset reloads SUMO with a seed drawn from the env's generator, so
a seed fixes the whole episode.
"""

from __future__ import annotations

import contextlib
import hashlib
import io
import math
import os
import shutil
import socket
import subprocess
import tempfile
import weakref
import xml.etree.ElementTree as ET
from pathlib import Path
from typing import Any

import numpy as np
from gymnasium import spaces

from mapets_rl.envs.figure_eight import (
    CROSSING_CLEAR,
    GAP_RANGE,
    LANE_CHANGE_THRESHOLD,
    NEIGHBOUR_SLOTS,
    TWO_LANE_OBS_DIM,
    FigureEightEnv,
    observation_size,
)
from mapets_rl.envs.figure_eight_road import FigureEightGeometry
from mapets_rl.envs.parallel import FigureEightParallelEnv, TrafficParallelEnv
from mapets_rl.envs.traffic import require
from mapets_rl.envs.vehicles import ACC_MAX, ACC_MIN, TargetSpeedVehicle
from mapets_rl.metrics import agility, safety

SUMO_VERSION = "1.28.0"
"""The SUMO release the back end was built and tested with (the ``sumo`` extra pins it)."""
SUMO_EXTRA = "pip install 'mapets-rl[sumo]'"
"""What installs the back end's dependencies (``eclipse-sumo``, ``libsumo``, ``traci``)."""
NETWORK_VERSION = 1
"""Version of the network builder: part of the cache key, so a change rebuilds the network."""
SUMO_KEYS = (
    "n_cavs",
    "n_hvs",
    "lanes",
    "length",
    "horizon",
    "policy_frequency",
    "simulation_frequency",
    "max_speed",
    "initial_speed",
    "hv_target_speed",
    "min_spacing",
    "collision_reward",
    "observation",
)
"""The figure-eight config keys the SUMO back end implements; it refuses the others (highway-env's
rendering keys, ``stock_neighbour_search``) when they differ from their defaults."""
VEHICLE_LENGTH = 5.0
"""Length of every vehicle [m] (highway-env's and SUMO's passenger car)."""
LANE_CHANGE_DURATION = 2.0
"""Seconds a lane change takes (SUMO's ``--lanechange.duration``; highway-env's take about 2 s)."""
HUMAN_TYPE = {
    "carFollowModel": "Krauss",
    "laneChangeModel": "LC2013",
    "accel": "2.6",
    "decel": "4.5",
    "emergencyDecel": "9.0",
    "tau": "1.0",
    "sigma": "0.5",
    "minGap": "2.5",
    "length": str(VEHICLE_LENGTH),
    "speedDev": "0",
}
"""SUMO vehicle type of the human drivers (SMARTS's ``TrafficActor`` defaults, no speed spread:
each driver's desired speed is its ``speedFactor`` times the limit)."""
CAV_TYPE = {
    "accel": str(ACC_MAX),
    "decel": str(-ACC_MIN),
    "emergencyDecel": str(-ACC_MIN),
    "sigma": "0",
    "minGap": "0",
    "length": str(VEHICLE_LENGTH),
    "speedDev": "0",
}
"""SUMO vehicle type of the CAVs (their speed is set every step; the limits are highway-env's)."""
ARC_POINTS = 48
"""Shape points of each 135-degree arc of the network."""
CROSSING_NODE = "X"
"""The junction at the crossing (the origin)."""
ROUTE_EDGES = ("s1_r", "r_s2", "s2_l", "l_s1")
"""The network's edges in travel order: straight 1's second half and the right lobe's first
half, the right lobe's second half and straight 2's first half, then the same on the left."""


def import_sumo() -> tuple[Any, Any, Path]:
    """``(libsumo, traci, SUMO's bin folder)``; ImportError naming the extra to install where
    SUMO is missing."""
    try:
        import libsumo
        import sumo
        import traci
    except ImportError as err:
        raise ImportError(
            f"backend='sumo' needs SUMO {SUMO_VERSION} (eclipse-sumo, libsumo, traci): "
            f"{SUMO_EXTRA} ({err})"
        ) from None
    return libsumo, traci, Path(sumo.SUMO_HOME) / "bin"


def cache_root() -> Path:
    """Where the built networks are kept: ``$XDG_CACHE_HOME/mapets_rl/sumo`` (default
    ``~/.cache/mapets_rl/sumo``)."""
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "mapets_rl" / "sumo"


# --- the road network ------------------------------------------------------------------------
def _arc(centre: tuple[float, float], radius: float, start: float, end: float) -> np.ndarray:
    """``[ARC_POINTS, 2]`` points of the arc around ``centre`` from angle ``start`` to ``end``
    (degrees), both ends included."""
    angles = np.radians(np.linspace(start, end, ARC_POINTS))
    return np.stack([centre[0] + radius * np.cos(angles), centre[1] + radius * np.sin(angles)], 1)


def network_xml(geometry: FigureEightGeometry, max_speed: float) -> dict[str, str]:
    """The plain node, edge and connection XML of the figure-eight: file name -> text.

    Three nodes: the crossing ``X`` at the origin and the lobes' far points ``c`` (right) and
    ``f`` (left); four edges (:data:`ROUTE_EDGES`) whose shapes are the reference line of
    ``geometry`` with ``spreadType="center"`` (lane ``k`` lies at ``geometry.lateral_offset(k)``,
    left of travel); at ``X`` each lane goes straight on, nothing turns.
    """
    r = geometry.radius
    c = math.sqrt(2.0) * r
    lanes, width = geometry.lanes, geometry.lane_width
    x_c, x_f = (c + r, 0.0), (-c - r, 0.0)
    shapes = {
        "s1_r": np.vstack([[[0.0, 0.0]], _arc((c, 0.0), r, 135.0, 0.0)]),
        "r_s2": np.vstack([_arc((c, 0.0), r, 0.0, -135.0), [[0.0, 0.0]]]),
        "s2_l": np.vstack([[[0.0, 0.0]], _arc((-c, 0.0), r, 45.0, 180.0)]),
        "l_s1": np.vstack([_arc((-c, 0.0), r, 180.0, 315.0), [[0.0, 0.0]]]),
    }
    ends = {"s1_r": ("X", "c"), "r_s2": ("c", "X"), "s2_l": ("X", "f"), "l_s1": ("f", "X")}
    nodes = (
        "<nodes>\n"
        f'  <node id="{CROSSING_NODE}" x="0" y="0" type="right_before_left"/>\n'
        f'  <node id="c" x="{x_c[0]!r}" y="{x_c[1]!r}" type="priority"/>\n'
        f'  <node id="f" x="{x_f[0]!r}" y="{x_f[1]!r}" type="priority"/>\n'
        "</nodes>\n"
    )
    edges = ["<edges>"]
    for edge, points in shapes.items():
        shape = " ".join(f"{float(x)!r},{float(y)!r}" for x, y in points)
        edges.append(
            f'  <edge id="{edge}" from="{ends[edge][0]}" to="{ends[edge][1]}" priority="1" '
            f'numLanes="{lanes}" width="{width!r}" speed="{max_speed!r}" spreadType="center" '
            f'shape="{shape}"/>'
        )
    edges.append("</edges>\n")
    connections = ["<connections>"]
    for into, out in (("l_s1", "s1_r"), ("r_s2", "s2_l"), ("s1_r", "r_s2"), ("s2_l", "l_s1")):
        for lane in range(lanes):
            connections.append(
                f'  <connection from="{into}" to="{out}" fromLane="{lane}" toLane="{lane}"/>'
            )
    connections.append("</connections>\n")
    return {
        "figure_eight.nod.xml": nodes,
        "figure_eight.edg.xml": "\n".join(edges),
        "figure_eight.con.xml": "\n".join(connections),
    }


def network_file(
    length: float = 480.0,
    lanes: int = 1,
    max_speed: float = 13.89,
    lane_width: float = 4.0,
    root: Path | None = None,
) -> Path:
    """The SUMO network (``.net.xml``) of the figure-eight, built by ``netconvert`` at first use.

    The network lives in ``root`` (default :func:`cache_root`) under a hash of everything it is
    built from (the geometry, the speed limit, :data:`NETWORK_VERSION` and the SUMO version).
    A build writes into a temporary folder beside it and renames that folder into place, so a
    reader never sees a half-written network, and two processes building the same one at once
    both end with the same complete files (the loser of the rename discards its copy).
    """
    _libsumo, _traci, bin_dir = import_sumo()
    geometry = FigureEightGeometry(length, lanes, lane_width)
    files = network_xml(geometry, max_speed)
    key = hashlib.sha256(
        repr((NETWORK_VERSION, SUMO_VERSION, sorted(files.items()))).encode()
    ).hexdigest()[:16]
    root = Path(root) if root is not None else cache_root()
    final = root / key
    net = final / "figure_eight.net.xml"
    if net.is_file():
        return net
    root.mkdir(parents=True, exist_ok=True)
    work = Path(tempfile.mkdtemp(prefix=f".{key}-", dir=root))
    try:
        for name, text in files.items():
            (work / name).write_text(text)
        command = [
            str(bin_dir / "netconvert"),
            "--node-files", str(work / "figure_eight.nod.xml"),
            "--edge-files", str(work / "figure_eight.edg.xml"),
            "--connection-files", str(work / "figure_eight.con.xml"),
            "--output-file", str(work / "figure_eight.net.xml"),
            "--no-turnarounds", "true",
            "--offset.disable-normalization", "true",
            "--junctions.corner-detail", "0",
            "--no-warnings", "true",
        ]  # fmt: skip
        done = subprocess.run(command, capture_output=True, text=True, check=False)
        if done.returncode != 0:
            raise RuntimeError(
                f"netconvert failed to build the figure-eight network ({done.returncode}): "
                f"{done.stderr.strip()[-500:]}"
            )
        with contextlib.suppress(OSError):  # another process renamed its copy first
            work.rename(final)
    finally:
        shutil.rmtree(work, ignore_errors=True)
    if not net.is_file():
        raise RuntimeError(f"the figure-eight network {net} is missing after its build")
    return net


class LaneMap:
    """Route coordinates of positions on the lanes of a built figure-eight network.

    Each lane of the network (internal lanes of the junctions included) is mapped, point by
    point of its shape, onto the reference line of the geometry; a vehicle's route coordinate
    is interpolated from its lane and its position along it, all vehicles at once.

    Attributes:
        lane_ids: ``[K]`` the network's lane ids (``index``: id -> its position there).
        lane_of: ``[K]`` the figure-eight lane (0 or 1: the lateral slot) of each.
        lane_length: ``[K]`` their lengths in SUMO's lane positions [m].
        span: ``[K]`` the route metres each covers.
    """

    def __init__(self, net: Path, geometry: FigureEightGeometry) -> None:
        self.geometry = geometry
        keys, coords, bases, lengths, lanes, ids = [], [], [], [], [], []
        base = 0.0
        for lane in ET.parse(net).getroot().iter("lane"):
            points = np.array(
                [[float(v) for v in p.split(",")[:2]] for p in lane.get("shape").split()]
            )
            length = float(lane.get("length"))
            along = np.concatenate(
                [[0.0], np.cumsum(np.linalg.norm(np.diff(points, axis=0), axis=1))]
            )
            along *= length / max(along[-1], 1e-9)
            s, lateral = self._project(points)
            step = (np.diff(s) + geometry.length / 2) % geometry.length - geometry.length / 2
            s = s[0] + np.concatenate([[0.0], np.cumsum(step)])
            keys.append(base + along)
            coords.append(s)
            bases.append(base)
            lengths.append(length)
            lanes.append(self._lane_slot(float(np.median(lateral))))
            ids.append(lane.get("id"))
            base += length + 10.0
        self._keys = np.concatenate(keys)
        self._coords = np.concatenate(coords)
        self._base = np.array(bases)
        self.lane_ids = ids
        self.lane_of = np.array(lanes, dtype=np.int64)
        self.index = {lane: k for k, lane in enumerate(ids)}
        self.lane_length = np.array(lengths)
        self.span = np.array([c[-1] - c[0] for c in coords])

    def _lane_slot(self, lateral: float) -> int:
        """The figure-eight lane (0 or 1) at ``lateral`` metres left of the reference line."""
        g = self.geometry
        return int(np.clip(round(lateral / g.lane_width + (g.lanes - 1) / 2), 0, g.lanes - 1))

    def _project(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Route coordinates ``[P]`` and lateral offsets ``[P]`` (left of travel) of the points
        ``[P, 2]`` of one lane, on the piece of the reference line each lies nearest to (the
        two straights cross at the origin: there the lane's direction picks the straight)."""
        g = self.geometry
        r, c = g.radius, math.sqrt(2.0) * g.radius
        offsets = g.segment_offsets
        direction = points[-1] - points[0]
        u1, u2 = np.array([1.0, 1.0]) / math.sqrt(2), np.array([-1.0, 1.0]) / math.sqrt(2)
        h = c / 2.0
        candidates = []
        # straight 1: a (-h,-h) -> b (h,h); straight 2: d (h,-h) -> e (-h,h)
        for start, u, offset in (((-h, -h), u1, offsets[0]), ((h, -h), u2, offsets[3])):
            rel = points - np.array(start)
            along = rel @ u
            lateral = rel @ np.array([-u[1], u[0]])
            outside = np.maximum(0.0, np.maximum(-along, along - 2 * r))
            penalty = 1e6 if float(direction @ u) < 0 else 0.0  # travels the other way
            candidates.append((offset + along, lateral, np.abs(lateral) + outside + penalty))
        # right lobe: clockwise from 135 degrees; left lobe: counter-clockwise from 45 degrees
        for centre, sign, start, offset in (
            ((c, 0.0), -1.0, 135.0, offsets[1]),
            ((-c, 0.0), 1.0, 45.0, offsets[4]),
        ):
            rel = points - np.array(centre)
            angle = np.degrees(np.arctan2(rel[:, 1], rel[:, 0]))
            swept = (sign * (angle - start)) % 360.0
            radius = np.linalg.norm(rel, axis=1)
            lateral = -sign * (radius - r)
            outside = np.where(
                swept > 270.0, r * np.radians(np.minimum(swept - 270, 360 - swept)), 0
            )
            candidates.append((offset + r * np.radians(swept), lateral, np.abs(lateral) + outside))
        cost = np.stack([cand[2] for cand in candidates])  # [4, P]
        best = cost.argmin(0)
        s = np.stack([cand[0] for cand in candidates])[best, np.arange(len(points))]
        lateral = np.stack([cand[1] for cand in candidates])[best, np.arange(len(points))]
        return s % g.length, lateral

    def front_coordinates(self, lanes: np.ndarray, positions: np.ndarray) -> np.ndarray:
        """Route coordinates ``[N]`` [m] (unwrapped along each lane) of the points at
        ``positions [N]`` (SUMO's lane positions) along the lanes ``lanes [N]`` (indices into
        :attr:`lane_ids`)."""
        key = self._base[lanes] + np.clip(positions, 0.0, self.lane_length[lanes])
        return np.interp(key, self._keys, self._coords)

    def coordinates(self, lanes: np.ndarray, positions: np.ndarray) -> np.ndarray:
        """Route coordinates ``[N]`` in ``[0, length)`` of the centres of vehicles whose front
        bumpers are at ``positions [N]`` along the lanes ``lanes [N]`` (SUMO normalises lane
        positions to the edge's length, so a vehicle's half length is as many route metres)."""
        front = self.front_coordinates(lanes, positions)
        return (front - 0.5 * VEHICLE_LENGTH) % self.geometry.length


# --- the connection to SUMO ------------------------------------------------------------------
class _InProcess:
    """The one ``libsumo`` simulation of this process: the env that holds it (a weak
    reference), or None."""

    holder: weakref.ref | None = None

    @classmethod
    def free(cls) -> bool:
        """Whether no live env holds the in-process simulation."""
        return cls.holder is None or cls.holder() is None


def _free_port() -> int:
    """A TCP port of this machine that nothing listens on now (for a ``sumo`` process)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as probe:
        probe.bind(("localhost", 0))
        return int(probe.getsockname()[1])


def _close_quietly(connection: Any, traci: Any) -> None:
    """Close a ``traci`` connection (and its ``sumo`` process) that may be closed already."""
    with contextlib.suppress(traci.TraCIException, traci.FatalTraCIError, OSError):
        connection.close()


def _sumo_args(config: dict, net: Path, routes: Path, seed: int) -> list[str]:
    """SUMO's command-line options of one episode."""
    return [
        "-n", str(net),
        "-r", str(routes),
        "--step-length", repr(1.0 / config["simulation_frequency"]),
        "--seed", str(seed),
        "--collision.action", "warn",
        "--collision.check-junctions", "true",
        "--collision.mingap-factor", "0",
        "--time-to-teleport", "-1",
        "--lanechange.duration", repr(LANE_CHANGE_DURATION),
        "--no-step-log", "true",
        "--no-warnings", "true",
        "--begin", "0",
    ]  # fmt: skip


VARIABLES = (0x51, 0x56, 0x40, 0x42, 0x43, 0xB8)
"""Subscribed vehicle variables (traci constants): lane id, lane position, speed, position,
angle, lateral lane position."""


class SumoFigureEightEnv:
    """The figure-eight on SUMO with the array interface of
    :class:`~mapets_rl.envs.figure_eight.FigureEightEnv` (what
    :class:`~mapets_rl.envs.parallel.TrafficParallelEnv` reads): ``reset`` and ``step`` return
    ``obs [I, obs_dim]`` and the per-CAV signals in ``info`` (``agent_rewards``,
    ``agent_terminated``, ``positions``, ``distance``, ``speed``, ``collided``, ``alive``,
    ``neighbour_changed``, ``neighbour_cav``; ``episode`` at the end).

    Config: the figure-eight's (same defaults and checks, :data:`SUMO_KEYS`); the highway-env
    keys the back end does not implement raise ValueError when they differ from their defaults.
    """

    def __init__(self, config: dict | None = None, render_mode: str | None = None) -> None:
        self.libsumo, self.traci, self.bin_dir = import_sumo()
        config = dict(config or {})
        defaults = FigureEightEnv.default_config()
        ignored = sorted(k for k in config if k not in SUMO_KEYS and config[k] != defaults.get(k))
        require(
            not ignored,
            f"backend='sumo' does not implement the config key(s) {ignored}; it accepts "
            f"{sorted(SUMO_KEYS)}",
        )
        require(
            render_mode is None,
            f"backend='sumo' does not render (render_mode must be None), got {render_mode!r}",
        )
        self.config = FigureEightEnv.resolved_config(config)
        self.render_mode = None
        cfg = self.config
        self.obs_dim = observation_size(cfg["observation"], cfg["lanes"])
        self.geometry = FigureEightGeometry(cfg["length"], cfg["lanes"])
        self.net = network_file(cfg["length"], cfg["lanes"], cfg["max_speed"])
        self.lane_map = LaneMap(self.net, self.geometry)
        n, act = cfg["n_cavs"], 2 if cfg["lanes"] == 2 else 1
        high = np.tile(np.array([cfg["max_speed"], 1.0][:act], dtype=np.float32), (n, 1))
        self.action_space = spaces.Box(np.zeros_like(high), high, dtype=np.float32)
        self.observation_space = spaces.Box(-np.inf, np.inf, (n, self.obs_dim), np.float32)
        self.np_random = np.random.default_rng()
        self._workdir = Path(tempfile.mkdtemp(prefix="mapets_rl_sumo_"))
        self._sim: Any = None
        self._finalizer = weakref.finalize(self, shutil.rmtree, self._workdir, True)
        self.alive = np.zeros(n, dtype=bool)
        self.steps_taken = 0

    @property
    def dt(self) -> float:
        """Duration of one environment step [s]."""
        return 1.0 / self.config["policy_frequency"]

    @property
    def connection(self) -> str:
        """``"libsumo"`` (in-process), ``"traci"`` (a ``sumo`` process) or ``"none"`` yet."""
        if self._sim is None:
            return "none"
        return "libsumo" if self._sim is self.libsumo else "traci"

    # --- episode ---------------------------------------------------------------------------
    def _routes(self, rng: np.random.Generator) -> tuple[Path, int]:
        """Write the episode's vehicles (the highway-env scenario's draw) as a SUMO route
        file; returns it and the number of human drivers."""
        cfg, geometry = self.config, self.geometry
        lo, hi = FigureEightEnv.hv_range(cfg["n_hvs"])
        n_hvs = int(rng.integers(lo, hi + 1))
        n_cavs = cfg["n_cavs"]
        slots = [
            (s, lane)
            for lane in range(cfg["lanes"])
            for s in FigureEightEnv.spawn_slots(geometry, cfg["min_spacing"])
        ]
        chosen = rng.choice(len(slots), size=n_cavs + n_hvs, replace=False)
        is_cav = np.zeros(n_cavs + n_hvs, dtype=bool)
        is_cav[rng.choice(n_cavs + n_hvs, size=n_cavs, replace=False)] = True
        speeds = rng.uniform(*cfg["initial_speed"], size=n_cavs + n_hvs)
        targets = rng.uniform(*cfg["hv_target_speed"], size=n_cavs + n_hvs)
        laps = math.ceil(cfg["horizon"] * self.dt * cfg["max_speed"] / geometry.length) + 2
        lines = ["<routes>"]
        for name, attrs in (("human", HUMAN_TYPE), ("cav", CAV_TYPE)):
            text = " ".join(f'{k}="{v}"' for k, v in attrs.items())
            lines.append(f'  <vType id="{name}" maxSpeed="{cfg["max_speed"]!r}" {text}/>')
        for k in range(len(ROUTE_EDGES)):
            edges = " ".join((ROUTE_EDGES[k:] + ROUTE_EDGES[:k]) * laps)
            lines.append(f'  <route id="loop{k}" edges="{edges}"/>')
        starts, scale = self._edge_starts()
        cav, hv = 0, 0
        for k, slot in enumerate(chosen):
            s, lane = slots[slot]
            front = s + 0.5 * VEHICLE_LENGTH
            edge = int(np.searchsorted(starts[:, lane], front, side="right") - 1) % len(starts)
            pos = (front - starts[edge, lane]) % geometry.length
            pos *= scale[edge, lane]
            if is_cav[k]:
                vid, vtype, factor = f"cav_{cav}", "cav", 1.0
                cav += 1
            else:
                vid, vtype, factor = f"hv_{hv}", "human", targets[k] / cfg["max_speed"]
                hv += 1
            lines.append(
                f'  <vehicle id="{vid}" type="{vtype}" route="loop{edge}" depart="0" '
                f'departLane="{lane}" departPos="{float(pos)!r}" '
                f'departSpeed="{float(speeds[k])!r}" speedFactor="{float(factor)!r}" '
                'insertionChecks="none"/>'
            )
        lines.append("</routes>\n")
        path = self._workdir / "episode.rou.xml"
        path.write_text("\n".join(lines))
        return path, n_hvs

    def _edge_starts(self) -> tuple[np.ndarray, np.ndarray]:
        """``[4, lanes]`` route coordinates where the lanes of each edge of
        :data:`ROUTE_EDGES` start, and ``[4, lanes]`` their lane metres per route metre."""
        m = self.lane_map
        lanes = np.array(
            [
                [m.index[f"{edge}_{lane}"] for lane in range(self.geometry.lanes)]
                for edge in ROUTE_EDGES
            ]
        )
        starts = m.front_coordinates(lanes.ravel(), np.zeros(lanes.size)).reshape(lanes.shape)
        return starts % self.geometry.length, m.lane_length[lanes] / m.span[lanes]

    def _start(self, args: list[str]) -> None:
        """Load the episode into this env's simulation, starting one at first use."""
        if self._sim is not None:
            self._sim.load(args)
            return
        binary = str(self.bin_dir / "sumo")
        if _InProcess.free():
            if _InProcess.holder is not None:  # its env was dropped without close()
                with contextlib.suppress(self.libsumo.TraCIException):
                    self.libsumo.close()
            self.libsumo.start([binary, *args])
            _InProcess.holder = weakref.ref(self)
            self._sim = self.libsumo
        else:
            port = _free_port()
            process = subprocess.Popen(
                [binary, *args, "--remote-port", str(port)],
                stdout=subprocess.DEVNULL,
                stderr=subprocess.DEVNULL,
            )
            with contextlib.redirect_stdout(io.StringIO()):  # traci prints every retry
                self._sim = self.traci.connect(
                    port, numRetries=500, proc=process, waitBetweenRetries=0.01
                )
            self._closer = weakref.finalize(self, _close_quietly, self._sim, self.traci)

    def reset(
        self, seed: int | None = None, options: dict | None = None
    ) -> tuple[np.ndarray, dict]:
        """Start an episode (``seed`` reseeds the env's generator); ``obs [I, obs]``, info."""
        if seed is not None:
            self.np_random = np.random.default_rng(seed)
        routes, self.n_hvs = self._routes(self.np_random)
        self._start(
            _sumo_args(self.config, self.net, routes, int(self.np_random.integers(2**31 - 1)))
        )
        sim = self._sim
        sim.simulationStep()
        n = self.config["n_cavs"]
        self.cav_ids = [f"cav_{i}" for i in range(n)]
        for vid in sim.vehicle.getIDList():
            sim.vehicle.subscribe(vid, VARIABLES)
            if vid.startswith("cav_"):
                sim.vehicle.setSpeedMode(vid, 0)
                sim.vehicle.setLaneChangeMode(vid, 0)
        self.alive = np.ones(n, dtype=bool)
        self.collision_step = np.full(n, self.config["horizon"], dtype=np.int64)
        self._crashed_now = np.zeros(n, dtype=bool)
        self._distance_step = np.zeros(n)
        self._episode_distances: list[np.ndarray] = []
        self._positions = np.zeros((n, 2), dtype=np.float32)
        self._previous_ids: np.ndarray | None = None
        self._collided: set[str] = set()
        self.steps_taken = 0
        self._read()
        obs = self.observe_agents()
        return obs, self._info(obs)

    # --- reading the simulation ------------------------------------------------------------
    def _read(self) -> None:
        """Every vehicle's state from the subscriptions: ids, route coordinates of the centres,
        figure-eight lanes, lateral lane positions (lane widths), speeds and centres ``[N, 2]``."""
        results = self._sim.vehicle.getAllSubscriptionResults()
        ids = list(results)
        lane_id, lane_pos, speed, pos, angle, lat = VARIABLES
        index = self.lane_map.index
        lanes = np.array([index[results[v][lane_id]] for v in ids], dtype=np.int64)
        along = np.array([results[v][lane_pos] for v in ids], dtype=np.float64)
        front = np.array([results[v][pos] for v in ids], dtype=np.float64).reshape(-1, 2)
        heading = np.radians([results[v][angle] for v in ids])
        self.veh_ids = ids
        self.veh_speed = np.array([results[v][speed] for v in ids], dtype=np.float64)
        self.veh_s = self.lane_map.coordinates(lanes, along)
        self.veh_lane = self.lane_map.lane_of[lanes]
        lateral = np.array([results[v][lat] for v in ids], dtype=np.float64)
        self.veh_lateral = self.veh_lane + lateral / self.geometry.lane_width
        direction = np.stack([np.sin(heading), np.cos(heading)], 1).reshape(-1, 2)
        self.veh_centre = front - 0.5 * VEHICLE_LENGTH * direction
        n = self.config["n_cavs"]
        self.veh_number = np.array(
            [int(v[4:]) if v.startswith("cav_") else n + int(v[3:]) for v in ids], dtype=np.int64
        )
        self._index_cavs()

    def _index_cavs(self) -> None:
        """``cav_row [I]``: each CAV's row in the vehicle arrays (``-1``: not on the road)."""
        n = self.config["n_cavs"]
        self.cav_row = np.full(n, -1, dtype=np.int64)
        is_cav = self.veh_number < n
        self.cav_row[self.veh_number[is_cav]] = np.flatnonzero(is_cav)

    def _per_cav(self, values: np.ndarray, fill: float = 0.0) -> np.ndarray:
        """``[I]`` each CAV's entry of the vehicle array ``values [N]``; ``fill`` for CAVs not
        on the road."""
        out = np.full(len(self.cav_row), fill, dtype=values.dtype)
        on_road = self.cav_row >= 0
        out[on_road] = values[self.cav_row[on_road]]
        return out

    def human_speeds(self) -> np.ndarray:
        """``[H]`` speeds [m/s] of the human drivers on the road now."""
        return self.veh_speed[self.veh_number >= self.config["n_cavs"]]

    def _neighbours(
        self, rows: np.ndarray, lane: np.ndarray, ahead: bool
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Leader (``ahead``) or follower of the vehicles ``rows [M]`` among those on ``lane
        [M]``: speeds ``[M]``, bumper-to-bumper gaps clipped to ``[0, 75]`` m and vehicle
        numbers (``-1``: nobody within 75 m)."""
        period = self.geometry.length
        delta = (self.veh_s[None, :] - self.veh_s[rows][:, None]) % period  # [M, N]
        if not ahead:
            delta = (period - delta) % period
        valid = (self.veh_lane[None, :] == lane[:, None]) & (
            np.arange(len(self.veh_s))[None, :] != rows[:, None]
        )
        delta = np.where(valid, delta, np.inf)
        nearest = delta.argmin(1) if delta.size else np.zeros(len(rows), dtype=np.int64)
        gap = (
            delta[np.arange(len(rows)), nearest] - VEHICLE_LENGTH
            if delta.size
            else np.full(len(rows), np.inf)
        )
        seen = gap <= GAP_RANGE
        return (
            np.where(seen, self.veh_speed[nearest] if delta.size else 0.0, 0.0),
            np.where(seen, np.clip(gap, 0.0, GAP_RANGE), GAP_RANGE),
            np.where(seen, self.veh_number[nearest] if delta.size else -1, -1),
        )

    def observe_agents(self) -> np.ndarray:
        """Per-CAV observations ``[I, obs_dim]`` (zero rows for CAVs that left the road), the
        features of :mod:`mapets_rl.envs.figure_eight`; records the observed vehicles' numbers
        ``[I, K]`` for ``neighbour_changed`` / ``neighbour_cav``."""
        n = self.config["n_cavs"]
        obs = np.zeros((n, self.obs_dim), dtype=np.float32)
        ids = np.full((n, 2 + 2 * (self.obs_dim > 7) + 2 * (self.obs_dim == 15)), -1, np.int64)
        cavs = np.flatnonzero(self.alive & (self.cav_row >= 0))
        rows = self.cav_row[cavs]
        self._positions[cavs] = self.veh_centre[rows]  # a crashed CAV's stays at the crash
        if len(rows):
            lane = self.veh_lane[rows]
            v_ahead, gap_ahead, id_ahead = self._neighbours(rows, lane, True)
            v_behind, gap_behind, id_behind = self._neighbours(rows, lane, False)
            columns = [
                self.veh_speed[rows],
                self.veh_centre[rows, 0],
                self.veh_centre[rows, 1],
                v_ahead,
                v_behind,
                gap_ahead,
                gap_behind,
            ]
            ids[cavs, 0], ids[cavs, 1] = id_ahead, id_behind
            if self.obs_dim > 7:
                columns += list(self._crossing_features(rows, cavs, ids))
            if self.obs_dim == TWO_LANE_OBS_DIM:
                other = 1 - lane
                v_a, g_a, i_a = self._neighbours(rows, other, True)
                v_b, g_b, i_b = self._neighbours(rows, other, False)
                columns += [self.veh_lateral[rows], v_a, v_b, g_a, g_b]
                ids[cavs, 4], ids[cavs, 5] = i_a, i_b
            obs[cavs] = np.stack(columns, 1)
        self._observed_ids = ids
        return obs

    def _crossing_features(
        self, rows: np.ndarray, cavs: np.ndarray, ids: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(d_cross, d_conflict, v_conflict)``, each ``[M]``, of the CAVs at road rows
        ``rows`` (agent indices ``cavs``); writes their crossing branch and conflicting
        vehicle's number into ``ids[:, 2:4]`` (the highway-env scenario's definition)."""
        period, crossings = self.geometry.length, self.geometry.crossing_coordinates
        ahead = (crossings[None, :] - self.veh_s[rows][:, None] + CROSSING_CLEAR) % period
        ahead -= CROSSING_CLEAR  # [M, 2]
        branch = ahead.argmin(1)
        d_cross = np.minimum(ahead[np.arange(len(rows)), branch], GAP_RANGE)
        others = (crossings[1 - branch][:, None] - self.veh_s[None, :] + CROSSING_CLEAR) % period
        others -= CROSSING_CLEAR  # [M, N]
        others[np.arange(len(rows)), rows] = np.inf
        nearest = others.argmin(1)
        distance = others[np.arange(len(rows)), nearest]
        seen = distance <= GAP_RANGE
        ids[cavs, 2] = branch
        ids[cavs, 3] = np.where(seen, self.veh_number[nearest], -1)
        return (
            d_cross,
            np.where(seen, distance, GAP_RANGE),
            np.where(seen, self.veh_speed[nearest], 0.0),
        )

    def _info(self, obs: np.ndarray) -> dict:
        n = self.config["n_cavs"]
        speed = np.where(self.alive, self._per_cav(self.veh_speed), 0.0)
        current, previous = self._observed_ids, self._previous_ids
        changed = np.zeros(n, dtype=bool)
        if previous is not None:
            changed = (current != previous).any(1) & self.alive
        self._previous_ids = current
        slots = NEIGHBOUR_SLOTS[self.obs_dim]
        observed = current[:, [column for column, _speed in slots]]
        is_cav = (observed >= 0) & (observed < n)
        neighbour_cav = np.where(is_cav & self.alive[np.clip(observed, 0, n - 1)], observed, -1)
        return {
            "positions": self._positions.copy(),
            "speed": speed.astype(np.float32),
            "distance": self._distance_step.astype(np.float32),
            "alive": self.alive.copy(),
            "neighbour_changed": changed,
            "neighbour_cav": neighbour_cav.astype(np.int64),
        }

    # --- stepping ----------------------------------------------------------------------------
    def validate_action(self, action: Any) -> np.ndarray:
        """``action`` as ``[I, act_dim]`` float64; ValueError unless it has that shape, is
        finite and within the bounds (target speed in ``[0, max_speed]``, the flag in
        ``[0, 1]``)."""
        try:
            action = np.asarray(action, dtype=np.float64)
        except (TypeError, ValueError):
            raise ValueError(
                f"action must be an array of numbers, got {type(action).__name__}"
            ) from None
        low, high = self.action_space.low, self.action_space.high
        require(
            action.shape == low.shape,
            f"action must have shape {low.shape} (n_cavs, act_dim), got {action.shape}",
        )
        require(bool(np.isfinite(action).all()), "action must be finite (got NaN or inf)")
        if not ((action >= low - 1e-4) & (action <= high + 1e-4)).all():
            flag = " and the lane-change flag in [0, 1]" if low.shape[1] == 2 else ""
            raise ValueError(
                f"action out of bounds: target speed must be in [0, {high[0, 0]:.2f}] m/s"
                f"{flag}, got min {action.min(0)} max {action.max(0)}"
            )
        return np.clip(action, low, high)

    def step(self, action: Any) -> tuple[np.ndarray, float, bool, bool, dict]:
        """Advance one policy step; outputs as :class:`~mapets_rl.envs.traffic.
        MultiAgentTrafficEnv`'s (``obs [I, obs]``, mean reward, terminated, truncated, info)."""
        require(
            self._sim is not None
            and self.steps_taken < self.config["horizon"]
            and self.alive.any(),
            "the episode is over (or never started: call reset() before stepping)",
        )
        action = self.validate_action(action)
        sim, cfg = self._sim, self.config
        frames = cfg["simulation_frequency"] // cfg["policy_frequency"]
        dt = 1.0 / cfg["simulation_frequency"]
        self._crashed_now[:] = False
        self._distance_step[:] = 0.0
        if action.shape[1] == 2:
            self._request_lane_changes(action[:, 1])
        for _ in range(frames):
            driving = np.flatnonzero(self.alive & ~self._crashed_now & (self.cav_row >= 0))
            v = self.veh_speed[self.cav_row[driving]]
            acc = np.clip(TargetSpeedVehicle.KP_A * (action[driving, 0] - v), ACC_MIN, ACC_MAX)
            command = np.maximum(v + acc * dt, 0.0)
            for i, speed in zip(driving, command, strict=True):
                sim.vehicle.setSpeed(self.cav_ids[i], float(speed))
            sim.simulationStep()
            crashed = self._collisions()
            self._read()
            moved = self.alive & ~self._crashed_now & (self.cav_row >= 0)
            self._distance_step += np.where(moved, self._per_cav(self.veh_speed) * dt, 0.0)
            self._crashed_now |= crashed & self.alive
        self.steps_taken += 1
        obs = self.observe_agents()
        crashed_now = self._crashed_now.copy()
        rewards = obs[:, 0] + obs[:, 3] + obs[:, 4] + cfg["collision_reward"] * crashed_now
        rewards = (rewards * (self.alive | crashed_now)).astype(np.float32)
        self.collision_step[crashed_now] = self.steps_taken
        self.alive &= ~crashed_now
        self._remove_crashed()
        self._episode_distances.append(self._distance_step.copy())
        info = self._info(obs)
        terminated = not self.alive.any()
        truncated = self.steps_taken >= cfg["horizon"]
        info.update(agent_rewards=rewards, agent_terminated=~self.alive, collided=crashed_now)
        if terminated or truncated:
            info["episode"] = self.episode_metrics()
        return obs, float(rewards.mean()), terminated, truncated, info

    def _request_lane_changes(self, flags: np.ndarray) -> None:
        """``changeLane`` to the other lane for the driving CAVs whose flag ``[I]`` is above
        0.5 and that are settled within ``SETTLED`` metres of their lane's centre."""
        lane = self._per_cav(self.veh_lane, -1)
        off_centre = np.abs(self._per_cav(self.veh_lateral) - lane) * self.geometry.lane_width
        wants = (flags > LANE_CHANGE_THRESHOLD) & self.alive & (lane >= 0)
        wants &= off_centre <= TargetSpeedVehicle.SETTLED
        for i in np.flatnonzero(wants):
            target = int(1 - lane[i])
            self._sim.vehicle.changeLane(self.cav_ids[i], target, LANE_CHANGE_DURATION)

    def _collisions(self) -> np.ndarray:
        """``[I]`` the CAVs in a collision SUMO reported in the last simulation step; every
        vehicle involved is noted to leave the road at the end of the policy step."""
        crashed = np.zeros(self.config["n_cavs"], dtype=bool)
        for collision in self._sim.simulation.getCollisions():
            for vid in (collision.collider, collision.victim):
                self._collided.add(vid)
                if vid.startswith("cav_"):
                    crashed[int(vid[4:])] = True
        return crashed

    def _remove_crashed(self) -> None:
        """Take the vehicles that collided in this step off the road (highway-env's rule) and
        out of the state read from the simulation."""
        gone = np.array([vid in self._collided for vid in self.veh_ids], dtype=bool)
        for vid in sorted(self._collided & set(self.veh_ids)):
            self._sim.vehicle.unsubscribe(vid)
            self._sim.vehicle.remove(vid)
        self._collided.clear()
        if gone.any():
            keep = ~gone
            self.veh_ids = [vid for vid, k in zip(self.veh_ids, keep, strict=True) if k]
            for name in (
                "veh_speed",
                "veh_s",
                "veh_lane",
                "veh_lateral",
                "veh_centre",
                "veh_number",
            ):
                setattr(self, name, getattr(self, name)[keep])
            self._index_cavs()

    def episode_metrics(self) -> dict[str, float]:
        """Agility and safety (paper eqs. 27-28), collisions and the CAVs' mean speed."""
        distances = np.stack(self._episode_distances, 0) if self._episode_distances else None
        horizon = self.config["horizon"]
        steps = max(len(self._episode_distances), 1)
        collision_steps = np.where(self.alive, horizon, self.collision_step - 1)
        n = self.config["n_cavs"]
        return {
            "agility": float(agility(distances, collision_steps)) if distances is not None else 0.0,
            "safety": float(safety(collision_steps, horizon)),
            "collisions": int((~self.alive).sum()),
            "mean_speed": float(distances.sum() / steps / self.dt / n)
            if distances is not None
            else 0.0,
        }

    def render(self) -> None:
        """No frames (``render_mode`` is None)."""
        return None

    def close(self) -> None:
        """End the simulation (and free the in-process one for another env)."""
        if self._sim is self.libsumo:
            with contextlib.suppress(self.libsumo.TraCIException):
                self.libsumo.close()
            _InProcess.holder = None
        elif self._sim is not None:
            self._closer()
        self._sim = None
        self._finalizer()


class SumoFigureEightParallelEnv(FigureEightParallelEnv):
    """The SUMO figure-eight as a PettingZoo ``ParallelEnv`` (:class:`~mapets_rl.envs.parallel.
    FigureEightParallelEnv`'s arguments and constructor, on :class:`SumoFigureEightEnv`;
    ``render_mode`` must be None)."""

    metadata = {**TrafficParallelEnv.metadata, "name": "sumo_figure_eight_v0"}
    env_class = SumoFigureEightEnv  # type: ignore[assignment]
