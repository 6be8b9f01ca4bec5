"""Freeway with an on-ramp (issue 21): a social dilemma on the 3-lane freeway.

The freeway of :mod:`mapets_rl.envs.freeway` (same lanes, discrete actions ``KL, CL, CR, ES``,
reward eq. 10 ``w * velocity + comfort`` with collisions, CAV ratio and vehicle count) gains an
on-ramp on its right, built as highway-env's ``merge-v0`` builds its own: a ramp lane
(``ramp_length`` metres, slanting in from ``ramp_offset`` metres to the right of the rightmost
lane) leads to an acceleration lane parallel to the rightmost lane from ``merge_start`` for
``merge_length`` metres, which ends at an :class:`~highway_env.vehicle.objects.Obstacle` (the
*merge point*, ``merge_end = merge_start + merge_length``). Both ramp lanes are ``forbidden``
(mainline vehicles never change into them). A share ``ramp_fraction`` of the ``n_vehicles``
vehicles starts on the ramp (random slots ``min_spacing`` apart, speeds drawn from
``ramp_speed``), the rest on the mainline as on the freeway; CAVs are drawn at random among
all of them. Every vehicle, CAV or human, draws its target speed from the one range
``target_speed``, so that a trend over the CAV ratio cannot come from target speeds.

Merging. Human drivers merge as highway-env's do: MOBIL on the acceleration lane, whose
obstacle is a standing leader, so a ramp vehicle merges when MOBIL finds the gap safe for the
new follower (imposed braking <= 2 m/s^2) and otherwise stops before the obstacle; like
highway-env's IDM vehicles it never starts a lane change below 1 m/s, so a ramp vehicle that
has come to a stop stays there. A CAV on the ramp merges the same way (MOBIL) whatever it
plays, and on the acceleration lane ``CL`` merges at once (with ``ramp_forcing``, the
default; without it ``CL``/``CR`` on the acceleration lane count as ``KL``, motion and comfort,
so a ramp CAV merges only as a ramp human does); ``CL``/``CR`` on the slanted ramp lane have
no lane to go to and count as ``KL``. On the mainline a CAV's actions are the
freeway's (``CR`` from the rightmost lane stays refused: the acceleration lane is not a lane
to drive in).

The dilemma: a mainline CAV in the rightmost lane near the merge point gives up little when
it moves left to leave a ramp vehicle a gap (one step of comfort 1 instead of 3), but the
ramp vehicle that finds no gap stops at the end of the acceleration lane and earns
``w * 0 + comfort`` for the rest of the episode; a selfish CAV keeps its lane (or overtakes).

The dilemma variant (issue 50; the settings of ``configs/fragments/freeway-merge-dilemma-stack``:
``ramp_forcing=False``, ``target_speed=(28, 28)``, ``velocity_weight=0.08``,
``lane_change_comfort=0``, with the shield). With the defaults at ``w = 1`` the scenario is no
dilemma: the left lanes are faster and the merging ramp traffic slows the rightmost lane, so
leaving it near the merge is worth more speed to the mover than the comfort it costs (3 -> 1
for the step of the change), and a ramp CAV's ``CL`` on the acceleration lane forces its way
in without MOBIL's safety test, a selfish lever worth +8.7% over keep lane. The variant closes
both, each setting for one reason:

- without ``ramp_forcing`` a ramp CAV merges only when MOBIL finds the gap, whatever it plays,
  so forcing is worth nothing;
- with one target speed for every vehicle no lane is faster by its drivers' wishes (a lane is
  slower only where traffic slows it), so a move buys its mover little speed;
- a small ``w`` weighs that speed (``w * dv`` per step) below the comfort a move costs, while a
  ramp vehicle let in goes from standing to driving, ``w * 15-25`` per step for the rest of the
  episode, to the system. ``w`` alone cannot do it: every vehicle earns comfort 3 per step
  whatever it does, so what cooperation can change shrinks with ``w`` (at ``w = 0.05`` the
  cooperative rule gains less than 5% over keep lane);
- so a lane change also earns no comfort (``lane_change_comfort = 0``, 1 in the paper's eq. 9:
  a move costs its mover 3 instead of 2), which raises the mover's cost without shrinking the
  system's gain.

Measured with the exact counterfactuals of :mod:`mapets_rl.envs.torch_freeway.counterfactuals`
(``benchmarks/dilemma_counterfactuals.py``; ``docs/results/scenarios.md``, "The dilemma variant
of freeway-merge", which also lists what was tried): against keep-lane co-players 84% of the
cooperative rule's yields cost the yielder and 92% of all mainline moves near the merge cost the
mover (discounted by 0.95; undiscounted 61% and 75%), the rule still beats keep lane by +6.6%,
and forcing changes nothing.

Observation (``OBS_DIM = 24``): the freeway's 22 entries, where for a CAV in the rightmost
lane the *right* neighbour block reads the ramp (the nearest ramp vehicle ahead and behind,
on the slanted ramp or the acceleration lane) and for a CAV on the ramp the *own* block reads
the ramp and the *left* block the rightmost lane; then ``(merge_start - x, merge_end - x)``,
the distances [m] along the road to the start of the acceleration lane and to the merge
point, clipped to ``+-perception``.

Behaviour counts (in :meth:`FreewayMergeEnv.episode_metrics`, with the same definitions on the
torch backend, :class:`~mapets_rl.envs.torch_freeway.simulator.BatchedFreeway`), read per policy
step by comparing every vehicle's lane before and after the step (:data:`BEHAVIOUR_COUNTS`):

- ``mainline_changes_near_merge``: CAV moves from one mainline lane to another that start (the
  CAV's x at the step's start) from :data:`NEAR_MERGE` metres before the acceleration lane to
  its end (``merge_start - NEAR_MERGE <= x <= merge_end``); ``mainline_changes_elsewhere``:
  the other mainline-to-mainline CAV moves (a merge from the ramp is neither);
- ``ramp_forced_merges``: ramp CAVs that reach the mainline through their own Change Left on the
  acceleration lane (a forced merge: the CAV's ``CL`` sets its target lane, without MOBIL's
  safety test); ``ramp_mobil_merges``: every other ramp vehicle, CAV or human driver, that
  reaches the mainline (MOBIL chose the change). A CAV's move onto the mainline counts as forced
  when its own ``CL`` set the pending change (the mark is dropped at the end of a step that
  finds the change cancelled by MOBIL's abort rule, so an abort followed by MOBIL's own change
  within one policy step still counts as forced);
  ``ramp_forced_merges + ramp_mobil_merges + ramp_stuck`` plus the ramp vehicles that crashed
  on the ramp is the number of ramp vehicles.

The freeway without a ramp reports none of them: its lane changes have no merge to be near, and
its metrics stay those of the paper's freeway.

Why an on-ramp rather than a lane drop. With a lane drop every CAV in the dropped lane must
change lanes or stop, so "keep lane" is not a policy but a crash into the lane's end, and the
scripted reference every learner is compared with would be meaningless. With an on-ramp
keep-lane stays a safe, sensible policy whose cost falls on the ramp vehicles: exactly the
situation in which a selfish CAV's best reply differs from the system's (measured in
``docs/results/scenarios.md``, section "freeway-merge: an on-ramp social dilemma"). A lane drop
was not measured.
"""

