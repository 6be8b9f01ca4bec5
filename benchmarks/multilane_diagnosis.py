"""Why CAVs crash on the two-lane figure-eight: policies scored and every crash classified.

Drives ``figure-eight-multilane`` (22 CAVs, 400 steps, the recipe's scenario defaults) with
policies that separate the causes, one change at a time, on the same seeds:

- ``scripted``: :class:`~mapets_rl.envs.ScriptedCAVPolicy` (IDM, first come first served at
  the crossing, never changes lanes): the scenario is drivable;
- ``random`` / ``random-keep-lane``: uniform target speeds with uniform lane-change flags /
  with the flag held at 0 (what the first MA-PETS episode drives, and its share of lane changes);
- ``oracle`` / ``oracle-keep-lane``: the MA-PETS planner (cpu-preset CEM, the recipe's reward
  and termination with the lane-aware test) planning through
  :class:`~mapets_rl.envs.figure_eight_kinematics.FigureEightKinematicModel` (exact own speed,
  constant-speed neighbours) instead of a learned ensemble: a crash here is the planner's or
  the unforeseeable traffic's, not the model's. Its margins are the scenario's planner-reward
  section (:class:`~mapets_rl.envs.FigureEightPlannerReward`, the ones MA-PETS plans with)
  with ``--reward key=value`` changes: ``--reward lane_change_gap=0 lane_change_time=0``
  switches the lane-aware termination off, ``--reward headway=0 lane_change_time=0`` gives the
  fixed margins of earlier versions;
- ``oracle-shared`` / ``learned-shared``: the same planners with plan sharing
  (:class:`~mapets_rl.planning.shared_plans.PlanSharingPlanner`, MA-PETS ``comm.share_plans``):
  each CAV plans with the broadcast plans of the CAVs it observes within ``--comm-range``
  metres as their future speeds;
- ``oracle-exact``: the oracle told its observed CAVs' *actual* future speeds, replayed from a
  rollout of the same seed (``benchmarks/exact_futures.py``): the upper bound of plan sharing.
  The CAVs react to what they are told, so it iterates: rollout 0 is ``oracle-shared``, rollout
  ``k = 1..--replay-iterations`` replays every CAV's speeds of rollout ``k - 1``; the row is the
  last rollout's, with every rollout's safety, agility and how exact its known speeds were
  (``rollouts``);
- ``oracle-exact-windowed``: the same iteration window by window (``--replay-window`` steps):
  each window restarts ``--replay-iterations`` times from the state the previous windows
  committed (the env re-driven with the committed actions, the planner's warm start and
  generator restored), replaying the latest speeds of every CAV, and commits the last
  iteration's first window of steps; the row is the committed episode's. A window's replays
  only have to agree over ``window + horizon`` steps, not the whole episode;
- ``learned``: the planner of a trained MA-PETS run (``--run RUN_DIR``, its last checkpoint:
  the learned ensembles, the recipe's reward, termination and CEM) on the same seeds: what the
  learned model adds to the oracle's crashes, class by class.

Every CAV crash is classified from the simulator state of the step before it: ``crossing``
(the two vehicles on different branches, both near the crossing point), ``lane change (CAV)``
/ ``lane change (other)`` (one of the two was between lanes), ``into leader`` (the partner was
ahead in the CAV's lane), ``rear-ended`` (it was behind). The partner is the nearest vehicle
that crashed in the same step.

Usage::

    python benchmarks/multilane_diagnosis.py --seeds 0 1 2 --policies scripted random oracle
    python benchmarks/multilane_diagnosis.py --policies learned --run RUN_DIR
"""

from __future__ import annotations

import argparse
import functools
import json
import time
from collections import Counter
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import torch
from exact_futures import ExactFuturePlanner, broadcast_schedule, schedule_exactness
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase

from mapets_rl.comm import CommunicationRange
from mapets_rl.config import ConfigError, parse_override
from mapets_rl.envs import ScriptedCAVPolicy, make_env, traffic_env
from mapets_rl.envs.figure_eight import FigureEightPlannerReward, neighbour_speed_columns
from mapets_rl.envs.figure_eight_kinematics import FigureEightKinematicModel
from mapets_rl.machine import machine_line
from mapets_rl.planning import CPU_PRESET, TrajectorySamplingCEM
from mapets_rl.planning.shared_plans import PlanSharingPlanner

