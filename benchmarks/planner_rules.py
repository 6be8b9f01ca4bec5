"""Coordination rules on top of MA-PETS' planner on the two-lane figure-eight (issue 33).

Below the 0.5 s headway margin most CAV crashes of the two-lane figure-eight are classified as
lane changes (``benchmarks/multilane_diagnosis.py``), and at the crossing CAVs that plan against
each other's plans can both commit to going first. Each rule here is one candidate cure, put
on top of the oracle planner (exact own motion; ``oracle-shared``: with plan sharing) one at a
time and driven over the same seeds as the frontier (``benchmarks/safety_agility_frontier.py``):

- ``none``: the planner as it is (the reference row of the same run);
- ``occupy``: *a vehicle between lanes occupies both*. A CAV that is between lanes (its lane
  position more than ``SETTLED_LANE_POSITION`` lane widths from a lane centre), or whose
  other-lane leader is a CAV linked to it that is between lanes (the lateral position is part
  of its broadcast), plans with the nearer of its own-lane and other-lane leaders as its
  leader (gap, speed and, for plan sharing, which CAV it is);
- ``crossing-order``: *first come, first served among linked CAVs*. A CAV whose conflicting
  vehicle is a CAV linked to it and farther from the crossing point (ties: the lower agent
  index goes first) plans as if the crossing were free, provided that CAV can still stop
  before the conflict zone (``crossing_gap``) braking at ``ACC_MIN``; the other one still sees
  it and yields;
- ``brake``: *inside the margin, brake*. A CAV whose gap ahead already fails the planner's
  gap test (below ``collision_gap``, or below ``collision_gap + headway * v`` while it is
  faster than its leader: ``FigureEightPlannerReward.lost``) takes target speed 0 and keeps its
  lane, whatever the planner chose (MA-PETS' ``planner_reward.brake_when_lost``).
  There every plan is predicted to crash at its first step, so the planner's choice is
  arbitrary (traces: from there it accelerates into its leader and starts lane changes into
  gaps of 0-2 m);
- ``recover``: the same CAVs plan with their gap ahead raised by what puts it just outside
  the test for every action at the first step (``RECOVER_SLACK`` beyond the margin and the
  step's closing): the planner chooses again, among plans that do not close the gap further
  than the first step must, instead of braking to a stop.

Rows are appended to ``OUT/rows.jsonl`` as episodes finish and a stopped run resumes; the
table (means with 95% percentile-bootstrap intervals over seeds, crash classes per episode)
is printed and written to ``OUT/rules.md``.

    OMP_NUM_THREADS=1 PYTHONPATH=.:benchmarks python benchmarks/planner_rules.py --out OUT \\
        [--policy oracle-shared] [--rules none occupy crossing-order brake] \\
        [--headway 0 0.25 0.5] [--seeds 0 1 2 3 4 5] [--env n_hvs=0] [--reward key=value]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch
from multilane_diagnosis import CLASSES, SCENARIO, drive
from safety_agility_frontier import load_rows
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase

from mapets_rl.comm.plans import linked_senders
from mapets_rl.config import ConfigError, parse_override
from mapets_rl.envs import make_env
from mapets_rl.envs.figure_eight import (
    GAP_RANGE,
    SETTLED_LANE_POSITION,
    TWO_LANE_OBS_DIM,
    FigureEightPlannerReward,
)
from mapets_rl.envs.vehicles import ACC_MAX, ACC_MIN
from mapets_rl.experiment import atomic_write_text
from mapets_rl.machine import machine_line
from mapets_rl.statistics import bootstrap_interval

RULES = ("none", "occupy", "crossing-order", "brake", "recover")
OBS_KEY = ("agents", "observation")
ACTION_KEY = ("agents", "action")
NEIGHBOUR_KEY = ("agents", "info", "neighbour_cav")
LINKS_KEY = ("agents", "neighbors")
DT = 0.1
"""The figure-eight's step [s]."""
LEADER, CONFLICT, OTHER_LEADER = 0, 2, 3
"""Slots of ``info["neighbour_cav"]`` on two lanes: leader, follower, conflicting vehicle,
other-lane leader, other-lane follower."""
RECOVER_SLACK = 0.1
"""Metres ``recover`` adds beyond the gap test's margin and one step's closing [m]."""
STOP_MARGIN = 1.0
"""Metres a yielding CAV must have to spare, beyond its braking distance, for the other to go
first [m]."""


