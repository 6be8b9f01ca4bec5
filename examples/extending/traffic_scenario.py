"""A custom traffic scenario trained with MA-PETS: the README's "Extending" recipe, end to end.

The scenario, ``stop-and-go``: one straight lane, ``n_cavs`` CAVs queued among ``n_hvs``
human drivers (highway-env IDM) whose desired speeds are drawn per episode, 0.1 s steps. A CAV
sets its target speed in ``[0, max_speed]`` m/s and observes ``(v, gap_ahead, v_ahead)``
(speeds in m/s; bumper-to-bumper gap in [0, 50] m, 50 and 0 when nobody is within 50 m).
Reward per step: ``v`` (m/s), ``collision_reward`` in the step a CAV crashes. A CAV that drives
at top speed runs into a slower driver ahead: the planner must learn when to brake.

The three pieces an extension writes, in the order of the README:

1. the scenario: :class:`StopAndGoEnv` subclasses ``mapets_rl.envs.MultiAgentTrafficEnv``
   (road, spawning, ``observe_agents``, ``agent_rewards``, ``episode_metrics``),
   :class:`StopAndGoParallelEnv` wraps it as a PettingZoo ``TrafficParallelEnv``, and
   :func:`make_stop_and_go` turns that into the torchrl env every recipe uses with
   ``mapets_rl.envs.wrap_pettingzoo`` (which puts the CAVs' positions under
   ``("agents", "position")``, where MA-PETS' ``CommunicationRange`` reads them);
2. a reward function for MA-PETS: :func:`stop_and_go_reward` and
   :func:`stop_and_go_collision`, vectorised functions of ``(obs, action, next_obs)`` that the
   planner evaluates on predicted trajectories;
3. a loss: :class:`EnsembleMSELoss`, a ``LossModule`` that fits the ensemble's mean by squared
   error (a deterministic ensemble, PETS' "DE"), used by the recipe
   :class:`StopAndGoMAPETS` (MA-PETS with this scenario's reward and that loss; the planner
   then propagates the members' mean, ``planner.propagation="expectation"``).

Make the scenario and recipe available by name: in this process with
``register_env("stop-and-go", make_stop_and_go)`` (``main`` does this); in every process (the
``mapets-rl`` command, ``resume`` and ``evaluate`` included) with entry points in your
package's ``pyproject.toml``::

    [project.entry-points."mapets_rl.scenarios"]
    stop-and-go = "traffic_scenario:make_stop_and_go"

    [project.entry-points."mapets_rl.recipes"]
    mapets-stop-and-go = "traffic_scenario:StopAndGoMAPETS"

then ``mapets-rl train mapets-stop-and-go --env stop-and-go episodes=3``.

Run it to train MA-PETS on the scenario (the first episode drives randomly; cpu preset planner
with mean propagation, 30 model epochs per episode; about 20 s on two cores):

    python examples/extending/traffic_scenario.py [--episodes 4] [--horizon 60] [--comm-range 100]
"""

from __future__ import annotations

import argparse
import dataclasses
import tempfile
from typing import Any

import numpy as np
import torch
from highway_env.road.lane import LineType, StraightLane
from highway_env.road.road import RoadNetwork
from highway_env.vehicle.kinematics import Vehicle
from tensordict import TensorDict, TensorDictBase
from torchrl.envs import EnvBase
from torchrl.objectives import LossModule

from mapets_rl.envs import MultiAgentTrafficEnv, TrafficParallelEnv, wrap_pettingzoo
from mapets_rl.envs.figure_eight import TargetSpeedAction
from mapets_rl.envs.road import SortedNeighbourRoad
from mapets_rl.envs.traffic import AgentObservation, require
from mapets_rl.envs.vehicles import HumanVehicle, TargetSpeedVehicle
from mapets_rl.metrics import agility, safety
from mapets_rl.models import ProbabilisticEnsemble
from mapets_rl.objectives import read_transitions
from mapets_rl.planning import PlannerConfig
from mapets_rl.recipes.mapets import MAPETS, MAPETSConfig