SCENARIO = "figure-eight-multilane"
POLICIES = (
    "scripted",
    "random",
    "random-keep-lane",
    "oracle",
    "oracle-keep-lane",
    "oracle-shared",
    "oracle-exact",
    "oracle-exact-windowed",
    "learned",
    "learned-shared",
)
CLASSES = ("crossing", "lane change (CAV)", "lane change (other)", "into leader", "rear-ended")
NEAR_CROSSING = 10.0
"""A vehicle within this many metres of a crossing point [m] is at the crossing."""
BETWEEN_LANES = 0.6
"""A vehicle more than this far from its lane's centre [m], or steering to another lane, is
changing lanes."""


class RandomPolicy(TensorDictModuleBase):
    """Uniform target speeds, uniform lane-change flags (``keep_lane``: flag 0)."""

    in_keys = [("agents", "observation")]
    out_keys = [("agents", "action")]

    def __init__(self, env, keep_lane: bool, seed: int) -> None:
        super().__init__()
        self.env, self.keep_lane = env, keep_lane
        self.generator = torch.Generator().manual_seed(seed)

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        spec = self.env.full_action_spec["agents", "action"]
        low, high = spec.space.low, spec.space.high
        action = low + (high - low) * torch.rand(low.shape, generator=self.generator)
        if self.keep_lane:
            action[..., 1] = 0.0
        return tensordict.set(("agents", "action"), action)


class KeepLane(TensorDictModuleBase):
    """Wraps a policy and sets its lane-change flag to 0."""

    def __init__(self, policy: TensorDictModuleBase) -> None:
        super().__init__()
        self.policy = policy
        self.in_keys, self.out_keys = policy.in_keys, policy.out_keys

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        tensordict = self.policy(tensordict)
        tensordict.get(("agents", "action"))[..., 1] = 0.0
        return tensordict


def oracle_planner(
    env, reward: FigureEightPlannerReward, seed: int, **cem: bool
) -> TrajectorySamplingCEM:
    """The cpu-preset CEM over the kinematic model (one particle: the model is deterministic),
    scoring with ``reward``'s reward and collision test; ``cem``: PlannerConfig fields over the
    preset's (``anchor_candidates``, ``keep_best``, ``population``, ``noise_beta``, ...)."""
    spec = env.full_action_spec["agents", "action"]
    n_agents, action_dim = spec.shape
    obs_dim = env.observation_spec["agents", "observation"].shape[-1]
    return TrajectorySamplingCEM(
        FigureEightKinematicModel(n_agents, obs_dim, action_dim),
        reward.reward,
        spec.space.low,
        spec.space.high,
        CPU_PRESET.planner,
        termination_fn=reward.collision,
        seed=seed,
        particles=1,
        propagation="expectation",
        **cem,
    )


@functools.cache
def learned_planner(run_dir: str, overrides: tuple[str, ...] = ()) -> TensorDictModuleBase:
    """The planner of MA-PETS run ``run_dir`` at its last checkpoint (loaded once), with
    ``overrides`` of its config (e.g. ``planner_reward.lane_change_time=1``)."""
    from mapets_rl.recipes.mapets import MAPETS

    exp = MAPETS.from_run_dir(run_dir, overrides=list(overrides))
    exp.close()  # only its planner is used: release the run directory
    return exp.planner


def make_policy(
    name: str,
    env,
    seed: int,
    reward: FigureEightPlannerReward,
    run: str | None = None,
    run_overrides: tuple[str, ...] = (),
    *,
    record: torch.Tensor | None = None,
    **cem: Any,
) -> TensorDictModuleBase:
    """``record``: oracle-exact, the rollout whose speeds it replays ([T + 1, I])."""
    obs_dim = env.observation_spec["agents", "observation"].shape[-1]
    if name.startswith("learned"):
        planner = learned_planner(run, run_overrides)
        planner.generator.manual_seed(seed)
        if name.endswith("shared"):
            return PlanSharingPlanner(planner, neighbour_speed_columns(obs_dim))
        return planner
    if name == "scripted":
        return ScriptedCAVPolicy(env)
    if name.startswith("random"):
        return RandomPolicy(env, keep_lane=name.endswith("keep-lane"), seed=seed)
    planner = oracle_planner(env, reward, seed, **cem)
    if name.startswith("oracle-exact"):
        return ExactFuturePlanner(planner, neighbour_speed_columns(obs_dim), record)
    if name.endswith("shared"):
        return PlanSharingPlanner(planner, neighbour_speed_columns(obs_dim))
    return KeepLane(planner) if name.endswith("keep-lane") else planner