def linked_sender(neighbour: torch.Tensor, links: torch.Tensor | None, slot: int):
    """``(sender [I], heard [I])`` of ``slot`` (:func:`~mapets_rl.comm.plans.linked_senders`;
    ``links`` None: nobody is heard)."""
    if links is None:
        links = torch.zeros(*neighbour.shape[:-1], neighbour.shape[-2], dtype=torch.bool)
    index, heard = linked_senders(neighbour, links.to(torch.bool))
    return index[..., slot], heard[..., slot]


def occupy_both_lanes(
    obs: torch.Tensor, neighbour: torch.Tensor, links: torch.Tensor | None
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Rule ``occupy`` on ``obs [I, 15]``, ``neighbour [I, 5]``, ``links [I, I]`` (or None).

    Returns the planner's observation and neighbour slots, and ``[I]`` bool: the CAVs whose
    leader became their other-lane leader."""
    position = obs[..., 10]
    between = (position - position.round()).abs() > SETTLED_LANE_POSITION
    sender, heard = linked_sender(neighbour, links, OTHER_LEADER)
    moving_in = heard & between[sender]
    swap = (between | moving_in) & (obs[..., 13] < obs[..., 5])
    out = obs.clone()
    out[..., 3] = torch.where(swap, obs[..., 11], obs[..., 3])
    out[..., 5] = torch.where(swap, obs[..., 13], obs[..., 5])
    slots = neighbour.clone()
    slots[..., LEADER] = torch.where(swap, neighbour[..., OTHER_LEADER], neighbour[..., LEADER])
    return out, slots, swap


def crossing_order(
    obs: torch.Tensor,
    neighbour: torch.Tensor,
    links: torch.Tensor | None,
    crossing_gap: float,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Rule ``crossing-order`` on ``obs [I, 10 or 15]``, ``neighbour [I, K]``, ``links``.

    Returns the planner's observation and neighbour slots, and ``[I]`` bool: the CAVs that go
    first (their conflicting vehicle removed from what they plan with)."""
    sender, heard = linked_sender(neighbour, links, CONFLICT)
    mine, theirs, speed = obs[..., 7], obs[..., 8], obs[..., 9]
    index = torch.arange(obs.shape[-2], device=obs.device)
    first = (mine < theirs) | ((mine == theirs) & (index < sender))
    can_stop = theirs - crossing_gap >= speed.square() / (2.0 * -ACC_MIN) + STOP_MARGIN
    go = heard & first & can_stop & (theirs < GAP_RANGE)
    out = obs.clone()
    out[..., 8] = torch.where(go, torch.full_like(theirs, GAP_RANGE), theirs)
    out[..., 9] = torch.where(go, torch.zeros_like(speed), speed)
    slots = neighbour.clone()
    slots[..., CONFLICT] = torch.where(go, -1, neighbour[..., CONFLICT])
    return out, slots, go


def recover_gap(obs: torch.Tensor, reward: FigureEightPlannerReward, dt: float) -> torch.Tensor:
    """Rule ``recover``: ``obs [I, S]`` with the gap ahead of the CAVs inside the margin
    raised to the margin at the highest speed of the next step, plus one step of closing at
    the current speeds and ``RECOVER_SLACK``."""
    speed, gap = obs[..., 0], obs[..., 5]
    reach = reward.collision_gap + reward.headway * (speed + ACC_MAX * dt)
    closing = (speed - obs[..., 3]).clamp_min(0.0) * dt
    out = obs.clone()
    lifted = torch.maximum(gap, reach + closing + RECOVER_SLACK)
    out[..., 5] = torch.where(reward.lost(obs), lifted, gap)
    return out


class RulePolicy(TensorDictModuleBase):
    """A planner (or :class:`~mapets_rl.planning.shared_plans.PlanSharingPlanner`) under one
    rule: ``occupy`` and ``crossing-order`` change what it plans with (a copy of the
    observation and of ``info["neighbour_cav"]``), ``brake`` overrides its action.

    Attributes:
        applied: agent-steps at which the rule changed something since construction.
    """

    def __init__(
        self, policy: TensorDictModuleBase, rule: str, reward: FigureEightPlannerReward
    ) -> None:
        super().__init__()
        if rule not in RULES:
            raise ValueError(f"rule must be one of {list(RULES)}, got {rule!r}")
        self.policy, self.rule, self.reward = policy, rule, reward
        self.in_keys, self.out_keys = policy.in_keys, policy.out_keys
        self.applied = 0

    def reset(self) -> None:
        if hasattr(self.policy, "reset"):
            self.policy.reset()

    @property
    def broadcasts(self) -> int:
        return getattr(self.policy, "broadcasts", 0)

    @property
    def plans_used(self) -> int:
        return getattr(self.policy, "plans_used", 0)

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        obs = tensordict.get(OBS_KEY)
        if self.rule == "brake":
            tensordict = self.policy(tensordict)
            self.applied += int(self.reward.lost(obs).sum())
            return tensordict.set(
                ACTION_KEY, self.reward.brake_if_lost(obs, tensordict.get(ACTION_KEY))
            )
        if self.rule == "none":
            return self.policy(tensordict)
        if self.rule == "recover":
            self.applied += int(self.reward.lost(obs).sum())
            view = tensordict.clone(False).set(OBS_KEY, recover_gap(obs, self.reward, DT))
            return tensordict.set(ACTION_KEY, self.policy(view).get(ACTION_KEY))
        neighbour = tensordict.get(NEIGHBOUR_KEY)
        links = tensordict.get(LINKS_KEY, None)
        if self.rule == "occupy":
            planned, slots, changed = occupy_both_lanes(obs, neighbour, links)
        else:
            planned, slots, changed = crossing_order(
                obs, neighbour, links, self.reward.crossing_gap
            )
        self.applied += int(changed.sum())
        view = tensordict.clone(False)
        view.set(OBS_KEY, planned)
        view.set(NEIGHBOUR_KEY, slots)
        return tensordict.set(ACTION_KEY, self.policy(view).get(ACTION_KEY))


def summarise(rows: list[dict]) -> list[dict]:
    """Per (rule, headway): safety and agility with 95% bootstrap intervals, crashes and
    their classes per episode, and how often the rule acted per step."""
    groups: dict[tuple, list[dict]] = {}
    for row in rows:
        groups.setdefault((row["rule"], row["headway"]), []).append(row)
    out = []
    for (rule, headway), group in sorted(
        groups.items(), key=lambda g: (g[0][1], RULES.index(g[0][0]))
    ):
        point = {"rule": rule, "headway": headway, "seeds": len(group)}
        for metric, bounds in (("safety", (0.0, 1.0)), ("agility", (0.0, np.inf))):
            point[metric] = bootstrap_interval([r[metric] for r in group], bounds=bounds)
        point["crashes"] = float(np.mean([r["crashes"] for r in group]))
        point["classes"] = {
            c: float(np.mean([r["classes"].get(c, 0) for r in group])) for c in CLASSES
        }
        point["applied"] = float(np.mean([r["applied"] for r in group]))
        out.append(point)
    return out


def table(points: list[dict]) -> str:
    head = " | ".join(CLASSES)
    lines = [
        f"| headway [s] | rule | seeds | safety [95% CI] | agility [m/step] [95% CI] | "
        f"crashes / 22 | {head} | rule acted / step |",
        "|---|---|---|---|---|---|" + "---|" * (len(CLASSES) + 1),
    ]
    for p in points:
        s, a = p["safety"], p["agility"]
        classes = " | ".join(f"{p['classes'][c]:.1f}" for c in CLASSES)
        lines.append(
            f"| {p['headway']:g} | {p['rule']} | {p['seeds']} | {s.estimate:.3f} [{s.low:.3f}, "
            f"{s.high:.3f}] | {a.estimate:.3f} [{a.low:.3f}, {a.high:.3f}] | {p['crashes']:.1f} | "
            f"{classes} | {p['applied']:.2f} |"
        )
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> list[dict]:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, required=True, help="folder of rows.jsonl")
    parser.add_argument("--policy", default="oracle-shared", choices=("oracle", "oracle-shared"))
    parser.add_argument("--rules", nargs="+", choices=RULES, default=list(RULES))
    parser.add_argument("--headway", nargs="+", type=float, default=[0.0, 0.25, 0.5])
    parser.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2, 3, 4, 5])
    parser.add_argument("--steps", type=int, default=400, help="steps per episode (>= 1)")
    parser.add_argument("--comm-range", type=float, default=100.0, help="oracle-shared: d [m]")
    parser.add_argument(
        "--env",
        nargs="*",
        default=[],
        metavar="key=value",
        help="scenario changes for every episode, e.g. n_hvs=0",
    )
    parser.add_argument(
        "--reward",
        nargs="*",
        default=[],
        metavar="key=value",
        help="FigureEightPlannerReward fields besides headway (default "
        "lane_change_gap 8 m and the rest of the recipe's margins)",
    )
    args = parser.parse_args(argv)
    if args.steps < 1:
        parser.error(f"--steps must be >= 1, got {args.steps}")
    if not args.comm_range >= 0:
        parser.error(f"--comm-range must be >= 0 metres, got {args.comm_range}")
    try:
        env_config = dict(map(parse_override, args.env))
        env = make_env(SCENARIO, **env_config)
        obs_dim = env.observation_spec[OBS_KEY].shape[-1]
        env.close()
        reward_fields = dict(map(parse_override, args.reward))
        if "headway" in reward_fields:
            raise ConfigError("headway is the grid's: give it as --headway")
        rewards = {h: FigureEightPlannerReward(**reward_fields, headway=h) for h in args.headway}
    except (ConfigError, ValueError, TypeError) as err:
        parser.error(str(err))
    if obs_dim != TWO_LANE_OBS_DIM:
        parser.error("the rules read the two-lane observation (observation=crossing)")
    torch.set_num_threads(1)
    print(f"# {machine_line()}")
    args.out.mkdir(parents=True, exist_ok=True)
    path = args.out / "rows.jsonl"
    tag = " ".join([args.policy, *args.env, *args.reward, f"steps={args.steps}"])
    rows = [r for r in load_rows(path) if r.get("tag") == tag]
    done = {(r["rule"], r["headway"], r["seed"]) for r in rows}
    for headway in args.headway:
        for rule in args.rules:
            for seed in args.seeds:
                if (rule, headway, seed) in done:
                    continue
                made: list[RulePolicy] = []

                def wrap(policy, rule=rule, reward=rewards[headway], made=made) -> RulePolicy:
                    made.append(RulePolicy(policy, rule, reward))
                    return made[-1]

                row, trace = drive(
                    args.policy, seed, args.steps, rewards[headway], SCENARIO,
                    comm_range=args.comm_range, env_config=env_config, wrap=wrap,
                    anchor_candidates=True, keep_best=True,
                )  # fmt: skip
                steps = trace["speeds"].shape[0] - 1
                row.update(rule=rule, headway=headway, tag=tag, applied=made[0].applied / steps)
                rows.append(row)
                with path.open("a") as handle:
                    handle.write(json.dumps(row) + "\n")
                print(json.dumps(row), flush=True)
    selected = [r for r in rows if r["rule"] in args.rules and r["headway"] in args.headway]
    text = table(summarise(selected))
    print(text)
    atomic_write_text(args.out / "rules.md", f"# {tag}\n\n{text}\n")
    return selected


if __name__ == "__main__":
    from mapets_rl import quiet_dependencies

    quiet_dependencies()
    main()
