"""What the benchmark scripts share (they import nothing else of ``benchmarks/``):

- the episode loop of the two-lane figure-eight studies (``multilane_diagnosis.py``,
  ``safety_agility_frontier.py``): the policies that separate the causes of a crash, one
  episode of each, every CAV crash classified;
- a published config with ``--set`` scenario settings over it (``critic_resolution.py``,
  ``dilemma_counterfactuals.py``);
- mbrl-lib as an in-process reference (``planner.py`` and ``ensemble_training.py``
  ``--reference mbrl-lib``), below.

mbrl-lib is facebookresearch/mbrl-lib 0.2.0; nothing here installs it. It pins
``hydra-core==1.0.3`` (which does not import on Python 3.11), ``omegaconf<2.1`` and
``gymnasium==0.26.3``, and the project's torch and gymnasium must not change: :data:`INSTALL`
is the recipe, a separate virtual environment layered on the project's one (its own
site-packages first, then the project's), with mbrl installed without its pins.

How mbrl-lib is configured here and what differs from our planner at the same sizes:
[docs/results/performance.md](../docs/results/performance.md#mbrl-lib-as-the-reference-how-it-is-configured).
"""

from __future__ import annotations

import argparse
import functools
import sys
import time
from collections import Counter
from collections.abc import Callable
from types import ModuleType
from typing import Any

import numpy as np
import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase

from mapets_rl.app.plugins import load_recipe
from mapets_rl.comm import CommunicationRange
from mapets_rl.envs import ScriptedCAVPolicy, make_env, traffic_env
from mapets_rl.envs.figure_eight import FigureEightPlannerReward, neighbour_speed_columns
from mapets_rl.envs.figure_eight_kinematics import FigureEightKinematicModel
from mapets_rl.experiment import RunConfig
from mapets_rl.experiment.published import load_published
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
    "learned",
    "learned-shared",
)
"""The policies of :func:`make_policy` (``multilane_diagnosis.py``'s docstring)."""
CLASSES = ("crossing", "lane change (CAV)", "lane change (other)", "into leader", "rear-ended")
"""The classes of a CAV crash (:func:`classify`)."""
NEAR_CROSSING = 10.0
"""A vehicle within this many metres of a crossing point [m] is at the crossing."""
BETWEEN_LANES = 0.6
"""A vehicle more than this far from its lane's centre [m], or steering to another lane, is
changing lanes."""


def add_published_config_args(parser: argparse.ArgumentParser, default: str) -> None:
    """``--config`` (a published config's name, ``default`` unless given) and ``--set
    KEY=VALUE ...`` (scenario settings over the config's), read by :func:`published_config`."""
    parser.add_argument("--config", default=default)
    parser.add_argument("--set", nargs="*", default=[], metavar="KEY=VALUE",
                        help="scenario settings over the config's (env_config keys)")  # fmt: skip


def published_config(args: argparse.Namespace) -> RunConfig:
    """The run config of the published config ``args.config`` with the scenario settings
    ``args.set`` (``KEY=VALUE``, each an ``env_config`` key) over its own."""
    published = load_published(args.config)
    overrides = [f"env_config.{item}" for item in args.set]
    return load_recipe(published.recipe).Config.from_fields(published.fields, overrides)


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
    **cem: Any,
) -> TensorDictModuleBase:
    """The policy ``name`` of :data:`POLICIES` for ``env`` (``learned*``: the planner of the
    MA-PETS run ``run``; ``cem``: PlannerConfig fields of the oracle's planner)."""
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
    **cem: Any,
) -> dict:
    """One episode of policy ``name``: safety, agility and crashes (each CAV crash classified,
    :func:`classify`), the time per step, the human drivers' mean m/step, the plans sent and
    used per step."""
    env = make_env(scenario, seed=seed, horizon=horizon, **(env_config or {}))
    if name.endswith("shared"):  # the step's communication graph, for the broadcasts
        env = env.append_transform(CommunicationRange(comm_range))
    raw = traffic_env(env)
    policy = make_policy(name, env, seed, reward, run, run_overrides, **cem)
    if hasattr(policy, "reset"):
        policy.reset()
    td = env.reset()
    classes: Counter = Counter()
    with_cav = 0
    start = time.perf_counter()
    steps = 0
    human_distance = 0.0  # summed over the steps: the human drivers' mean m/step
    with torch.no_grad():
        while True:
            before = snapshot(raw)
            alive = raw.alive.copy()
            td = env.step(policy(td))
            steps += 1
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
    env.close()
    return row