GAP_RANGE = 50.0
"""Gaps beyond this many metres read as ``GAP_RANGE`` (nobody ahead)."""
COLLISION_GAP = 2.0
"""The planner predicts a crash when the predicted gap ahead falls below this [m]."""


# ------------------------------------------------------------------------------ 1. scenario
class StopAndGoEnv(MultiAgentTrafficEnv):
    """A single lane with CAVs among human drivers (see the module docstring).

    Config keys (defaults): ``n_cavs=4``, ``n_hvs=4``, ``horizon=100`` steps,
    ``max_speed=13.89`` m/s, ``hv_target_speed=(3, 10)`` m/s, ``spacing=15`` m (initial,
    centre to centre), ``collision_reward=-10``, plus those of ``MultiAgentTrafficEnv``.
    """

    obs_dim = 3

    @classmethod
    def default_config(cls) -> dict:
        config = super().default_config()
        config.update(
            {
                "n_cavs": 4,
                "n_hvs": 4,
                "lanes": 1,  # read by TargetSpeedAction: no lane-change flag
                "horizon": 100,
                "max_speed": 13.89,
                "hv_target_speed": (3.0, 10.0),
                "spacing": 15.0,
                "screen_width": 600,
                "screen_height": 150,
            }
        )
        return config

    @classmethod
    def validate_config(cls, config: dict) -> None:
        super().validate_config(config)
        require(
            isinstance(config["n_hvs"], int) and config["n_hvs"] >= 0,
            f"n_hvs must be an integer >= 0, got {config['n_hvs']!r}",
        )
        require(config["lanes"] == 1, f"lanes must be 1, got {config['lanes']!r}")
        require(config["spacing"] >= 7.0, f"spacing must be >= 7 m, got {config['spacing']!r}")

    def define_spaces(self) -> None:
        self.observation_type = AgentObservation(self, self.obs_dim)
        self.action_type = TargetSpeedAction(self)
        self.observation_space = self.observation_type.space()
        self.action_space = self.action_type.space()

    @property
    def road_length(self) -> float:
        """Long enough for the queue plus an episode at top speed [m]."""
        cfg = self.config
        queue = (cfg["n_cavs"] + cfg["n_hvs"]) * cfg["spacing"]
        return queue + 1.2 * cfg["max_speed"] * cfg["horizon"] * self.dt + 50.0

    def _make_road(self) -> SortedNeighbourRoad:
        net = RoadNetwork()
        lane = StraightLane(
            [0.0, 0.0],
            [self.road_length, 0.0],
            line_types=(LineType.CONTINUOUS_LINE, LineType.CONTINUOUS_LINE),
            speed_limit=self.config["max_speed"],
        )
        net.add_lane("a", "b", lane)
        return SortedNeighbourRoad(
            net,
            coordinate=lambda lane_index, position: float(position[0]),
            period=None,
            n_lanes=1,
            np_random=self.np_random,
        )

    def _spawn_vehicles(self) -> list[Vehicle]:
        cfg, rng = self.config, self.np_random
        n = cfg["n_cavs"] + cfg["n_hvs"]
        is_cav = self._draw_cavs(n)
        if cfg["n_hvs"] and is_cav[-1]:  # a human driver leads the queue
            is_cav[[-1, np.flatnonzero(~is_cav)[0]]] = [False, True]
        cavs = []
        for k in range(n):
            x, speed = k * cfg["spacing"], float(rng.uniform(4.0, 8.0))
            if is_cav[k]:
                vehicle = self._place_vehicle(
                    TargetSpeedVehicle, ("a", "b", 0), x, speed, cfg["max_speed"]
                )
                vehicle.target_speed = speed
                cavs.append(vehicle)
            else:
                target = float(rng.uniform(*cfg["hv_target_speed"]))
                self._place_vehicle(
                    HumanVehicle, ("a", "b", 0), x, speed, cfg["max_speed"], target_speed=target
                )
        return cavs

    def observe_agents(self) -> np.ndarray:
        """``[I, 3]``: own speed, gap to and speed of the vehicle ahead (zeros once crashed)."""
        obs = np.zeros((len(self.cavs), 3), dtype=np.float32)
        for i, cav in enumerate(self.cavs):
            if not self.alive[i]:
                continue
            front, _ = self.road.neighbour_vehicles(cav)
            gap, v_ahead = GAP_RANGE, 0.0
            if front is not None:
                gap = self.road.longitudinal_distance(cav, front) - 0.5 * (
                    cav.LENGTH + front.LENGTH
                )
                v_ahead = front.speed if gap <= GAP_RANGE else 0.0
            obs[i] = (cav.speed, float(np.clip(gap, 0.0, GAP_RANGE)), v_ahead)
        return obs

    def agent_rewards(self, obs: np.ndarray, action: Any) -> np.ndarray:
        """``v`` per CAV, ``collision_reward`` in its crash step, 0 once gone: ``[I]``."""
        rewards = np.where(self._crashed_now, self.config["collision_reward"], obs[:, 0])
        return (rewards * (self.alive | self._crashed_now)).astype(np.float32)

    def episode_metrics(self) -> dict[str, float]:
        """Agility [m/step] and safety (MA-PETS paper eqs. 27-28) of the episode so far."""
        horizon = self.config["horizon"]
        collision_steps = np.where(self.alive, horizon, self.collision_step - 1)
        distances = self._episode_distances
        return {
            "agility": agility(np.stack(distances), collision_steps) if distances else 0.0,
            "safety": safety(collision_steps, horizon),
            "collisions": int((~self.alive).sum()),
        }