from __future__ import annotations

import numpy as np
from highway_env.road.lane import LineType, StraightLane
from highway_env.road.road import RoadNetwork
from highway_env.vehicle.kinematics import Vehicle
from highway_env.vehicle.objects import Obstacle

from mapets_rl.envs.freeway import (
    CL,
    CR,
    KL,
    FreewayEnv,
    LaneDecisionAction,
    LaneDecisionVehicle,
)
from mapets_rl.envs.freeway import (
    OBS_DIM as FREEWAY_OBS_DIM,
)
from mapets_rl.envs.lanes import FastStraightLane
from mapets_rl.envs.parallel import FreewayParallelEnv
from mapets_rl.envs.road import SortedNeighbourRoad
from mapets_rl.envs.traffic import require
from mapets_rl.envs.validation import is_real, require_number, require_range

OBS_DIM = FREEWAY_OBS_DIM + 2
RAMP_ROAD = ("r", "0")
"""Road segment (from, to) of the slanted ramp lane ``("r", "0", 0)``; the acceleration lane
is ``("0", "1", lanes)``, beside the mainline lanes ``("0", "1", 0 .. lanes - 1)``."""
MERGE_VIEW_POINT = 0.8
"""Where the merge point stands in a rendered frame, as a fraction of its width from the left
(:attr:`FreewayMergeEnv.view_centre`)."""
NEAR_MERGE = 100.0
"""A mainline lane change counts as near the merge from this many metres before the
acceleration lane to its end [m] (where a cooperative CAV yields to the ramp)."""
BEHAVIOUR_COUNTS = (
    "mainline_changes_near_merge",
    "mainline_changes_elsewhere",
    "ramp_forced_merges",
    "ramp_mobil_merges",
)
"""The episode's behaviour counts of ``freeway-merge`` (module docstring), on both backends."""