def snapshot(raw) -> dict[int, dict]:
    """Per vehicle (by id): route coordinate, lane, lateral offset, lane-changing, CAV."""
    cavs = {id(c) for c in raw.cavs}
    out = {}
    for v in raw.road.vehicles:
        _s, lateral = v.lane.local_coordinates(v.position)
        out[id(v)] = {
            "vehicle": v,
            "coord": raw.road.route_coordinate(v),
            "lane": v.lane_index[2],
            "changing": v.lane_index != v.target_lane_index or abs(lateral) > BETWEEN_LANES,
            "cav": id(v) in cavs,
        }
    return out


def classify(raw, before: dict[int, dict], cav) -> tuple[str, bool]:
    """Class of ``cav``'s crash and whether the partner was a CAV."""
    crashed = [s for k, s in before.items() if k != id(cav) and s["vehicle"].crashed]
    me = before[id(cav)]
    if not crashed:
        return "into leader", False
    partner = min(crashed, key=lambda s: np.linalg.norm(s["vehicle"].position - cav.position))
    period, crossings = raw.road.period, raw.geometry.crossing_coordinates

    def branch_at_crossing(coord: float) -> int | None:
        r = np.abs((coord - crossings + period / 2) % period - period / 2)
        return int(np.argmin(r)) if r.min() < NEAR_CROSSING else None

    mine, theirs = branch_at_crossing(me["coord"]), branch_at_crossing(partner["coord"])
    if mine is not None and theirs is not None and mine != theirs:
        return "crossing", partner["cav"]
    if me["changing"]:
        return "lane change (CAV)", partner["cav"]
    if partner["changing"] or partner["lane"] != me["lane"]:
        return "lane change (other)", partner["cav"]
    ahead = (partner["coord"] - me["coord"] + period / 2) % period - period / 2
    return ("into leader" if ahead > 0 else "rear-ended"), partner["cav"]


def run_episode(
    name: str,
    seed: int,
    horizon: int,
    reward: FigureEightPlannerReward,
    scenario: str = SCENARIO,
    run: str | None = None,
    run_overrides: tuple[str, ...] = (),
    comm_range: float = 100.0,
    env_config: dict[str, Any] | None = None,
    replay_iterations: int = 3,
    replay_window: int = 50,
    **cem: Any,
) -> dict:
    """One episode of policy ``name`` (``oracle-exact``: its ``replay_iterations + 1``
    rollouts, the row of the last one; ``oracle-exact-windowed``: its committed episode; see
    the module docstring)."""
    args = (seed, horizon, reward, scenario, run, run_overrides, comm_range, env_config)
    if name == "oracle-exact-windowed":
        return run_windowed(*args, replay_iterations, replay_window, **cem)
    if name != "oracle-exact":
        return drive(name, *args, **cem)[0]
    start = time.perf_counter()
    row, trace = drive("oracle-shared", *args, **cem)
    rollouts = [rollout_summary(row, trace)]
    fixed_point = None
    for k in range(1, replay_iterations + 1):
        if fixed_point is None:  # else the replay of an unchanged rollout: the same rollout
            previous = trace["speeds"]
            row, trace = drive(name, *args, record=previous, **cem)
            if torch.equal(previous.nan_to_num(-1.0), trace["speeds"].nan_to_num(-1.0)):
                fixed_point = k
        rollouts.append(rollout_summary(row, trace))
    row.update(
        policy=name,
        rollouts=rollouts,
        replay_iterations=replay_iterations,
        fixed_point=fixed_point,
        wall_time=time.perf_counter() - start,
    )
    return row