class StopAndGoParallelEnv(TrafficParallelEnv):
    """:class:`StopAndGoEnv` as a PettingZoo ``ParallelEnv`` (``**config``: its keys)."""

    metadata = {**TrafficParallelEnv.metadata, "name": "stop_and_go_v0"}
    env_class = StopAndGoEnv

    def __init__(self, render_mode: str | None = None, **config: Any) -> None:
        super().__init__(StopAndGoEnv(config, render_mode=render_mode), render_mode)


def make_stop_and_go(**config: Any) -> EnvBase:
    """The scenario factory: ``factory(**env_config)`` -> the torchrl env of the scenario."""
    return wrap_pettingzoo(StopAndGoParallelEnv(**config))


# ------------------------------------------------------------------- 2. reward for MA-PETS
def stop_and_go_collision(
    obs: torch.Tensor, action: torch.Tensor, next_obs: torch.Tensor
) -> torch.Tensor:
    """Predicted crash: the predicted gap ahead below ``COLLISION_GAP``. ``[...]`` bool."""
    return next_obs[..., 1] < COLLISION_GAP


def stop_and_go_reward(
    obs: torch.Tensor, action: torch.Tensor, next_obs: torch.Tensor
) -> torch.Tensor:
    """The scenario's reward on a predicted step: ``v'``, -10 on a predicted crash. ``[...]``.

    Args:
        obs: ``[..., 3]`` observation (unused: the reward depends on the outcome).
        action: ``[..., 1]`` target speed (unused).
        next_obs: ``[..., 3]`` predicted next observation.
    """
    crash = stop_and_go_collision(obs, action, next_obs)
    return torch.where(crash, torch.full_like(next_obs[..., 0], -10.0), next_obs[..., 0])