def ramp_vehicle_count(config: dict) -> int:
    """How many of ``n_vehicles`` start on the ramp: ``round(ramp_fraction * n_vehicles)``."""
    return int(round(config["ramp_fraction"] * config["n_vehicles"]))


class MergeCAV(LaneDecisionVehicle):
    """A CAV of ``freeway-merge``: on the ramp it merges by MOBIL as a human driver does."""

    def act(self, action: dict | str | None = None) -> None:
        self.enable_lane_change = self.road.lane_id(self.lane_index) == self.road.n_lanes - 1
        super().act(action)


class MergeDecisionAction(LaneDecisionAction):
    """``LaneDecisionAction`` where ``CL``/``CR`` on the slanted ramp lane count as ``KL``, and
    on the acceleration lane too when ``ramp_forcing`` is off."""

    @property
    def vehicle_class(self) -> type:
        return MergeCAV

    def act(self, action: np.ndarray) -> None:
        """Apply ``action [I]``; a CAV on the acceleration lane whose ``CL`` sets its target
        lane (it is not already changing lanes) is marked as forcing its merge
        (``FreewayMergeEnv.forcing``). Without ``ramp_forcing`` every ramp CAV's ``CL``/``CR``
        is ``KL`` (motion and comfort), so it merges by MOBIL only."""
        env = self.env
        action = np.array(action, dtype=np.int64)
        acceleration_lane = ("0", "1", env.config["lanes"])
        forcing = env.config["ramp_forcing"]
        for i, cav in enumerate(env.cavs):
            refused = cav.lane_index[:2] == RAMP_ROAD or (
                not forcing and cav.lane_index == acceleration_lane
            )
            if refused and action[i] in (CL, CR):
                action[i] = KL
            settled = cav.lane_index == acceleration_lane == cav.target_lane_index
            env.forcing[i] |= bool(env.alive[i] and settled and action[i] == CL)
        super().act(action)