def run_windowed(
    seed: int,
    horizon: int,
    reward: FigureEightPlannerReward,
    scenario: str,
    run: str | None,
    run_overrides: tuple[str, ...],
    comm_range: float,
    env_config: dict[str, Any] | None,
    iterations: int,
    window: int,
    **cem: Any,
) -> dict:
    """``oracle-exact-windowed`` (see the module docstring): the row of the committed episode,
    with rollout 0's (oracle-shared) and the committed one's summaries as ``rollouts``."""
    start = time.perf_counter()
    args = (seed, horizon, reward, scenario, run, run_overrides, comm_range, env_config)
    row, trace = drive("oracle-shared", *args, **cem)
    rollouts = [rollout_summary(row, trace)]
    guess = trace["speeds"].clone()  # [T + 1, I] the latest speeds of every CAV
    obs_key, action_key = ("agents", "observation"), ("agents", "action")

    def fresh_env():
        return make_env(scenario, seed=seed, horizon=horizon, **(env_config or {}))

    env = fresh_env()
    policy = make_policy("oracle-exact", env, seed, reward, record=guess, **cem)
    env.close()
    policy.reset()
    lookahead = policy.planner.config.horizon
    committed_state, actions, schedules = policy.state(), [], []
    for begin in range(0, horizon, window):
        end = min(begin + window, horizon)
        for k in range(iterations):
            env = fresh_env()
            td = env.reset()
            for action in actions:  # back to the committed state at ``begin``
                td = env.step(td.set(action_key, action))["next"]
            policy.load_state(committed_state)
            policy.record = guess
            tried, known, speeds, n, done = [], [], [], begin, False
            while n < min(end + lookahead, horizon) and not done:
                if n == end and k == iterations - 1:
                    next_state = policy.state()
                td = policy(td)
                if policy.last_schedule is not None:
                    known.append((n, *policy.last_schedule))
                tried.append(td[action_key].clone())
                td = env.step(td)
                n += 1
                driving = torch.as_tensor(traffic_env(env).alive)  # (mask: False at the end)
                speeds.append(torch.where(driving, td["next"][obs_key][:, 0], float("nan")))
                done = bool(td["next", "done"].all())
                td = td["next"]
            env.close()
            guess = guess.clone()
            guess[begin + 1 : n + 1] = torch.stack(speeds)
        actions += tried[: end - begin]
        schedules += [entry for entry in known if entry[0] < end]
        if end < horizon:
            committed_state = next_state
        if done and n <= end:  # every CAV stopped within the window: the episode ended
            break
    row, trace = drive("oracle-exact-windowed", *args, actions=actions, **cem)
    if not torch.equal(
        trace["speeds"].nan_to_num(-1.0), guess[: len(trace["speeds"])].nan_to_num(-1.0)
    ):
        raise RuntimeError("the committed actions did not drive the committed episode again")
    trace["schedules"] = schedules
    row.update(
        plans_used=sum(int((senders >= 0).sum()) for *_, senders in schedules) / len(actions)
    )
    rollouts.append(rollout_summary(row, trace))
    row.update(
        rollouts=rollouts,
        replay_iterations=iterations,
        replay_window=window,
        wall_time=time.perf_counter() - start,
    )
    return row


class ActionReplay(TensorDictModuleBase):
    """Plays recorded actions ``[I, A]`` in order (re-drives a committed episode)."""

    in_keys: list = []
    out_keys = [("agents", "action")]

    def __init__(self, actions: list[torch.Tensor]) -> None:
        super().__init__()
        self.actions = actions
        self.step = 0

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        action = self.actions[self.step]
        self.step += 1
        return tensordict.set(("agents", "action"), action)


def rollout_summary(row: dict, trace: dict) -> dict:
    """A rollout's safety, agility and crashes, and how exact its known speeds were."""
    summary = {k: v for k, v in row.items() if k != "seed"}
    columns = neighbour_speed_columns(trace["obs_dim"])
    summary.update(schedule_exactness(trace["schedules"], trace["speeds"], columns))
    return summary


