"""``freeway`` and ``freeway-merge`` as one tensor program over ``B`` independent roads.

:class:`BatchedFreeway` holds the state of ``B`` roads of ``V`` vehicles each (``[B, V]``
tensors; on ``freeway-merge`` a ``V + 1``-th body per road is the obstacle that ends the
acceleration lane) and their ``I`` CAVs (``[B, I]``), and advances all roads by one policy step
at a time: the CAVs' decisions (KL, CL, CR, ES), then ``simulation_frequency /
policy_frequency`` simulation steps of highway-env's drivers (IDM + MOBIL, lane-following
steering, the kinematic bicycle model, rectangle collisions; :mod:`.dynamics`), then the
observation, reward and episode bookkeeping of :class:`~mapets_rl.envs.FreewayEnv`. What each
part reproduces, and where the simulator departs from highway-env, is listed in
``docs/ARCHITECTURE.md`` and measured in ``docs/results/scenarios.md`` ("The batched freeway
against highway-env").

Randomness is drawn only when a road is reset (spawn slots, speeds, target speeds, human IDM
exponents, which vehicles are CAVs), from the simulator's own ``torch.Generator``; stepping is
deterministic. :meth:`BatchedFreeway.snapshot` / :meth:`BatchedFreeway.restore` copy the whole
state, the generator's included, so a rollout can branch and replay bit for bit.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import torch
from highway_env.vehicle.behavior import IDMVehicle
from tensordict import TensorDict, TensorDictBase

from mapets_rl.envs.freeway import CL, CR, ES, KL
from mapets_rl.envs.freeway import OBS_DIM as FREEWAY_OBS_DIM
from mapets_rl.envs.freeway_merge import BEHAVIOUR_COUNTS, NEAR_MERGE
from mapets_rl.envs.torch_freeway.dynamics import (
    COMFORT_ACC_MAX,
    COMFORT_ACC_MIN,
    DISTANCE_WANTED,
    KP_HEADING,
    KP_LATERAL,
    LENGTH,
    MAX_STEERING_ANGLE,
    SQRT_AB,
    TIME_WANTED,
)
from mapets_rl.envs.torch_freeway.geometry import (
    LANE_WIDTH,
    MAINLINE,
    VEHICLE_LENGTH,
    FreewayGeometry,
)
from mapets_rl.envs.torch_freeway.native import kernel_unavailable, load_kernel
from mapets_rl.envs.torch_freeway.physics import (
    ACC_MAX,
    LANE_CHANGE_DELAY,
    MAX_BRAKING_IMPOSED,
    MIN_ACC_GAIN,
    Bodies,
    RoadPhysics,
)
from mapets_rl.envs.validation import check_device, check_seed, is_integer, is_real
from mapets_rl.envs.vehicles import ACC_MIN
from mapets_rl.memory import available_memory

DELTA_RANGE = tuple(IDMVehicle.DELTA_RANGE)
"""Range of a human driver's IDM exponent (``IDMVehicle.randomize_behavior``)."""

KERNELS = ("auto", "native", "torch")
"""How a CPU simulator steps: the fused C++ kernel where it builds (``"auto"``), always
(``"native"``), or never (``"torch"``: the torch program, as on other devices). The two
programs are different experiments: they agree step by step only up to rounding, and the
trajectories part after some steps (a run records which one ran,
:func:`mapets_rl.experiment.runner.simulator_program`)."""

STATE_FLOAT = (
    "x", "y", "heading", "speed", "target_speed", "delta", "acc", "steer",
    "impact_x", "impact_y",
)  # fmt: skip
"""Per-body float entries of the state ``[B, N]`` (in the simulator's dtype; the lane-change
timer ``"timer"`` is float64 whatever the dtype: highway-env adds 0.1 s to it every simulation
step and decides when it exceeds 1 s, and 0.1 added ten times is 0.99999... in float64 but
1.0000001 in float32, which would make every MOBIL decision one simulation step early)."""


STEP_WORKING_SET = 24
"""A road's memory while it steps, in multiples of its state's: the copies, neighbour tables
and outputs of a policy step (measured at 17-21x, the torch program with the shield the
most)."""


def empty_state(
    roads: int,
    n_bodies: int,
    n_cavs: int,
    merge: bool,
    device: torch.device | str = "cpu",
    dtype: torch.dtype = torch.float32,
) -> TensorDict:
    """The zeroed state of ``roads`` roads: bodies ``[roads, n_bodies]``, agents
    ``[roads, n_cavs]`` and the per-road counters (with the behaviour counts where ``merge``)."""
    b, n, i = roads, n_bodies, n_cavs
    bodies = {key: torch.zeros(b, n, dtype=dtype, device=device) for key in STATE_FLOAT}
    bodies["timer"] = torch.zeros(b, n, dtype=torch.float64, device=device)
    for key in ("lane", "target", "decision"):
        bodies[key] = torch.zeros(b, n, dtype=torch.long, device=device)
    for key in ("crashed", "present", "has_impact", "cav"):
        bodies[key] = torch.zeros(b, n, dtype=torch.bool, device=device)
    agents = {
        "slot": torch.zeros(b, i, dtype=torch.long, device=device),
        "alive": torch.zeros(b, i, dtype=torch.bool, device=device),
    }
    roads_state = {
        "steps": torch.zeros(b, dtype=torch.long, device=device),
        "speed_sum": torch.zeros(b, dtype=torch.float64, device=device),
        "comfort_sum": torch.zeros(b, dtype=torch.float64, device=device),
        "samples": torch.zeros(b, dtype=torch.float64, device=device),
        "shielded": torch.zeros(b, dtype=torch.long, device=device),
    }
    if merge:  # the behaviour counts (FreewayMergeEnv's)
        agents["forcing"] = torch.zeros(b, i, dtype=torch.bool, device=device)
        roads_state.update({key: torch.zeros(b, dtype=torch.long, device=device)
                            for key in BEHAVIOUR_COUNTS})  # fmt: skip
    return TensorDict(
        {
            "bodies": TensorDict(bodies, batch_size=[b, n], device=device),
            "agents": TensorDict(agents, batch_size=[b, i], device=device),
            **roads_state,
        },
        batch_size=[b],
        device=device,
    )