#: Values accepted by the benchmarks' ``--reference`` flag.
REFERENCES = ("mbrl-lib",)

#: How to install mbrl-lib beside the project's pinned torch without changing it.
INSTALL = """\
mbrl-lib is not importable from this Python ({reason}).
Install it in a separate virtual environment layered on the project's (nothing in the
project's .venv changes; torch stays {torch}):

  python3 -m venv /work/mbrl-venv
  SHARED=$(/work/main/.venv/bin/python -c 'import site; print(site.getsitepackages()[0])')
  OWN=$(/work/mbrl-venv/bin/python -c 'import site; print(site.getsitepackages()[0])')
  echo "import site; site.addsitedir('$SHARED')" > "$OWN/zz_shared_venv.pth"
  /work/mbrl-venv/bin/pip install --no-deps mbrl==0.2.0 hydra-core==1.3.2 omegaconf==2.3.0 \\
      antlr4-python3-runtime==4.9.3 termcolor
  /work/mbrl-venv/bin/python -c "import torch, mbrl.models, mbrl.planning; print(torch.__version__)"

(--no-deps: mbrl 0.2.0 pins hydra-core==1.0.3, which fails to import on Python 3.11, and
gymnasium==0.26.3; the benchmarks use only mbrl.models, mbrl.planning and mbrl.util, which run
with hydra-core 1.3 and the project's gymnasium.) Then run the benchmark with that Python from
the repository root, e.g.

  PYTHONPATH=. /work/mbrl-venv/bin/python benchmarks/planner.py --reference mbrl-lib ...
"""


def import_mbrl() -> ModuleType:
    """Import the parts of mbrl-lib the references use; any failure propagates."""
    import mbrl
    import mbrl.models
    import mbrl.planning
    import mbrl.types
    import mbrl.util.replay_buffer  # noqa: F401

    return mbrl


def require_mbrl(reference: str) -> ModuleType:
    """Return the ``mbrl`` package, or print :data:`INSTALL` and exit with status 2.

    Called right after argument parsing, before any benchmark work.
    """
    if reference not in REFERENCES:
        raise ValueError(f"reference must be one of {list(REFERENCES)}, got {reference!r}.")
    try:
        return import_mbrl()
    except Exception as exc:  # ImportError, or hydra-core 1.0.3's ValueError on Python 3.11
        reason = f"{type(exc).__name__}: {exc}"
        print(INSTALL.format(reason=reason, torch=torch.__version__), file=sys.stderr)
        raise SystemExit(2) from None


def _gaussian_dynamics(
    mbrl: ModuleType,
    in_size: int,
    out_size: int,
    members: int,
    hidden: tuple[int, ...],
    propagation: str | None,
    learn_logvar_bounds: bool,
    device: str = "cpu",
) -> Any:
    """mbrl-lib's ``GaussianMLP`` ensemble (SiLU, equal hidden sizes) inside a
    ``OneDTransitionRewardModel`` predicting normalised state deltas (no learned reward)."""
    if len(set(hidden)) != 1:
        raise ValueError(
            f"mbrl-lib's GaussianMLP has equal hidden sizes, got hidden={list(hidden)}."
        )
    net = mbrl.models.GaussianMLP(
        in_size,
        out_size,
        device,
        num_layers=len(hidden),
        ensemble_size=members,
        hid_size=hidden[0],
        deterministic=False,
        propagation_method=propagation,
        learn_logvar_bounds=learn_logvar_bounds,
        activation_fn_cfg={"_target_": "torch.nn.SiLU"},
    )
    return mbrl.models.OneDTransitionRewardModel(
        net,
        target_is_delta=True,
        normalize=True,
        normalize_double_precision=True,
        learned_rewards=False,
    )