def drive(
    name: str,
    seed: int,
    horizon: int,
    reward: FigureEightPlannerReward,
    scenario: str = SCENARIO,
    run: str | None = None,
    run_overrides: tuple[str, ...] = (),
    comm_range: float = 100.0,
    env_config: dict[str, Any] | None = None,
    *,
    record: torch.Tensor | None = None,
    actions: list[torch.Tensor] | None = None,
    wrap: Callable[[TensorDictModuleBase], TensorDictModuleBase] | None = None,
    **cem: Any,
) -> tuple[dict, dict]:
    """One episode: its row, and its trace: ``speeds`` ``[T + 1, I]`` (each CAV's observed own
    speed after each step, NaN once it no longer drives), ``schedules`` (per decision with
    known neighbour speeds: ``(step, schedule [I, H, S], senders [I, K])``) and ``obs_dim``.
    ``actions``: play these instead of deciding (:class:`ActionReplay`); ``wrap``: drive
    ``wrap(policy)`` instead (e.g. a rule of ``benchmarks/planner_rules.py``)."""
    env = make_env(scenario, seed=seed, horizon=horizon, **(env_config or {}))
    if name.endswith("shared"):  # the step's communication graph, for the broadcasts
        env = env.append_transform(CommunicationRange(comm_range))
    raw = traffic_env(env)
    if actions is not None:
        policy = ActionReplay(actions)
    else:
        policy = make_policy(name, env, seed, reward, run, run_overrides, record=record, **cem)
    if wrap is not None:
        policy = wrap(policy)
    if hasattr(policy, "reset"):
        policy.reset()
    td = env.reset()
    obs_key = ("agents", "observation")
    speeds = [td[obs_key][:, 0].clone()]
    schedules = []
    classes: Counter = Counter()
    with_cav = 0
    start = time.perf_counter()
    steps = 0
    human_distance = 0.0  # summed over the steps: the human drivers' mean m/step
    with torch.no_grad():
        while True:
            before = snapshot(raw)
            alive = raw.alive.copy()
            known = None
            if isinstance(policy, PlanSharingPlanner):  # what it is about to plan with
                known = broadcast_schedule(policy, td)
            td = policy(td)
            if isinstance(policy, ExactFuturePlanner):
                known = policy.last_schedule
            if known is not None:
                schedules.append((steps, *known))
            td = env.step(td)
            steps += 1
            driving = torch.as_tensor(raw.alive)
            speeds.append(torch.where(driving, td["next"][obs_key][:, 0], float("nan")))
            humans = [s["vehicle"].speed for s in before.values() if not s["cav"]]
            human_distance += float(np.mean(humans)) * raw.dt if humans else 0.0
            for i in np.flatnonzero(alive & ~raw.alive):
                label, partner_cav = classify(raw, before, raw.cavs[i])
                classes[label] += 1
                with_cav += partner_cav
            if bool(td["next", "done"].all()):
                break
            td = td["next"]
    metrics = raw.episode_metrics()
    messages = getattr(policy, "broadcasts", 0) / steps
    row = {
        "policy": name,
        "seed": seed,
        "safety": metrics["safety"],
        "agility": metrics["agility"],
        "crashes": metrics["collisions"],
        "partner_cav": with_cav,
        "classes": dict(classes),
        "step_time": (time.perf_counter() - start) / steps,
        "human_agility": human_distance / steps,
        "plan_messages": messages,
        "plans_used": getattr(policy, "plans_used", 0) / steps,
    }
    trace = {
        "speeds": torch.stack(speeds),
        "schedules": schedules,
        "obs_dim": env.observation_spec[obs_key].shape[-1],
    }
    return row, trace