# ------------------------------------------------------------------------------- 3. a loss
class EnsembleMSELoss(LossModule):
    """Squared error of every member's mean next-state delta (normalised), no bootstrap.

    The contract of :meth:`mapets_rl.recipes.mapets.MAPETS.make_loss`: it holds the ensemble as
    ``model`` and reads a batch ``[n]`` of the ``"agents"`` keys (``("agents",
    "observation")``, ``("agents", "action")``, ``("next", "agents", "observation")``
    ``[n, I, *]``, ``("agents", "mask")`` ``[n, I]``), validated by ``read_transitions``.
    Output: ``loss_mse`` (sum over agents and members of the mean squared error) and
    ``nll_per_member`` ``[I, B]`` (the per-member MSE, the diagnostic MA-PETS logs).
    """

    def __init__(self, model: ProbabilisticEnsemble) -> None:
        super().__init__()
        self.model = model

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        obs, action, next_obs, mask = read_transitions(tensordict, self.model)  # [n, I, *]
        model = self.model
        x = model.normalize_inputs(obs.transpose(0, 1), action.transpose(0, 1))  # [I, n, in]
        y = ((next_obs - obs).transpose(0, 1) - model.output_mean[:, 0]) / model.output_std[:, 0]
        mean, _ = model.normalized_forward(x.unsqueeze(1).expand(-1, model.ensemble_size, -1, -1))
        weight = torch.ones(y.shape[:2], dtype=y.dtype, device=y.device)  # [I, n]
        if mask is not None:
            weight = mask.transpose(0, 1).to(y.dtype)
        se = (mean - y.unsqueeze(1)).pow(2).mean(-1)  # [I, B, n]
        mse = (se * weight.unsqueeze(1)).sum(-1) / weight.sum(-1, keepdim=True).clamp_min(1.0)
        return TensorDict({"loss_mse": mse.sum(), "nll_per_member": mse.detach()}, batch_size=[])


@dataclasses.dataclass
class StopAndGoMAPETSConfig(MAPETSConfig):
    """MA-PETS on ``stop-and-go`` (see :class:`mapets_rl.recipes.mapets.MAPETSConfig`), with the cpu
    preset and mean propagation (the ensemble is deterministic) as defaults."""

    env: str = "stop-and-go"
    preset: str = "cpu"
    planner: PlannerConfig | None = dataclasses.field(
        default_factory=lambda: {"propagation": "expectation"}
    )


class StopAndGoMAPETS(MAPETS):
    """MA-PETS that plans with :func:`stop_and_go_reward` / :func:`stop_and_go_collision` and
    fits its ensembles with :class:`EnsembleMSELoss`."""

    name = "mapets-stop-and-go"
    Config = StopAndGoMAPETSConfig

    def __init__(self, config: StopAndGoMAPETSConfig, run_dir: Any = None) -> None:
        super().__init__(
            config,
            run_dir,
            reward_fn=stop_and_go_reward,
            termination_fn=stop_and_go_collision,
        )

    def make_loss(self, model: ProbabilisticEnsemble) -> LossModule:
        return EnsembleMSELoss(model)


def main() -> None:
    from mapets_rl.experiment import register_env

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--episodes", type=int, default=4, help="episodes (1 random)")
    parser.add_argument("--horizon", type=int, default=60, help="steps per episode")
    parser.add_argument("--comm-range", type=float, default=100.0, help="d in metres")
    args = parser.parse_args()
    register_env("stop-and-go", make_stop_and_go)
    config = StopAndGoMAPETSConfig(
        episodes=args.episodes,
        env_config={"horizon": args.horizon},
        comm={"comm_range": args.comm_range},
        logger="none",
        progress=False,
        seed=0,
    )
    with tempfile.TemporaryDirectory() as run_dir:
        history = StopAndGoMAPETS(config, run_dir).train()
    for entry in history:
        m = entry["metrics"]
        print(
            f"episode {int(m['episode'])}: safety {m['safety']:.3f} agility "
            f"{m['agility']:.3f} m/step transitions_shared {int(m['transitions_shared'])} "
            f"model_mse {m.get('model_nll', float('nan')):.4f}"
        )


if __name__ == "__main__":
    main()