class FreewayMergeEnv(FreewayEnv):
    """The freeway with an on-ramp (see module docstring).

    Config keys: the freeway's (:class:`FreewayEnv`) except ``cav_target_speed`` and
    ``hv_target_speed``, replaced by ``target_speed`` (one range for CAVs and humans), plus
    ``merge_start`` (x of the acceleration lane's start [m]), ``merge_length`` [m],
    ``ramp_length`` [m], ``ramp_offset`` (lateral distance of the ramp's far end from the
    acceleration lane [m]), ``ramp_fraction`` (share of the vehicles that start on the ramp)
    and ``ramp_speed`` (their start speeds [m/s]), ``ramp_forcing`` (True: a ramp CAV's ``CL``
    on the acceleration lane merges it at once; False: it counts as ``KL``, the dilemma
    variant's setting); defaults in :meth:`default_config`.
    """

    obs_dim = OBS_DIM
    cav_class = MergeCAV
    forcing: np.ndarray
    """``[I]`` the CAVs whose pending change onto the mainline their own ``CL`` set."""
    behaviour: dict[str, int]
    """The episode's behaviour counts so far (:data:`BEHAVIOUR_COUNTS`, module docstring)."""

    @classmethod
    def default_config(cls) -> dict:
        config = super().default_config()
        del config["cav_target_speed"], config["hv_target_speed"]
        config.update(
            {
                "target_speed": (25.0, 31.0),
                "merge_start": 500.0,
                "merge_length": 45.0,
                "ramp_length": 300.0,
                "ramp_offset": 15.0,
                "ramp_fraction": 0.5,
                "ramp_speed": (15.0, 20.0),
                "ramp_forcing": True,
            }
        )
        return config

    @classmethod
    def validate_target_speeds(cls, config: dict) -> None:
        """Every vehicle draws its target speed from ``target_speed``."""
        require_range(config, "target_speed", low=0.0, high=config["speed_limit"], unit="m/s")
        require(config["target_speed"][0] > 0.0, "target_speed must be a range with lo > 0 "
                f"[m/s], got {config['target_speed']!r}")  # fmt: skip

    @classmethod
    def validate_config(cls, config: dict) -> None:
        require(
            is_real(config["ramp_fraction"]) and 0.0 <= config["ramp_fraction"] <= 1.0,
            f"ramp_fraction must be a number in [0, 1], got {config['ramp_fraction']!r}",
        )
        super().validate_config(config)
        require_number(config, "merge_length", low=10.0, unit="m")
        require_number(
            config,
            "merge_start",
            low=0.0,
            low_open=True,
            high=config["road_length"] - config["merge_length"],
            unit="m",
        )
        require_number(config, "ramp_length", low=config["min_spacing"], unit="m")
        require_number(config, "ramp_offset", low=0.0, unit="m")
        require_range(config, "ramp_speed", low=0.0, high=config["speed_limit"], unit="m/s")
        require(
            isinstance(config["ramp_forcing"], bool),
            f"ramp_forcing must be True or False, got {config['ramp_forcing']!r}",
        )
        n_ramp = ramp_vehicle_count(config)
        ramp_slots = int(config["ramp_length"] // config["min_spacing"])
        require(
            n_ramp <= ramp_slots,
            f"ramp_fraction={config['ramp_fraction']} puts {n_ramp} of n_vehicles="
            f"{config['n_vehicles']} on a ramp of ramp_length={config['ramp_length']} m, which "
            f"holds {ramp_slots} at min_spacing={config['min_spacing']} m: ramp_fraction must "
            f"be <= {ramp_slots / config['n_vehicles']:.3g}",
        )
        main_slots = FreewayEnv.capacity(config)
        require(
            config["n_vehicles"] - n_ramp <= main_slots,
            f"n_vehicles={config['n_vehicles']} leave {config['n_vehicles'] - n_ramp} on the "
            f"mainline, which holds {main_slots} (spawn_length={config['spawn_length']} m x "
            f"{config['lanes']} lanes at min_spacing={config['min_spacing']} m): n_vehicles "
            f"must be <= {main_slots + n_ramp}",
        )

    @staticmethod
    def capacity(config: dict) -> int:
        """Vehicles that fit in the spawn region and on the ramp at ``min_spacing``."""
        return FreewayEnv.capacity(config) + int(config["ramp_length"] // config["min_spacing"])

    # --- rendering ---------------------------------------------------------------------------
    @property
    def view_centre(self) -> np.ndarray:
        """The camera's centre [m]: fixed on the merge area (unlike the freeway's camera on the
        CAVs, which leaves the ramp behind within a few steps), so that every merge of the
        episode can be watched. The merge point stands at :data:`MERGE_VIEW_POINT` of the
        frame's width, with the end of the slanted ramp and the acceleration lane before it and
        the mainline after it; vertically the frame is centred between the leftmost lane and
        the ramp's far end."""
        width = StraightLane.DEFAULT_WIDTH
        visible = self.config["screen_width"] / self.config["scaling"]
        x = self.merge_end - (MERGE_VIEW_POINT - 0.5) * visible
        y = (self.config["lanes"] * width + self.config["ramp_offset"] - width / 2) / 2
        return np.array([x, y])

    # --- road --------------------------------------------------------------------------------
    @property
    def merge_end(self) -> float:
        """x of the merge point, the end of the acceleration lane [m]."""
        return float(self.config["merge_start"] + self.config["merge_length"])

    @property
    def lane_tables(self) -> int:
        """The mainline lanes and the ramp (slanted lane and acceleration lane as one)."""
        return self.config["lanes"] + 1

    def lane_id(self, lane_index: tuple) -> int:
        """Neighbour-search lane of ``lane_index``: the ramp is lane ``lanes``."""
        return self.config["lanes"] if lane_index[:2] == RAMP_ROAD else lane_index[2]

    def _make_network(self) -> RoadNetwork:
        cfg = self.config
        net = super()._make_network()
        y = cfg["lanes"] * StraightLane.DEFAULT_WIDTH
        start, end = cfg["merge_start"], self.merge_end
        c, s = LineType.CONTINUOUS_LINE, LineType.STRIPED
        ramp = FastStraightLane(
            [start - cfg["ramp_length"], y + cfg["ramp_offset"]],
            [start, y],
            line_types=(c, c),
            forbidden=True,
            speed_limit=cfg["speed_limit"],
        )
        net.add_lane(*RAMP_ROAD, ramp)
        acceleration = FastStraightLane(
            [start, y], [end, y], line_types=(s, c), forbidden=True, speed_limit=cfg["speed_limit"]
        )
        net.add_lane("0", "1", acceleration)
        return net

    def _make_road(self) -> SortedNeighbourRoad:
        road = super()._make_road()
        lane_index = ("0", "1", self.config["lanes"])
        end = Obstacle(
            road, road.network.get_lane(lane_index).position(self.config["merge_length"], 0)
        )
        end.lane_index, end.lane = lane_index, road.network.get_lane(lane_index)
        road.objects.append(end)
        return road

    # --- vehicles ----------------------------------------------------------------------------
    def _spawn_slots(self, n: int | None = None) -> list[tuple[tuple, float]]:
        """The freeway's mainline slots for all but the ramp vehicles, then random distinct
        slots ``min_spacing`` apart on the slanted ramp lane."""
        cfg = self.config
        n_ramp = ramp_vehicle_count(cfg)
        slots = super()._spawn_slots(cfg["n_vehicles"] - n_ramp)
        ramp_slots = int(cfg["ramp_length"] // cfg["min_spacing"])
        for slot in self.np_random.choice(ramp_slots, size=n_ramp, replace=False):
            slots.append(((*RAMP_ROAD, 0), float(slot * cfg["min_spacing"])))
        return slots

    def _initial_speed(self, lane_index: tuple) -> float:
        key = "ramp_speed" if lane_index[:2] == RAMP_ROAD else "initial_speed"
        return float(self.np_random.uniform(*self.config[key]))

    def _target_speed(self, cav: bool) -> float:
        """A draw from ``target_speed``, for CAVs and human drivers alike."""
        return float(self.np_random.uniform(*self.config["target_speed"]))

    def on_ramp(self, vehicle: Vehicle) -> bool:
        """Whether ``vehicle`` is on the ramp (slanted lane or acceleration lane)."""
        return self.lane_id(vehicle.lane_index) == self.config["lanes"]

    # --- behaviour counts ----------------------------------------------------------------------
    def _reset(self) -> None:
        super()._reset()
        self.forcing = np.zeros(len(self.cavs), dtype=bool)
        self.behaviour = dict.fromkeys(BEHAVIOUR_COUNTS, 0)

    def _simulate(self, action: np.ndarray | None = None) -> None:
        lanes_before = [v.lane_index for v in self.vehicles_all]
        x_before = [float(cav.position[0]) for cav in self.cavs]
        super()._simulate(action)
        self._count_behaviour(lanes_before, x_before)

    def _count_behaviour(self, lanes_before: list[tuple], x_before: list[float]) -> None:
        """Add the step's lane changes and merges to :attr:`behaviour` (module docstring), from
        every vehicle's lane index before the step (``vehicles_all`` order) and the CAVs' x at
        its start [m]; then keep the forcing mark only of CAVs still waiting on the ramp for the
        change their ``CL`` set."""
        lanes = self.config["lanes"]
        forcing = {id(cav): bool(self.forcing[i]) for i, cav in enumerate(self.cavs)}
        before_of = {}
        for vehicle, before in zip(self.vehicles_all, lanes_before, strict=True):
            before_of[id(vehicle)] = before
            if self.lane_id(before) == lanes and self.lane_id(vehicle.lane_index) < lanes:
                forced = forcing.get(id(vehicle), False)
                self.behaviour["ramp_forced_merges" if forced else "ramp_mobil_merges"] += 1
        near = (self.config["merge_start"] - NEAR_MERGE, self.merge_end)
        for i, cav in enumerate(self.cavs):
            before, after = before_of[id(cav)], cav.lane_index
            if before != after and max(self.lane_id(before), self.lane_id(after)) < lanes:
                where = "near_merge" if near[0] <= x_before[i] <= near[1] else "elsewhere"
                self.behaviour[f"mainline_changes_{where}"] += 1
            self.forcing[i] &= self.on_ramp(cav) and cav.target_lane_index != after

    # --- observations ------------------------------------------------------------------------
    def define_spaces(self) -> None:
        super().define_spaces()
        self.action_type = MergeDecisionAction(self)
        self.action_space = self.action_type.space()

    def _observed_lanes(self, cav: Vehicle) -> tuple[tuple | None, tuple | None, tuple | None]:
        """Left / own / right lanes by neighbour-search lane: the ramp is right of the
        rightmost lane."""
        own = self.lane_id(cav.lane_index)
        return tuple(
            ("0", "1", lane) if 0 <= lane <= self.config["lanes"] else None
            for lane in (own - 1, own, own + 1)
        )

    def observe_agents(self) -> np.ndarray:
        obs = super().observe_agents()
        perception = self.config["perception"]
        for i, cav in enumerate(self.cavs):
            if self.alive[i]:
                x = float(cav.position[0])
                obs[i, FREEWAY_OBS_DIM:] = np.clip(
                    (self.config["merge_start"] - x, self.merge_end - x), -perception, perception
                )
        return obs

    def episode_metrics(self) -> dict[str, float]:
        """The freeway's, plus ``ramp_stuck`` (vehicles still on the ramp at the end) and the
        behaviour counts of :data:`BEHAVIOUR_COUNTS` (module docstring)."""
        metrics = super().episode_metrics()
        metrics["ramp_stuck"] = sum(self.on_ramp(v) for v in self.road.vehicles)
        metrics.update(self.behaviour)
        return metrics


class FreewayMergeParallelEnv(FreewayParallelEnv):
    """``freeway-merge`` as a PettingZoo ``ParallelEnv`` (args as ``FreewayParallelEnv``;
    ``**config``: further ``FreewayMergeEnv`` keys)."""

    metadata = {**FreewayParallelEnv.metadata, "name": "freeway_merge_v0"}
    env_class = FreewayMergeEnv