def _copy_member_weights(net: torch.nn.Module, model: torch.nn.Module, agent: int) -> None:
    """Copy agent ``agent``'s layers of our ``ProbabilisticEnsemble`` into a ``GaussianMLP``.

    Both store ``[B, in, out]`` weights and ``[B, 1, out]`` biases per layer. Our model also
    de-normalises its outputs (``output_mean/std``); mbrl-lib's does not, so the predictions
    differ by that affine map (the shapes and FLOPs are the same).
    """
    layers = [seq[0] for seq in net.hidden_layers] + [net.mean_and_logvar]
    with torch.no_grad():
        for layer, weight, bias in zip(layers, model.weights, model.biases, strict=True):
            layer.weight.copy_(weight[agent])
            layer.bias.copy_(bias[agent])


def pets_agents(
    model: torch.nn.Module,
    cfg: object,
    low: float,
    high: float,
    reward_fn: Callable[[torch.Tensor, torch.Tensor, torch.Tensor], torch.Tensor],
    seed: int = 0,
    device: str = "cpu",
) -> list:
    """One mbrl-lib PETS agent per agent of ``model`` (a ``ProbabilisticEnsemble``).

    Args:
        model: our ensemble ``[I agents x B members]``; each mbrl-lib agent gets a
            ``GaussianMLP`` with agent ``i``'s weights and input normalisation.
        cfg: a :class:`~mapets_rl.planning.Preset` (planner and model sizes).
        low, high: scalar action bounds.
        reward_fn: our known reward ``(obs, action, next_obs) -> [...]``; mbrl-lib's reward
            sees only ``(action, next_obs)`` and is given ``next_obs`` as ``obs`` (the
            figure-eight's reads ``obs`` only in its headway test of a closing gap, which
            then never fires: give it ``headway=0`` for the same scores on both sides).
        seed: seeds each agent's ``ModelEnv`` generator.
        device: where mbrl-lib's models, particles and CEM run (``"cpu"``, ``"cuda"``).

    Returns:
        ``I`` ``TrajectoryOptimizerAgent`` s; ``agent.act(obs)`` takes a ``[obs]`` float32
        numpy array and returns a ``[act]`` array.
    """
    import gymnasium
    from omegaconf import OmegaConf

    mbrl = import_mbrl()
    planner, sizes = cfg.planner, cfg.model
    obs_dim, act_dim = model.obs_dim, model.action_dim
    if planner.propagation != "ts_inf":
        raise ValueError(f"the mbrl-lib reference uses TS-inf, got {planner.propagation!r}.")

    class _Spaces:  # ModelEnv reads only the spaces of the env it models
        observation_space = gymnasium.spaces.Box(-np.inf, np.inf, (obs_dim,), np.float32)
        action_space = gymnasium.spaces.Box(low, high, (act_dim,), np.float32)

    def reward(action: torch.Tensor, next_obs: torch.Tensor) -> torch.Tensor:
        return reward_fn(next_obs, action, next_obs).unsqueeze(-1)

    def no_termination(action: torch.Tensor, next_obs: torch.Tensor) -> torch.Tensor:
        return torch.zeros(next_obs.shape[0], 1, dtype=torch.bool, device=next_obs.device)

    agents = []
    for i in range(model.n_agents):
        dynamics = _gaussian_dynamics(
            mbrl,
            obs_dim + act_dim,
            obs_dim,
            sizes.ensemble_size,
            tuple(sizes.hidden),
            "fixed_model",
            learn_logvar_bounds=False,
            device=device,
        )
        _copy_member_weights(dynamics.model, model, i)
        dynamics.input_normalizer.mean = model.input_mean[i, 0].double().to(device)
        dynamics.input_normalizer.std = model.input_std[i, 0].double().to(device)
        model_env = mbrl.models.ModelEnv(
            _Spaces(),
            dynamics,
            no_termination,
            reward,
            generator=torch.Generator(device=device).manual_seed(seed + i),
        )
        agent_cfg = OmegaConf.create(
            {
                "_target_": "mbrl.planning.TrajectoryOptimizerAgent",
                # hydra >= 1.1 instantiates nested configs by default; mbrl 0.2.0 was written
                # for hydra 1.0 and instantiates the optimizer itself from this config.
                "_recursive_": False,
                "action_lb": [float(low)] * act_dim,
                "action_ub": [float(high)] * act_dim,
                "planning_horizon": planner.horizon,
                "replan_freq": 1,
                "verbose": False,
                "optimizer_cfg": {
                    "_target_": "mbrl.planning.CEMOptimizer",
                    "num_iterations": planner.iterations,
                    "elite_ratio": planner.elites / planner.population,
                    "population_size": planner.population,
                    "alpha": planner.alpha,
                    "lower_bound": "???",
                    "upper_bound": "???",
                    "return_mean_elites": True,
                    "device": device,
                    "clipped_normal": False,
                },
            }
        )
        agent = mbrl.planning.create_trajectory_optim_agent_for_model(
            model_env, agent_cfg, num_particles=planner.particles
        )
        elite_num = int(agent.optimizer.optimizer.elite_num)
        if elite_num != planner.elites:
            raise RuntimeError(f"mbrl-lib CEM keeps {elite_num} elites, expected {planner.elites}")
        agents.append(agent)
    return agents