def main(argv: list[str] | None = None) -> list[dict]:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--policies", nargs="+", choices=POLICIES, default=list(POLICIES))
    parser.add_argument(
        "--scenario",
        default=SCENARIO,
        choices=("figure-eight", SCENARIO),
        help="figure-eight: the one-lane reference (no keep-lane variants: one action)",
    )
    parser.add_argument("--horizon", type=int, default=400, help="steps per episode")
    parser.add_argument(
        "--reward",
        nargs="*",
        default=[],
        metavar="key=value",
        help="oracle: FigureEightPlannerReward fields over its defaults (the margins MA-PETS "
        "plans with), e.g. headway=0 lane_change_time=0 lane_change_gap=8",
    )
    parser.add_argument(
        "--anchor-candidates", action="store_true", help="oracle: iCEM's fallback candidates"
    )
    parser.add_argument("--keep-best", action="store_true", help="oracle: best sequence")
    parser.add_argument("--run", default=None, help="learned: a MA-PETS run directory")
    parser.add_argument(
        "--set",
        nargs="*",
        default=[],
        metavar="key=value",
        help="learned: overrides of the run's config, e.g. planner_reward.lane_change_time=1",
    )
    parser.add_argument(
        "--planner",
        nargs="*",
        default=[],
        metavar="key=value",
        help="oracle: PlannerConfig fields over the cpu preset's, e.g. population=16 "
        "noise_beta=2 keep_elites=0.3 (model rows per decision scale with population)",
    )
    parser.add_argument(
        "--comm-range", type=float, default=100.0,
        help="*-shared: the range d [m] within which CAVs hear each other's plans",
    )  # fmt: skip
    parser.add_argument(
        "--replay-iterations", type=int, default=3,
        help="oracle-exact: rollouts replaying the previous rollout's speeds (after rollout 0, "
        "oracle-shared)",
    )  # fmt: skip
    parser.add_argument(
        "--replay-window", type=int, default=50,
        help="oracle-exact-windowed: steps committed per window",
    )  # fmt: skip
    parser.add_argument("--out", type=Path, default=None, help="write the rows as JSON here")
    args = parser.parse_args(argv)
    if not args.comm_range >= 0:
        parser.error(f"--comm-range must be >= 0 metres, got {args.comm_range}")
    if args.replay_iterations < 1:
        parser.error(f"--replay-iterations must be >= 1, got {args.replay_iterations}")
    if args.replay_window < 1:
        parser.error(f"--replay-window must be >= 1, got {args.replay_window}")
    try:
        planner_settings = dict(map(parse_override, args.planner))
        CPU_PRESET.planner.replace(**planner_settings)
    except (ConfigError, TypeError) as err:
        parser.error(f"--planner: {err}")
    try:
        reward = FigureEightPlannerReward(**dict(map(parse_override, args.reward)))
    except ConfigError as err:
        parser.error(f"--reward: {err}")
    if any(p.startswith("learned") for p in args.policies) and (
        args.run is None or not (Path(args.run) / "config.yaml").is_file()
    ):
        parser.error(f"--policies learned needs --run RUN_DIR of a MA-PETS run, got {args.run}")
    torch.set_num_threads(1)
    print(f"# {machine_line()}")
    rows = []
    for name in args.policies:
        for seed in args.seeds:
            row = run_episode(
                name,
                seed,
                args.horizon,
                reward,
                args.scenario,
                args.run,
                tuple(args.set),
                args.comm_range,
                replay_iterations=args.replay_iterations,
                replay_window=args.replay_window,
                anchor_candidates=args.anchor_candidates,
                keep_best=args.keep_best,
                **planner_settings,
            )
            rows.append(row)
            print(json.dumps(row), flush=True)
    header = " | ".join(CLASSES)
    print(
        f"\n| policy | seeds | safety | agility [m/step] | crashes / 22 | {header} | "
        "plans sent / step |"
    )
    print("|---|---|---|---|---|" + "---|" * (len(CLASSES) + 1))
    for name in args.policies:
        group = [r for r in rows if r["policy"] == name]
        total: Counter = Counter()
        for r in group:
            total.update(r["classes"])
        n = len(group)
        cells = " | ".join(f"{total[c] / n:.1f}" for c in CLASSES)
        print(
            f"| {name} | {n} | {np.mean([r['safety'] for r in group]):.3f} | "
            f"{np.mean([r['agility'] for r in group]):.3f} | "
            f"{np.mean([r['crashes'] for r in group]):.1f} | {cells} | "
            f"{np.mean([r['plan_messages'] for r in group]):.1f} |"
        )
    if args.out is not None:
        tmp = args.out.with_suffix(".tmp")
        tmp.write_text(json.dumps(rows, indent=1))
        tmp.replace(args.out)
    return rows


if __name__ == "__main__":
    from mapets_rl import quiet_dependencies

    quiet_dependencies()
    main()