def road_bytes(config: dict, merge: bool, dtype: torch.dtype = torch.float32) -> int:
    """The bytes one road of scenario ``config`` takes while it steps: its state tensors
    (:func:`empty_state`) times :data:`STEP_WORKING_SET`."""
    bodies = int(config["n_vehicles"]) + (1 if merge else 0)
    state = empty_state(1, bodies, int(config["n_cavs"]), merge, "cpu", dtype)
    return STEP_WORKING_SET * sum(t.numel() * t.element_size() for t in state.values(True, True))


def check_roads_fit(
    config: dict,
    merge: bool,
    roads: int,
    device: torch.device | str,
    dtype: torch.dtype,
    name: str,
) -> None:
    """ValueError (one line, naming ``name``) when ``roads`` roads of scenario ``config`` would
    take more memory while they step (:func:`road_bytes`) than ``device`` has available
    (:func:`~mapets_rl.memory.available_memory`: the host, ``ulimit -v`` and the process's
    own cgroup; CUDA's free memory): before a road is allocated."""
    free = available_memory(device)
    per_road = road_bytes(config, merge, dtype)
    if free is not None and roads * per_road > free:
        raise ValueError(
            f"{name}={roads} roads need about {roads * per_road / 2**30:.1f} GiB on {device} "
            f"({per_road / 1024:.0f} KiB each while they step), more than the "
            f"{free / 2**30:.1f} GiB available: {name} must be at most {free // per_road}"
        )


@dataclass
class StepResult:
    """What one policy step of every road returns (``B`` roads, ``I`` CAVs).

    Attributes:
        observation: ``[B, I, obs_dim]`` of the CAVs that acted (zero rows for the others).
        reward: ``[B, I]`` reward of the step (0 for CAVs that did not act).
        acting: ``[B, I]`` the CAVs that were driving at the start of the step.
        alive: ``[B, I]`` the CAVs still driving after it.
        collided: ``[B, I]`` the CAVs that crashed in this step.
        distance: ``[B, I]`` metres travelled in the step.
        traffic_velocity, traffic_comfort: ``[B]`` means over all vehicles on the road.
        truncated: ``[B]`` the horizon is reached.
        terminated: ``[B]`` every CAV has crashed.
        shielded: ``[B, I]`` the CAVs whose decision the shield replaced (all False without
            ``config["shield"]``).
    """

    observation: torch.Tensor
    reward: torch.Tensor
    acting: torch.Tensor
    alive: torch.Tensor
    collided: torch.Tensor
    distance: torch.Tensor
    traffic_velocity: torch.Tensor
    traffic_comfort: torch.Tensor
    truncated: torch.Tensor
    terminated: torch.Tensor
    shielded: torch.Tensor | None = None