def train_ensembles(
    obs: torch.Tensor,
    action: torch.Tensor,
    next_obs: torch.Tensor,
    members: int,
    hidden: tuple[int, ...],
    epochs: int,
    batch_size: int,
    lr: float = 1e-3,
    seed: int = 0,
) -> tuple[float, list[float]]:
    """Train one mbrl-lib ``GaussianMLP`` ensemble per agent with its ``ModelTrainer``.

    Same workload as our ``train_ensemble``: per agent ``B`` members, ``epochs`` passes over
    the agent's ``N`` transitions in minibatches of ``batch_size``, a bootstrap resample per
    member (mbrl-lib's ``BootstrapIterator`` with replacement, its PETS default), Gaussian NLL
    with learned log-variance bounds and their 0.01 penalty, Adam ``lr`` without weight decay,
    targets ``next_obs - obs``, inputs normalised (float64 normaliser, fitted on the data).

    Args:
        obs, next_obs: ``[N, I, obs]``; action: ``[N, I, act]``.
        members, hidden, epochs, batch_size, lr: ensemble size, hidden widths, training sizes.
        seed: seeds the iterators and the weight initialisation.

    Returns:
        Seconds for all ``I`` agents (model construction excluded; normaliser fit, iterator
        construction and training included) and each agent's last-epoch mean training loss.
    """
    mbrl = import_mbrl()
    from mbrl.util.replay_buffer import BootstrapIterator

    rows, n_agents, obs_dim = obs.shape
    act_dim = action.shape[-1]
    total, losses = 0.0, []
    for i in range(n_agents):
        torch.manual_seed(seed + i)
        dynamics = _gaussian_dynamics(
            mbrl,
            obs_dim + act_dim,
            obs_dim,
            members,
            tuple(hidden),
            None,
            learn_logvar_bounds=True,
        )
        trainer = mbrl.models.ModelTrainer(dynamics, optim_lr=lr, weight_decay=0.0)
        batch = mbrl.types.TransitionBatch(
            obs[:, i].numpy(),
            action[:, i].numpy(),
            next_obs[:, i].numpy(),
            np.zeros(rows, np.float32),
            np.zeros(rows, bool),
            np.zeros(rows, bool),
        )
        start = time.perf_counter()
        dynamics.update_normalizer(batch)
        iterator = BootstrapIterator(
            batch,
            batch_size,
            members,
            shuffle_each_epoch=True,
            permute_indices=False,
            rng=np.random.default_rng(seed + i),
        )
        train_losses, _ = trainer.train(iterator, num_epochs=epochs, evaluate=False, silent=True)
        total += time.perf_counter() - start
        losses.append(train_losses[-1])
    return total, losses