class BatchedFreeway:
    """``B`` roads of ``freeway`` (``merge=False``) or ``freeway-merge`` stepped together.

    Args:
        config: a complete, validated ``FreewayEnv`` / ``FreewayMergeEnv`` config (defaults
            filled in, ``n_cavs`` derived).
        merge: the road has the on-ramp.
        num_roads: ``B``.
        device, dtype: where the state lives and its float precision (float32 by default;
            float64 matches highway-env's arithmetic to rounding).
        seed: seed of the simulator's random generator.
        kernel: on a CPU, step with the fused C++ kernel (:mod:`.native`; built on first use)
            instead of the torch program (``"auto"``: where it can be built; ``"native"``:
            required; ``"torch"``: never). On other devices the torch program runs.
    """

    def __init__(
        self,
        config: dict,
        merge: bool,
        num_roads: int,
        device: torch.device | str = "cpu",
        dtype: torch.dtype = torch.float32,
        seed: int = 0,
        kernel: str = "auto",
    ) -> None:
        if kernel not in KERNELS:
            raise ValueError(f"kernel must be one of {list(KERNELS)}, got {kernel!r}")
        if not (is_integer(num_roads) and num_roads >= 1):
            raise ValueError(f"num_roads must be an integer >= 1, got {num_roads!r}")
        seed = check_seed(seed) or 0
        self.config = dict(config)
        self.kernel_choice = kernel
        self.merge = merge
        self.device = check_device(device)
        check_roads_fit(self.config, merge, int(num_roads), self.device, dtype, "num_roads")
        self.dtype = dtype
        self.geometry = FreewayGeometry.from_config(config, merge, self.device, dtype)
        self.n_roads = int(num_roads)
        self.n_vehicles = int(config["n_vehicles"])
        self.n_bodies = self.n_vehicles + (1 if merge else 0)
        self.n_cavs = int(config["n_cavs"])
        self.n_ramp = int(round(config["ramp_fraction"] * self.n_vehicles)) if merge else 0
        self.obs_dim = FREEWAY_OBS_DIM + (2 if merge else 0)
        self.frames = int(config["simulation_frequency"]) // int(config["policy_frequency"])
        self.dt = 1.0 / float(config["simulation_frequency"])
        self.speed_limit = float(config["speed_limit"])
        self.generator = torch.Generator(device=self.device)
        self.generator.manual_seed(seed)
        self.physics = RoadPhysics(
            self.geometry, self.n_vehicles, self.n_bodies, self.speed_limit, self.dt
        )
        self.is_obstacle = self.physics.is_obstacle
        self.kernel = None
        if kernel != "torch" and self.device.type == "cpu":
            self.kernel = load_kernel()
            if self.kernel is None and kernel == "native":
                raise RuntimeError(f"the fused CPU kernel cannot be built: {kernel_unavailable()}")
            self._kernel_args = self._native_constants() if self.kernel is not None else None
        self.state = empty_state(
            self.n_roads, self.n_bodies, self.n_cavs, merge, self.device, self.dtype
        )
        self.reset(torch.ones(self.n_roads, dtype=torch.bool, device=self.device))

    # --- state ---------------------------------------------------------------------------------
    def snapshot(self) -> TensorDict:
        """A copy of the whole state of every road, the random generator's included
        (``"rng"``); :meth:`restore` brings it back bit for bit."""
        snap = self.state.clone()
        snap.batch_size = []
        snap["rng"] = self.generator.get_state().to(self.device)
        return snap

    def branch(self, road: int, copies: int) -> BatchedFreeway:
        """A new simulator of ``copies`` roads, each the current state of road ``road`` (same
        config, device, dtype and kernel): a rollout branches, and every copy can play other
        actions from here."""
        if not (is_integer(road) and 0 <= road < self.n_roads):
            raise ValueError(f"road must be in [0, {self.n_roads - 1}] (an integer), got {road!r}")
        if not (is_integer(copies) and copies >= 1):
            raise ValueError(f"copies must be an integer >= 1, got {copies!r}")
        check_roads_fit(self.config, self.merge, int(copies), self.device, self.dtype, "copies")
        return self.take(torch.full((copies,), road, dtype=torch.long))

    def take(self, roads: torch.Tensor) -> BatchedFreeway:
        """A new simulator whose road ``k`` is a copy of the current state of road
        ``roads[k]`` (``roads``: ``[K]`` indices, repeats allowed; same config, device, dtype
        and kernel): the branches of several roads, rolled out in one batch."""
        roads = torch.as_tensor(roads, dtype=torch.long).reshape(-1)
        if roads.numel() < 1 or int(roads.min()) < 0 or int(roads.max()) >= self.n_roads:
            raise ValueError(
                f"roads must be a non-empty list of indices in [0, {self.n_roads - 1}], "
                f"got {roads.tolist()}"
            )
        twin = BatchedFreeway(
            self.config,
            self.merge,
            roads.numel(),
            self.device,
            self.dtype,
            kernel=self.kernel_choice,
        )
        twin.state = self.state[roads.to(self.state.device)].clone()
        return twin

    def rollout_returns(
        self,
        decide: Callable[[torch.Tensor], torch.Tensor],
        *,
        gamma: float = 1.0,
        payoff: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """Step every road to the end of its episode with actions ``decide(observation)``
        (``[B, I, obs_dim]`` -> ``[B, I]``) and return each road's return from now on ``[B]``:
        the CAVs' rewards summed over CAVs and steps, the step ``k`` steps from now weighted by
        ``gamma ** k``; with ``payoff`` (bool or float ``[B, I]``) only the CAVs it selects (or
        weights) count. Default: the undiscounted system return. Roads are not reset."""
        if not (is_real(gamma) and 0.0 <= gamma <= 1.0):
            raise ValueError(f"gamma must be in [0, 1] (a number), got {gamma!r}")
        if payoff is not None and tuple(payoff.shape) != (self.n_roads, self.n_cavs):
            raise ValueError(
                f"payoff must have shape [{self.n_roads}, {self.n_cavs}], got {tuple(payoff.shape)}"
            )
        weights = (
            torch.ones(self.n_roads, self.n_cavs, dtype=torch.float64, device=self.device)
            if payoff is None
            else payoff.to(self.device, torch.float64)
        )
        observation = self.observe()
        total = torch.zeros(self.n_roads, dtype=torch.float64, device=self.device)
        running = (self.state.get("steps") < int(self.config["horizon"])) & self.state[
            "agents"
        ].get("alive").any(1)
        discount = 1.0
        while bool(running.any()):
            result = self.step(decide(observation))
            gained = (result.reward.double() * weights).sum(1)
            total += torch.where(running, discount * gained, 0.0)
            running &= ~(result.truncated | result.terminated)
            observation = result.observation
            discount *= gamma
        return total

    def restore(self, snapshot: TensorDict) -> None:
        """Return every road to ``snapshot`` (from :meth:`snapshot` of a simulator with the
        same config, number of roads, device and dtype); ValueError otherwise."""
        if not isinstance(snapshot, TensorDictBase):
            raise ValueError(
                "snapshot must be a TensorDict taken with snapshot() of an identical simulator, "
                f"got {type(snapshot).__name__}"
            )
        expected = self.snapshot()
        if set(snapshot.keys(True, True)) != set(expected.keys(True, True)) or any(
            snapshot.get(k).shape != expected.get(k).shape
            or snapshot.get(k).dtype != expected.get(k).dtype
            for k in expected.keys(True, True)
        ):
            raise ValueError(
                "snapshot does not fit this simulator (another scenario config, number of "
                "roads, device or dtype); take it with snapshot() of an identical simulator"
            )
        state = snapshot.exclude("rng").clone()
        state.batch_size = [self.n_roads]
        self.state = state.to(self.device)
        self.generator.set_state(snapshot.get("rng").cpu())

    def _decisions(self, action: object) -> torch.Tensor:
        """The CAVs' decisions ``action`` as a long tensor ``[B, I]`` on the simulator's device;
        ValueError (one line) unless it is an integer tensor of that shape with values in
        ``[0, 3]`` (KL, CL, CR, ES)."""
        shape = [self.n_roads, self.n_cavs]
        if not isinstance(action, torch.Tensor) or list(action.shape) != shape:
            got = list(action.shape) if isinstance(action, torch.Tensor) else type(action).__name__
            raise ValueError(f"action must be a tensor of the CAVs' decisions {shape}, got {got}")
        if action.dtype.is_floating_point or action.dtype.is_complex or action.dtype == torch.bool:
            raise ValueError(
                f"action must hold integer decisions in [0, 3] (KL, CL, CR, ES), got dtype "
                f"{action.dtype}"
            )
        action = action.to(self.device).long()
        if bool(((action < KL) | (action > ES)).any()):
            raise ValueError(
                "action must hold integer decisions in [0, 3] (KL, CL, CR, ES), got values in "
                f"[{int(action.min())}, {int(action.max())}]"
            )
        return action

    def predicted_crashes(self, action: torch.Tensor) -> torch.Tensor:
        """The shield's check: which CAVs crash, ``[shield_horizon, B, I]`` (bool, one row per
        policy step), when a copy of every road is stepped with the decisions ``action [B, I]``
        and then ``shield_horizon - 1`` more steps in which every CAV keeps its lane (the backup
        policy). The roads' state is the same afterwards. Stepping is deterministic, so row 0
        is exactly the crashes that ``action`` would cause in the real step."""
        action = self._decisions(action)
        saved = self.state.clone()
        keep = torch.full_like(action, KL)
        rows = [self._advance(action).collided]
        for _ in range(int(self.config["shield_horizon"]) - 1):
            rows.append(self._advance(keep).collided)
        self.state = saved
        return torch.stack(rows)

    def shield(self, action: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """A model-predictive shield (the Shapley paper's "safe learning process"): the CAVs'
        decisions ``[B, I]`` with every lane change or emergency stop that this simulator
        predicts to end in a crash replaced by Keep Lane, and which were replaced ``[B, I]``
        (bool). The roads' state is the same afterwards.

        The prediction is :meth:`predicted_crashes` (a lane change takes several policy steps,
        so a crash it causes may come after the first). A CAV that crashes in the copy and did
        not keep its lane is given Keep Lane. (A crash that Keep Lane does not avoid stays, as
        it would for a human driver.) With ``config["shield_passes"]`` above 1 the corrected
        decisions are checked again, and so on until a pass replaces nothing (at most that many
        passes): a move that was safe beside a neighbour's checked move may not be safe beside
        the Keep Lane that replaced it."""
        action = self._decisions(action)
        passes = int(self.config["shield_passes"])
        safe = action
        for done in range(1, passes + 1):
            unsafe = self.predicted_crashes(safe).any(0) & (safe != KL)
            safe = torch.where(unsafe, KL, safe)
            if done < passes and not bool(unsafe.any()):  # (one pass: no host sync)
                break
        return safe, safe != action

    # --- reset ---------------------------------------------------------------------------------
    def _uniform(self, low_high: tuple[float, float], shape: tuple[int, ...]) -> torch.Tensor:
        low, high = float(low_high[0]), float(low_high[1])
        u = torch.rand(shape, generator=self.generator, device=self.device, dtype=self.dtype)
        return low + (high - low) * u

    def _choose(self, k: int, population: int, count: int) -> torch.Tensor:
        """``[k, count]`` distinct draws from ``0 .. population - 1`` per road."""
        keys = torch.rand(k, population, generator=self.generator, device=self.device)
        return keys.argsort(dim=1)[:, :count]

    def reset(self, mask: torch.Tensor) -> None:
        """Start a new episode on the roads where ``mask [B]`` is True (spawned as the
        highway-env scenario spawns: random slots ``min_spacing`` apart, speeds and target
        speeds from the config's ranges, random human IDM exponents, random CAVs)."""
        idx = mask.nonzero().squeeze(-1)
        k = int(idx.numel())
        if k == 0:
            return
        cfg, geo = self.config, self.geometry
        n, v = self.n_bodies, self.n_vehicles
        spacing = float(cfg["min_spacing"])
        per_lane = int(cfg["spawn_length"] // cfg["min_spacing"])
        n_main = v - self.n_ramp
        slot = self._choose(k, per_lane * geo.lanes, n_main)
        lanes = [slot // per_lane]
        along = [(slot % per_lane).to(self.dtype) * spacing]
        if self.n_ramp:
            ramp_slots = int(cfg["ramp_length"] // cfg["min_spacing"])
            ramp = self._choose(k, ramp_slots, self.n_ramp)
            lanes.append(torch.full_like(ramp, geo.lanes + 1))
            along.append(ramp.to(self.dtype) * spacing)
        lane = torch.cat(lanes, dim=1)
        s = torch.cat(along, dim=1)
        x = geo.start_x[lane] + s * geo.dir_x[lane]
        y = geo.start_y[lane] + s * geo.dir_y[lane]
        cav = torch.zeros(k, v, dtype=torch.bool, device=self.device)
        cav.scatter_(1, self._choose(k, v, self.n_cavs), True)
        on_ramp = lane == geo.lanes + 1
        speed = self._uniform(cfg["initial_speed"], (k, v))
        if self.merge:
            speed = torch.where(on_ramp, self._uniform(cfg["ramp_speed"], (k, v)), speed)
            target_speed = self._uniform(cfg["target_speed"], (k, v))
        else:
            human = self._uniform(cfg["hv_target_speed"], (k, v))
            target_speed = torch.where(cav, float(cfg["cav_target_speed"]), human)
        delta = torch.where(cav, IDMVehicle.DELTA, self._uniform(DELTA_RANGE, (k, v)))
        bodies = {
            "x": x,
            "y": y,
            "heading": geo.heading[lane],
            "speed": speed,
            "target_speed": target_speed.to(self.dtype),
            "delta": delta.to(self.dtype),
            "timer": torch.remainder((x.double() + y.double()) * math.pi, LANE_CHANGE_DELAY),
            "lane": lane,
            "target": lane.clone(),
            "cav": cav,
        }
        if self.merge:  # the obstacle at the end of the acceleration lane, last body
            extra = {
                "x": geo.merge_end,
                "y": geo.lanes * LANE_WIDTH,
                "lane": geo.lanes,
                "target": geo.lanes,
            }
            for key, value in bodies.items():
                fill = extra.get(key, 0)
                column = torch.full((k, 1), fill, dtype=value.dtype, device=self.device)
                bodies[key] = torch.cat([value, column], dim=1)
        new = self.state["bodies"][idx].clone().zero_()
        for key, value in bodies.items():
            new.set(key, value)
        new.set("present", torch.ones(k, n, dtype=torch.bool, device=self.device))
        self.state["bodies"][idx] = new
        # agents in a fixed order along the road: by x, then by lane number
        number = geo.number[lane]
        by_lane = torch.argsort(torch.where(cav, number, number.max() + 1), dim=1, stable=True)
        cav_x = torch.where(cav, x, math.inf).gather(1, by_lane)
        order = by_lane.gather(1, torch.argsort(cav_x, dim=1, stable=True))
        agents = self.state["agents"][idx].clone()
        agents.set("slot", order[:, : self.n_cavs])
        agents.set("alive", torch.ones(k, self.n_cavs, dtype=torch.bool, device=self.device))
        if self.merge:
            agents.set("forcing", torch.zeros(k, self.n_cavs, dtype=torch.bool, device=self.device))
        self.state["agents"][idx] = agents
        counts = BEHAVIOUR_COUNTS if self.merge else ()
        for key in ("steps", "speed_sum", "comfort_sum", "samples", "shielded", *counts):
            self.state.get(key)[idx] = 0

    # --- one policy step -----------------------------------------------------------------------
    def step(self, action: torch.Tensor) -> StepResult:
        """Apply the CAVs' decisions ``[B, I]`` (0..3: KL, CL, CR, ES; ignored for CAVs no
        longer driving), corrected by :meth:`shield` where ``config["shield"]`` is set, and
        advance every road by one policy step."""
        action = self._decisions(action)
        if not self.config["shield"]:
            result = self._advance(action)
            result.shielded = torch.zeros_like(result.acting)
            return result
        safe, shielded = self.shield(action)
        shielded &= self.state["agents"].get("alive")
        self.state.set("shielded", self.state.get("shielded") + shielded.sum(1))
        result = self._advance(safe)
        result.shielded = shielded
        return result

    def _advance(self, action: torch.Tensor) -> StepResult:
        """One policy step of every road with the decisions ``action [B, I]`` (long)."""
        geo, bodies, agents = self.geometry, self.state["bodies"], self.state["agents"]
        slot, acting = agents.get("slot"), agents.get("alive")
        lane, target = bodies.get("lane"), bodies.get("target")
        cav_lane = lane.gather(1, slot)
        if self.merge:  # CL / CR on the slanted ramp lane (without ramp_forcing: the ramp) = KL
            if self.config["ramp_forcing"]:
                refused = geo.segment[cav_lane] != MAINLINE
            else:
                refused = geo.table[cav_lane] == geo.ramp_table
            action = torch.where(refused & ((action == CL) | (action == CR)), KL, action)
        decision = bodies.get("decision").scatter(
            1, slot, torch.where(acting, action, bodies.get("decision").gather(1, slot))
        )
        wanted = geo.number[cav_lane] + torch.where(action == CL, -1, 1)
        settled = cav_lane == target.gather(1, slot)
        change = acting & ((action == CL) | (action == CR)) & settled
        change &= (wanted >= 0) & (wanted < geo.lanes)
        new_target = torch.where(change, wanted, target.gather(1, slot))
        bodies.set("target", target.scatter(1, slot, new_target))
        bodies.set("decision", decision)
        if self.merge:  # what the behaviour counts compare after the step
            before = (lane.clone(), bodies.get("x").gather(1, slot))
            forcing = agents.get("forcing") | (change & (cav_lane == geo.lanes))
        result = self._move(slot, acting)
        if self.merge:
            self._count_behaviour(*before, forcing)
        return result

    def _move(self, slot: torch.Tensor, acting: torch.Tensor) -> StepResult:
        """The simulation steps of a policy step, once the decisions are set (``slot``: the
        CAVs' bodies ``[B, I]``; ``acting``: the CAVs driving at its start ``[B, I]``)."""
        if self.kernel is not None:
            return self._native_step(slot, acting)
        bodies = self.state["bodies"]
        state = dict(bodies.items())
        front, rear = self.physics.neighbours(state)
        zeros = torch.zeros(self.n_roads, self.n_bodies, dtype=self.dtype, device=self.device)
        book = {
            "abs_acc": zeros,
            "lane_change": torch.zeros_like(zeros, dtype=torch.bool),
            "distance": torch.zeros(acting.shape, dtype=self.dtype, device=self.device),
            "crashed_now": torch.zeros_like(acting),
        }
        for _ in range(self.frames):
            state, front, rear, book = self._frame(state, front, rear, book, slot, acting)
        for name, value in state.items():
            bodies.set(name, value)
        return self._finish_step(
            (front, rear),
            book["abs_acc"] / self.frames,
            book["lane_change"],
            book["crashed_now"],
            book["distance"],
        )

    def _count_behaviour(
        self, lane_before: torch.Tensor, x_before: torch.Tensor, forcing: torch.Tensor
    ) -> None:
        """Add one policy step to the behaviour counts of every road (``freeway-merge``; the
        definitions of ``FreewayMergeEnv``'s module docstring), from every body's lane id
        before the step ``[B, N]``, the CAVs' x at its start ``[B, I]`` [m] and which CAVs'
        pending change onto the mainline their own ``CL`` set ``[B, I]``; then keep that mark
        only for CAVs still on the ramp with the change pending."""
        geo, bodies, agents = self.geometry, self.state["bodies"], self.state["agents"]
        slot = agents.get("slot")
        lane = bodies.get("lane")
        main_before = geo.table[lane_before] < geo.lanes  # [B, N]
        main_after = geo.table[lane] < geo.lanes
        cav_lane = lane.gather(1, slot)
        changed = (lane_before.gather(1, slot) != cav_lane) & (
            main_before.gather(1, slot) & main_after.gather(1, slot)
        )
        near = (x_before >= geo.merge_start - NEAR_MERGE) & (x_before <= geo.merge_end)
        merged = ~main_before & main_after  # [B, N]: ramp -> mainline (the obstacle stays)
        forced = torch.zeros_like(merged).scatter(1, slot, forcing) & merged
        events = (changed & near, changed & ~near, forced, merged & ~forced)
        for key, happened in zip(BEHAVIOUR_COUNTS, events, strict=True):
            self.state.set(key, self.state.get(key) + happened.sum(1))
        pending = bodies.get("target").gather(1, slot) != cav_lane
        agents.set("forcing", forcing & ~main_after.gather(1, slot) & pending)

    def _native_constants(self) -> tuple:
        """The fixed arguments of the fused kernel (lanes, bodies, highway-env's constants)."""
        geo, ph = self.geometry, self.physics

        def f64(t: torch.Tensor) -> torch.Tensor:
            return t.detach().to(torch.float64).contiguous()

        lanes_f = [f64(t) for t in (geo.start_x, geo.start_y, geo.dir_x, geo.dir_y,
                                    geo.heading, geo.length)]  # fmt: skip
        lanes_i = [geo.table, geo.segment, geo.side.reshape(-1), geo.next_lane, geo.number]
        constants = [
            COMFORT_ACC_MAX, COMFORT_ACC_MIN, DISTANCE_WANTED, TIME_WANTED, IDMVehicle.DELTA,
            ACC_MAX, ACC_MIN, KP_LATERAL, KP_HEADING, MAX_STEERING_ANGLE, LENGTH, LANE_WIDTH,
            VEHICLE_LENGTH, LANE_CHANGE_DELAY, MIN_ACC_GAIN, MAX_BRAKING_IMPOSED,
            self.speed_limit, self.dt, SQRT_AB,
        ]  # fmt: skip
        ints = [geo.n_tables, geo.ramp_table, int(geo.merge)]
        return (
            lanes_f,
            [t.contiguous() for t in lanes_i],
            geo.forbidden.contiguous(),
            ph.is_obstacle.contiguous(),
            f64(ph.body_length),
            f64(ph.body_width),
            [float(v) for v in constants],
            ints,
        )

    def _native_step(self, slot: torch.Tensor, acting: torch.Tensor) -> StepResult:
        """The policy step through the fused CPU kernel (the torch program's step up to
        rounding, whose differences grow over a trajectory; see :mod:`.native` and
        :data:`KERNELS`)."""
        bodies = self.state["bodies"]
        for key in bodies.keys():  # the kernel writes in place: contiguous storage
            if not bodies.get(key).is_contiguous():
                bodies.set(key, bodies.get(key).contiguous())
        b, n = self.n_roads, self.n_bodies
        abs_acc = torch.zeros(b, n, dtype=self.dtype)
        lane_change = torch.zeros(b, n, dtype=torch.bool)
        distance = torch.zeros(acting.shape, dtype=self.dtype)
        crashed_now = torch.zeros_like(acting)
        front = torch.empty(b, n, 3, dtype=torch.long)
        rear = torch.empty(b, n, 3, dtype=torch.long)
        lanes_f, lanes_i, forbidden, obstacle, length, width, k, ki = self._kernel_args
        cfg = self.config
        settings = [
            float(cfg["comfort_threshold"]), float(cfg["velocity_weight"]),
            float(cfg["collision_reward"]), float(cfg["perception"]),
            self.geometry.merge_start, self.geometry.merge_end,
            float(bool(cfg["team_reward"])), float(self.merge), float(cfg["lane_change_comfort"]),
        ]  # fmt: skip
        alive = acting.clone()
        observation = torch.empty(b, self.n_cavs, self.obs_dim, dtype=torch.float32)
        reward = torch.empty(acting.shape, dtype=self.dtype)
        velocity = torch.empty(b, dtype=self.dtype)
        comfort = torch.empty(b, dtype=self.dtype)
        sums = [self.state.get(key) for key in ("speed_sum", "comfort_sum", "samples")]
        self.kernel.policy_step(
            [bodies.get(key) for key in STATE_FLOAT],
            bodies.get("timer"),
            [bodies.get(key) for key in ("lane", "target", "decision")],
            [bodies.get(key) for key in ("crashed", "present", "has_impact", "cav")],
            lanes_f, lanes_i, forbidden, obstacle, length, width, k, ki,
            slot.contiguous(), acting.contiguous(), abs_acc, lane_change, distance, crashed_now,
            front, rear, self.frames,
            settings, alive, observation, reward, velocity, comfort, *sums,
        )  # fmt: skip
        return self._end_step(
            observation, reward, acting, alive, crashed_now, distance, velocity, comfort
        )

    def _end_step(
        self,
        observation: torch.Tensor,
        reward: torch.Tensor,
        acting: torch.Tensor,
        alive: torch.Tensor,
        crashed_now: torch.Tensor,
        distance: torch.Tensor,
        velocity: torch.Tensor,
        comfort: torch.Tensor,
    ) -> StepResult:
        """Count the step, record the CAVs still driving and say which roads are done."""
        self.state["agents"].set("alive", alive)
        steps = self.state.get("steps") + 1
        self.state.set("steps", steps)
        return StepResult(
            observation=observation,
            reward=reward,
            acting=acting,
            alive=alive,
            collided=crashed_now,
            distance=distance,
            traffic_velocity=velocity,
            traffic_comfort=comfort,
            truncated=steps >= int(self.config["horizon"]),
            terminated=~alive.any(1),
        )

    def _frame(
        self,
        b: Bodies,
        front: torch.Tensor,
        rear: torch.Tensor,
        book: dict[str, torch.Tensor],
        slot: torch.Tensor,
        acting: torch.Tensor,
    ) -> tuple[Bodies, torch.Tensor, torch.Tensor, dict[str, torch.Tensor]]:
        """One simulation step of every road and its bookkeeping (``FreewayEnv._on_substep``:
        |acceleration| and lane changes of every vehicle, distance and crash of every CAV)."""
        b, front, rear = self.physics.substep(b, front, rear)
        driving = acting & ~book["crashed_now"]
        book = {
            "abs_acc": book["abs_acc"] + b["acc"].abs(),
            "lane_change": book["lane_change"] | (b["lane"] != b["target"]),
            "distance": book["distance"]
            + torch.where(driving, b["speed"].gather(1, slot) * self.dt, 0.0),
            "crashed_now": book["crashed_now"] | (driving & b["crashed"].gather(1, slot)),
        }
        return b, front, rear, book

    def _finish_step(
        self,
        neighbours: tuple[torch.Tensor, torch.Tensor],
        abs_acc: torch.Tensor,
        lane_change: torch.Tensor,
        crashed_now: torch.Tensor,
        distance: torch.Tensor,
    ) -> StepResult:
        """Comfort, observation, reward and episode bookkeeping at the end of a policy step
        (``FreewayEnv._simulate``, ``observe_agents``, ``agent_rewards`` and
        ``MultiAgentTrafficEnv.step``)."""
        cfg, bodies, agents = self.config, self.state["bodies"], self.state["agents"]
        slot, acting = agents.get("slot"), agents.get("alive")
        present = bodies.get("present") & ~self.is_obstacle
        comfort = torch.where(abs_acc < float(cfg["comfort_threshold"]), 3.0, 2.0)
        changing = float(cfg["lane_change_comfort"])
        comfort = torch.where(lane_change, changing, comfort)
        decision = bodies.get("decision")
        cav = bodies.get("cav")
        comfort = torch.where(cav & ((decision == CL) | (decision == CR)), changing, comfort)
        comfort = torch.where(cav & (decision == ES), 0.0, comfort).to(self.dtype)
        speed = bodies.get("speed")
        count = present.sum(1).clamp(min=1).to(self.dtype)
        velocity = torch.where(present, speed, 0.0).sum(1) / count
        mean_comfort = torch.where(present, comfort, 0.0).sum(1) / count
        self.state.set("speed_sum", self.state.get("speed_sum") + velocity.double() * count)
        self.state.set("comfort_sum", self.state.get("comfort_sum") + mean_comfort * count)
        self.state.set("samples", self.state.get("samples") + present.sum(1))
        observation = self._observe(neighbours, acting)
        reward = float(cfg["velocity_weight"]) * speed.gather(1, slot) + comfort.gather(1, slot)
        reward = torch.where(crashed_now, float(cfg["collision_reward"]), reward)
        if cfg["team_reward"]:
            paid = acting.to(self.dtype)
            mean = (reward * paid).sum(1, keepdim=True) / paid.sum(1, keepdim=True).clamp(min=1)
            reward = mean.expand_as(reward)
        reward = torch.where(acting, reward, 0.0)
        bodies.set("present", bodies.get("present") & ~bodies.get("crashed"))
        return self._end_step(
            observation, reward, acting, acting & ~crashed_now, crashed_now, distance,
            velocity, mean_comfort,
        )  # fmt: skip

    # --- observation and metrics ---------------------------------------------------------------
    def observe(self, acting: torch.Tensor | None = None) -> torch.Tensor:
        """The CAVs' observation ``[B, I, obs_dim]`` now (zero rows where ``acting`` is False;
        default: the CAVs still driving)."""
        acting = self.state["agents"].get("alive") if acting is None else acting
        return self._observe(self.physics.neighbours(dict(self.state["bodies"].items())), acting)

    def _observe(
        self, neighbours: tuple[torch.Tensor, torch.Tensor], acting: torch.Tensor
    ) -> torch.Tensor:
        """``FreewayEnv.observe_agents`` (and ``FreewayMergeEnv``'s two merge distances)."""
        geo, bodies = self.geometry, self.state["bodies"]
        slot = self.state["agents"].get("slot")
        perception = float(self.config["perception"])
        front, rear = neighbours
        index = slot.unsqueeze(-1).expand(*slot.shape, 3)
        front, rear = front.gather(1, index), rear.gather(1, index)  # [B, I, 3]
        lane = bodies.get("lane").gather(1, slot)
        x, y = bodies.get("x").gather(1, slot), bodies.get("y").gather(1, slot)
        speed = bodies.get("speed").gather(1, slot)
        _, lateral = geo.local_coordinates(x, y, lane)
        own = torch.stack(
            [speed, geo.number[lane].to(self.dtype), lateral, bodies.get("acc").gather(1, slot)],
            dim=-1,
        )
        table = geo.table[lane].unsqueeze(-1) + torch.tensor([-1, 0, 1], device=self.device)
        lane_ok = (table >= 0) & (table < geo.n_tables)
        blocks = []
        for other, sign in ((front, 1.0), (rear, -1.0)):
            exists = lane_ok & (other >= 0) & ~self.is_obstacle[other.clamp(min=0)]
            dx = self.physics.gather(bodies.get("x"), other) - x.unsqueeze(-1)
            dv = self.physics.gather(bodies.get("speed"), other) - speed.unsqueeze(-1)
            seen = exists & (dx.abs() <= perception)
            blocks.append(
                torch.stack(
                    [
                        seen.to(self.dtype),
                        torch.where(seen, dx, sign * perception),
                        torch.where(seen, dv, 0.0),
                    ],
                    dim=-1,
                )
            )
        neighbours = torch.stack(blocks, dim=-2).flatten(-3)  # [B, I, 3 lanes x 2 x 3]
        parts = [own, neighbours]
        if self.merge:
            merge = torch.stack([geo.merge_start - x, geo.merge_end - x], dim=-1)
            parts.append(merge.clamp(-perception, perception))
        obs = torch.cat(parts, dim=-1).to(torch.float32)
        return torch.where(acting.unsqueeze(-1), obs, 0.0)

    def episode_metrics(self) -> dict[str, torch.Tensor]:
        """The episode so far of every road, as ``FreewayEnv.episode_metrics`` reports it:
        ``average_velocity`` [m/s] and ``average_comfort`` over all vehicles and steps,
        ``collisions`` (CAVs crashed), with the ramp ``ramp_stuck`` (vehicles still on it) and
        the behaviour counts (``FreewayMergeEnv``'s ``BEHAVIOUR_COUNTS``: lane changes near the
        merge and elsewhere, forced and MOBIL merges), with the shield ``shielded`` (decisions
        it replaced); each ``[B]``."""
        samples = self.state.get("samples").clamp(min=1)
        metrics = {
            "average_velocity": self.state.get("speed_sum") / samples,
            "average_comfort": self.state.get("comfort_sum") / samples,
            "collisions": (~self.state["agents"].get("alive")).sum(1).double(),
        }
        if self.config["shield"]:
            metrics["shielded"] = self.state.get("shielded").double()
        if self.merge:
            bodies = self.state["bodies"]
            on_ramp = self.geometry.table[bodies.get("lane")] == self.geometry.ramp_table
            stuck = bodies.get("present") & ~self.is_obstacle & on_ramp
            metrics["ramp_stuck"] = stuck.sum(1).double()
            for key in BEHAVIOUR_COUNTS:
                metrics[key] = self.state.get(key).double()
        return metrics

    def positions(self) -> torch.Tensor:
        """The CAVs' positions ``[B, I, 2]`` [m] (a crashed CAV's where it crashed)."""
        slot = self.state["agents"].get("slot")
        bodies = self.state["bodies"]
        return torch.stack(
            [bodies.get("x").gather(1, slot), bodies.get("y").gather(1, slot)], dim=-1
        )
