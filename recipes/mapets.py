"""MA-PETS: multi-agent probabilistic ensembles with trajectory sampling (Wen et al., Algorithm 1).

Reads top to bottom: config -> env (+ :class:`~mapets_rl.comm.CommunicationRange`) -> per-agent
ensembles -> NLL loss + Adam -> batched CEM planner -> per-agent datasets ``D(i)+`` -> the episode
loop of :meth:`MAPETS.train` (one loop on :meth:`Experiment.training_loop`, one episode per
iteration):

1. episode ``k <= random_episodes`` drives every CAV with uniformly random actions (line 2);
   later episodes let the planner drive all CAVs, each re-planning every step with its own
   ensemble (lines 5-15);
2. at the episode's end every CAV stores its own transitions ``(s, a, s')`` (only steps where it
   was driving, without the crash step and without the steps in which its observed neighbours
   changed identity, ``("agents", "info", "neighbour_changed")``: their gap jumps are not
   dynamics) and sends them to the CAVs within range ``d`` of its last driving position
   (lines 16-17, :meth:`CommunicationRange.episode_graph` + :class:`NeighbourDatasets`; a CAV
   that crashed shares from its crash site);
3. every CAV's ensemble is refit on its ``D(i)+`` (line 4: normaliser refit, ``model.epochs`` passes
   of 128-row minibatches, Adam): one vectorised optimisation over all ``I`` agents and ``B``
   members per minibatch; the per-epoch NLL curve is logged under ``model/nll``;
4. ``loop.end_iteration`` sends the episode's metrics (agility, safety, reward, transitions
   shared, model NLL) to the logger and ``results.json`` and writes a checkpoint atomically.

A run resumes from its latest checkpoint at the next episode (``mapets-rl resume RUN_DIR``, or
``MAPETS.from_run_dir(run_dir).train()``); every random stream is re-seeded from
``(seed, episode)`` or restored, so a resumed run repeats an uninterrupted one.

Usage::

    from mapets_rl.recipes.mapets import MAPETS, MAPETSConfig
    MAPETS(MAPETSConfig(preset="cpu", episodes=5, seed=1)).train()

or ``mapets-rl train mapets --env figure-eight preset=cpu episodes=5 planner.horizon=15``.
"""

from __future__ import annotations

import dataclasses
import logging
import pkgutil
import time
from collections.abc import Callable, Iterable, Mapping
from typing import Any, ClassVar

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import TensorDictModule, TensorDictSequential
from torchrl.objectives import LossModule

from mapets_rl.comm import CommConfig, CommunicationRange, NeighbourDatasets, clique_cover_number
from mapets_rl.config import ConfigError, coerce_section, parse_override
from mapets_rl.envs import (
    FigureEightPlannerReward,
    PlannerReward,
    figure_eight_observation_bounds,
    registered_scenario,
)
from mapets_rl.envs.figure_eight import OBSERVATION_SIZES, neighbour_speed_columns
from mapets_rl.envs.registry import build_env, scenario_defaults
from mapets_rl.experiment import Experiment, RunConfig, check, log_scalars
from mapets_rl.models import EnsembleConfig, ProbabilisticEnsemble
from mapets_rl.modules import (
    AgentGroupSpec,
    TileCodedObservation,
    TileCoder,
    TileCodingConfig,
    action_quantiser,
    masked_mean,
)
from mapets_rl.objectives.ensemble_nll import EnsembleNLLLoss, ensemble_optimizer, fit_ensemble
from mapets_rl.planning import (
    PRESETS,
    PlannerConfig,
    RewardFn,
    TerminationFn,
    TrajectorySamplingCEM,
)
from mapets_rl.planning.memory import available_memory, dataset_bytes, ensemble_bytes
from mapets_rl.planning.shared_plans import PlanSharingPlanner

OBS = ("agents", "observation")
ACTION = ("agents", "action")
MASK = ("agents", "mask")
NEXT_OBS = ("next", "agents", "observation")
NEXT_REWARD = ("next", "agents", "reward")
NEXT_TERMINATED = ("next", "agents", "terminated")
NEXT_NEIGHBOUR_CHANGED = ("next", "agents", "info", "neighbour_changed")
MAX_STEPS = 100_000
"""Safety cap on the steps of one episode (the env truncates at its own horizon first)."""

#: Flat field names of ``config.yaml`` files written before the planner, ensemble,
#: communication and planner-reward settings became nested sections -> their nested names.
#: Reading such a file (resuming an old run, ``MAPETSConfig.from_yaml``) maps them with one
#: warning line; the resumed run's ``config.yaml`` is rewritten nested.
FLAT_FIELDS: dict[str, str] = {
    "horizon": "planner.horizon",
    "population": "planner.population",
    "elites": "planner.elites",
    "iterations": "planner.iterations",
    "particles": "planner.particles",
    "propagation": "planner.propagation",
    "epsilon": "planner.epsilon",
    "cem_momentum": "planner.alpha",
    "ensemble_size": "model.ensemble_size",
    "hidden": "model.hidden",
    "epochs": "model.epochs",
    "batch_size": "model.batch_size",
    "lr": "model.lr",
    "buffer_size": "model.buffer_size",
    "logvar_bound_coef": "model.logvar_bound_coef",
    "share_model": "model.share_model",
    "comm_range": "comm.comm_range",
    "p_fail": "comm.p_fail",
    **{name: f"planner_reward.{name}" for name in FigureEightPlannerReward.field_names()},
}

# the sections whose fields a preset fills when they are not given
_PRESET_SECTIONS = ("planner", "model")
log = logging.getLogger("mapets_rl.recipes.mapets")


@dataclasses.dataclass
class MAPETSConfig(RunConfig):
    """MA-PETS hyper-parameters (plus the shared :class:`RunConfig` fields); defaults are the
    paper's Table II except where noted. One section per concern:

    - ``planner``: :class:`~mapets_rl.planning.PlannerConfig`, the CEM sizes ``w, Q, X, Y, P``
      and propagation (``planner.horizon=25``);
    - ``model``: :class:`~mapets_rl.models.EnsembleConfig`, the ensembles' sizes and training
      (``model.hidden=[64,64]``, ``model.epochs=30``);
    - ``comm``: :class:`~mapets_rl.comm.CommConfig`, range-limited sharing
      (``comm.comm_range=inf``);
    - ``tile_coding``: :class:`~mapets_rl.modules.TileCodingConfig`, the paper's discretised
      variant (``tile_coding.tilings=4``; off by default).

    ``preset`` picks the sizes: the ``planner`` and ``model`` fields not given (a section passed
    as a mapping, e.g. ``planner={"horizon": 15}``, or a dotted override) come from it:

    - ``"paper"`` (Table II): ``w=25, Q=400, X=40, Y=5, P=20, B=5``, 3x300 hidden units, 5
      training epochs. About 0.37 TFLOP per agent and decision: a GPU workload.
    - ``"cpu"``: ``w=25, Q=8, X=4, Y=2, P=5, B=5``, 3x64 hidden units
      (:data:`mapets_rl.planning.CPU_PRESET`): the paper's horizon (a CAV must see 2.3 s ahead
      to brake from top speed), a narrower CEM with iCEM's anchor candidates and keep-best
      (:class:`~mapets_rl.planning.ICEMOptimizer`), each rollout step compiled, 30 training
      epochs.

    A field set explicitly wins over the preset (``preset=cpu planner.horizon=15``); a section
    passed as a :class:`PlannerConfig` / :class:`EnsembleConfig` instance is taken whole. The
    resolved values are what ``config.yaml`` records. A ``config.yaml`` with the flat names of
    earlier versions (``horizon``, ``hidden``, ``comm_range``, ...) is read through
    :data:`FLAT_FIELDS`.

    Attributes:
        episodes: ``K``, episodes to train for (paper: 15). ``train()`` continues a resumed
            run up to this number.
        random_episodes: leading episodes driven by uniformly random actions (paper: 1).
        preset: ``"paper"`` or ``"cpu"``, see above.
        planner: the CEM planner section (propagation ``"ts_inf"`` needs ``planner.particles``
            to be a multiple of ``model.ensemble_size``).
        model: the ensemble section (``epochs``: paper preset 5, the paper's; cpu preset 30,
            where 5 passes are 40-80 gradient steps that leave the model underestimating fast
            closing and the training NLL flattens by ~30).
        comm: the communication section (``comm_range`` ``d``, paper: 100; ``p_fail``).
        tile_coding: the discretised variant (paper sec. VI, its check of the tabular
            Assumption 1): with ``tilings >= 1`` the CAVs observe tile-coded observations
            (every feature one of ``bins * tilings`` values, :class:`TileCodedObservation`)
            and act on a grid (every action dimension one of ``action_bins * tilings``
            values, random episodes included); datasets, models and the planner's start
            states are discrete, the CEM still searches continuous action sequences and the
            model's predictions stay continuous. The figure-eight's feature bounds come
            from :func:`~mapets_rl.envs.figure_eight_observation_bounds`; other scenarios
            give ``tile_coding.obs_low`` / ``obs_high``.
        planner_reward: the scenario's planner-reward settings, the config section its
            registry entry declares (:class:`~mapets_rl.envs.FigureEightPlannerReward` on the
            figure-eights: ``planner_reward.headway=0.5``, ``planner_reward.collision_gap=2``,
            ...; a mapping fills the fields it gives, the rest keep the section's defaults);
            None for a scenario without one (it needs ``reward_fn``).
        reward_fn: ``"package.module:function"``, a planner reward ``(obs [..., S], action
            [..., A], next_obs [..., S]) -> [...]`` imported when the config is built (a
            ConfigError names ``reward_fn`` if it cannot be imported or is not callable); it
            replaces the scenario's (then ``planner_reward`` must keep its defaults) and gives
            a scenario without one its reward from the shell
            (``mapets-rl train mapets --env my-road reward_fn=my_pkg.rewards:speed``).
            Planned trajectories never terminate with it. Empty: the scenario's own.
        num_threads: torch intra-op threads (0: chosen by the machine's load, one thread on
            a busy machine; see :mod:`mapets_rl.threads`).

    MA-PETS has no frame budget (``total_frames``, ``frames_per_batch``, ``num_envs``,
    ``eval_interval``, ``checkpoint_interval`` are unknown keys; resuming a run whose
    ``config.yaml`` still holds them drops them): it plans on one env, trains for ``episodes``
    and checkpoints after every episode.
    """

    episodes: int = dataclasses.field(default=15, metadata={"unit": "episodes"})
    random_episodes: int = dataclasses.field(default=1, metadata={"unit": "episodes"})
    preset: str = "paper"
    planner: PlannerConfig | None = None
    model: EnsembleConfig | None = None
    comm: CommConfig = dataclasses.field(default_factory=CommConfig)
    tile_coding: TileCodingConfig = dataclasses.field(default_factory=TileCodingConfig)
    planner_reward: PlannerReward | None = None
    reward_fn: str = ""
    num_threads: int = 0

    # the frame-budget fields that MAPETSConfig inherited until it subclassed RunConfig
    retired_fields: ClassVar[tuple[str, ...]] = (
        "total_frames",
        "frames_per_batch",
        "num_envs",
        "eval_interval",
        "checkpoint_interval",
    )

    def __post_init__(self) -> None:
        check(
            isinstance(self.preset, str) and self.preset in PRESETS,
            "preset",
            f"one of {sorted(PRESETS)}",
            self.preset,
        )
        preset = PRESETS[self.preset]
        # the preset fills the section fields not given (a section instance is taken whole)
        for name in _PRESET_SECTIONS:
            given = getattr(self, name)
            if given is None:
                setattr(self, name, getattr(preset, name))
            elif isinstance(given, Mapping):
                setattr(self, name, {**getattr(preset, name).to_dict(), **given})
        self.planner_reward = scenario_planner_reward(self.env, self.planner_reward)
        super().__post_init__()
        check(self.episodes >= 1, "episodes", ">= 1", self.episodes)
        check(self.random_episodes >= 0, "random_episodes", ">= 0", self.random_episodes)
        plan = self.planner
        layout = plan.layout_error(self.model.ensemble_size)
        if layout is not None:  # before the run directory exists
            raise ConfigError(f"planner.{layout} (model.ensemble_size)")
        check(
            not plan.cuda_graph or self.device.startswith("cuda"),
            "planner.cuda_graph",
            f"False with device={self.device!r} (CUDA graphs need a CUDA device)",
            plan.cuda_graph,
        )
        if self.reward_fn:
            self.imported_reward_fn()
        check(self.num_threads >= 0, "num_threads", ">= 0", self.num_threads)

    def imported_reward_fn(self) -> RewardFn:
        """The function :attr:`reward_fn` names (``"package.module:function"``), imported;
        ConfigError naming ``reward_fn`` when it cannot be imported or is not callable."""
        allowed = "'package.module:function', an importable callable (obs, action, next_obs)"
        try:
            function = pkgutil.resolve_name(self.reward_fn)
        except (ImportError, AttributeError, ValueError) as err:
            raise ConfigError(
                f"reward_fn must be {allowed}, got {self.reward_fn!r} ({type(err).__name__}: {err})"
            ) from None
        if not callable(function):
            raise ConfigError(
                f"reward_fn must be {allowed}, got {self.reward_fn!r} (a "
                f"{type(function).__name__}, not callable)"
            )
        return function

    @classmethod
    def upgrade_dict(cls, data: Mapping[str, Any]) -> dict[str, Any]:
        """Drop the retired frame-budget keys and map the flat names of :data:`FLAT_FIELDS` to
        their sections (one warning line); a nested value given too wins. The flat
        planner-reward keys of a scenario without a planner reward (the defaults that a given
        ``reward_fn`` left unused) are dropped. A planner section written before
        ``planner.optimizer`` existed names the optimiser its iCEM fields chose
        (:meth:`PlannerConfig.upgrade_dict`)."""
        data = super().upgrade_dict(data)
        if _reward_section(data.get("env", cls.env)) is None:
            data = {
                k: v for k, v in data.items() if k not in FigureEightPlannerReward.field_names()
            }
        flat = [k for k in data if k in FLAT_FIELDS]
        if not flat:
            return _upgrade_planner(data)
        log.warning(
            "config written with the flat MA-PETS field names %s; read as %s",
            ", ".join(flat),
            ", ".join(FLAT_FIELDS[k] for k in flat),
        )
        out = {k: v for k, v in data.items() if k not in FLAT_FIELDS}
        for key in flat:
            section, leaf = FLAT_FIELDS[key].split(".")
            nested = out.get(section)
            nested = dict(nested) if isinstance(nested, Mapping) else {}
            nested.setdefault(leaf, data[key])
            out[section] = nested
        return _upgrade_planner(out)

    def with_overrides(self, overrides: Iterable[str]) -> MAPETSConfig:
        """``key=value`` overrides (dotted for the sections, ``planner.horizon=15``);
        ``preset=NAME`` re-fills the ``planner`` / ``model`` fields that still hold the current
        preset's values (fields set explicitly, here or earlier, are kept); ``env=NAME`` of a
        scenario with another planner-reward section (or none) starts ``planner_reward`` from
        that scenario's (the ``planner_reward.*`` overrides given with it apply on top)."""
        overrides = list(overrides)
        given = dict(parse_override(o) for o in overrides)  # values as YAML: preset="cpu" is cpu
        new = given.get("preset", self.preset)
        data = self.to_dict()
        if "env" in given and _reward_section(given["env"]) is not _reward_section(self.env):
            data["planner_reward"] = None
        if new != self.preset and new in PRESETS:
            old = PRESETS[self.preset]
            for name in _PRESET_SECTIONS:
                defaults = getattr(old, name).to_dict()
                data[name] = {k: v for k, v in data[name].items() if v != defaults[k]}
        return type(self).from_dict(self._apply_overrides(data, overrides))


def _upgrade_planner(data: dict[str, Any]) -> dict[str, Any]:
    """``data`` with its planner section, when it is a mapping, upgraded by
    :meth:`PlannerConfig.upgrade_dict`."""
    if isinstance(data.get("planner"), Mapping):
        data["planner"] = PlannerConfig.upgrade_dict(data["planner"])
    return data


def _reward_section(env: str) -> type[PlannerReward] | None:
    """The planner-reward section class scenario ``env`` registers (None: it has none)."""
    scenario = registered_scenario(env)
    return None if scenario is None else scenario.planner_reward


def scenario_planner_reward(
    env: str, given: PlannerReward | Mapping[str, Any] | None
) -> PlannerReward | None:
    """The ``planner_reward`` section of scenario ``env``: ``given`` as an instance of the
    section class the scenario registers (a mapping fills the fields it names, None gives the
    defaults); None for a scenario without one (ConfigError if settings were given)."""
    section = _reward_section(env)
    if section is None:
        check(
            given is None,
            "planner_reward",
            f"left out for env {env!r}, whose scenario registers no planner reward (give "
            "reward_fn=package.module:function instead)",
            given,
        )
        return None
    if given is None:
        return section()
    if isinstance(given, PlannerReward) and not isinstance(given, section):
        raise ConfigError(
            f"planner_reward must be a {section.__name__} for env {env!r}, got "
            f"{type(given).__name__}"
        )
    return coerce_section(given, section, "planner_reward")


class _Counters:
    """The episode counter as a checkpoint component."""

    def __init__(self) -> None:
        self.episode = 0

    def state_dict(self) -> dict[str, int]:
        return {"episode": self.episode}

    def load_state_dict(self, state: Mapping[str, int]) -> None:
        self.episode = int(state["episode"])


class MAPETS(Experiment):
    """Decentralised model-based MARL with range-limited data sharing (MA-PETS, Algorithm 1).

    Args:
        config: a :class:`MAPETSConfig`.
        run_dir: run directory (default ``runs/mapets_<env>_seed<N>_<time>``).
        reward_fn: the known reward the planner maximises, ``(obs [..., S], action [..., A],
            next_obs [..., S]) -> [...]``; default: ``config.reward_fn`` when it names one,
            else the scenario's planner reward with the config's settings
            (``config.planner_reward.reward``; the figure-eight scenarios':
            :class:`~mapets_rl.envs.FigureEightPlannerReward`, paper eq. 26 with a
            predicted-collision penalty); a scenario without one (the freeways, a
            ``register_env`` scenario) needs ``reward_fn`` (here or in the config).
        termination_fn: the known termination of a planned trajectory, ``(obs, action,
            next_obs) -> [...]`` bool; default (with the scenario's reward only) the
            scenario's (``config.planner_reward.termination_fn``, the figure-eight's predicted
            collision); ``None`` with a custom ``reward_fn`` means trajectories never
            terminate.

    Attributes:
        env: the env with the :class:`CommunicationRange` transform appended.
        comm: that transform (range ``config.comm.comm_range``).
        model: the CAVs' :class:`ProbabilisticEnsemble` ``(I agents x B members)``.
        loss: :class:`EnsembleNLLLoss` on the dataset keys ``observation``, ``action``,
            ``next_observation``, ``mask``.
        planner: :class:`TrajectorySamplingCEM` over all CAVs at once (also ``eval_policy``).
        datasets: :class:`NeighbourDatasets`, every CAV's ``D(i)+``.
        episode: episodes completed.
    """

    name = "mapets"
    Config = MAPETSConfig
    action_kinds = ("continuous",)
    action_kinds_reason = "the CEM planner optimises real-valued action sequences"
    progress_unit = "episode"
    # a resume may also extend the episode budget and change the torch threads
    resumable_fields = Experiment.resumable_fields | {"episodes", "num_threads"}

    def __init__(
        self,
        config: MAPETSConfig,
        run_dir: Any = None,
        reward_fn: RewardFn | None = None,
        termination_fn: TerminationFn | None = None,
    ) -> None:
        if not isinstance(config, MAPETSConfig):
            raise ValueError(f"config must be a MAPETSConfig, got {type(config).__name__}")
        if config.num_threads > 0:
            torch.set_num_threads(config.num_threads)
        # the scenario with the communication-range transform appended
        self.comm = CommunicationRange(config.comm.comm_range, config.comm.p_fail)
        env = build_env(config.env, config.env_config).append_transform(self.comm)
        group = AgentGroupSpec.from_env(env)
        try:  # refusals before the run directory is written
            self.refuse_action_kind(env, config.env)
            self._check_scenario(config, group, reward_fn)
            shared = ("agents", "info", "neighbour_cav")
            if config.comm.share_plans and (
                shared not in env.observation_spec.keys(True, True)
                or group.obs_dim not in OBSERVATION_SIZES
            ):
                raise ValueError(
                    "comm.share_plans=true needs a scenario that says which CAV each observed "
                    "vehicle is (per-agent info 'neighbour_cav', as the figure-eight scenarios "
                    f"report), and env {config.env!r} does not"
                )
        except ValueError:
            env.close()
            raise
        super().__init__(config, run_dir, env)
        bounds = group.action_spec.space
        self.obs_coder, self.action_coder = self._tile_coders(group, bounds.low, bounds.high)
        for transform in self.observation_transforms():
            self.env.append_transform(transform)
        if reward_fn is None and config.reward_fn:
            reward_fn = config.imported_reward_fn()
        elif reward_fn is None:  # the scenario's own (checked above), with the config's settings
            reward_fn = config.planner_reward.reward
            if termination_fn is None:
                termination_fn = config.planner_reward.termination_fn
        self.reward_fn = reward_fn
        self.termination_fn = termination_fn
        self.n_agents = n = group.n_agents
        device = self.device

        # per-CAV probabilistic ensembles + Gaussian NLL (eq. 9) + Adam
        self.model = ProbabilisticEnsemble(
            group.obs_dim,
            group.action_dim,
            n,
            **config.model.model_kwargs(),
        ).to(device)
        self.bootstrap_generator = torch.Generator(device=device)
        self.loss = self.make_loss(self.model)
        self.optimizer = ensemble_optimizer(self.loss, lr=config.model.lr)
        self.shuffle_generator = torch.Generator(device=device)

        # batched CEM planner with trajectory sampling over every CAV's ensemble
        self.plan_generator = torch.Generator(device=device)
        self.planner = TrajectorySamplingCEM(
            self.model,
            self.reward_fn,
            bounds.low.to(device),
            bounds.high.to(device),
            config.planner,
            generator=self.plan_generator,
            termination_fn=self.termination_fn,
        )
        log.info("planner compute dtype: %s", self.planner.dtype_reason)
        # the scenario overrules the plan where no plan can tell (a sharing CAV broadcasts it)
        fallback = None if config.planner_reward is None else config.planner_reward.fallback
        self.plan_sharing = (
            PlanSharingPlanner(
                self.planner, neighbour_speed_columns(group.obs_dim), fallback=fallback
            )
            if config.comm.share_plans
            else None
        )
        decide = self.planner if self.plan_sharing is None else self.plan_sharing
        if fallback is not None and self.plan_sharing is None:
            action_key = self.planner.out_keys[0]
            decide = TensorDictSequential(
                decide,
                TensorDictModule(
                    fallback, in_keys=[self.planner.in_keys[0], action_key], out_keys=[action_key]
                ),
            )
        self.policy = (
            decide
            if self.action_coder is None
            else TensorDictSequential(decide, action_quantiser(self.action_coder))
        )
        self.eval_policy = self.policy

        # D(i)+ of every CAV over one shared storage
        self.datasets = NeighbourDatasets(
            n, config.model.buffer_size, device=device, seed=config.seed
        )
        self.counters = _Counters()

    def _tile_coders(
        self, group: AgentGroupSpec, action_low: torch.Tensor, action_high: torch.Tensor
    ) -> tuple[TileCoder | None, TileCoder | None]:
        """The observations' and the actions' :class:`TileCoder` (``action_low`` /
        ``action_high`` ``[I, A]``, one row per CAV), ``(None, None)`` when the discretised
        variant is off."""
        tc = self.config.tile_coding
        if not tc.enabled:
            return None, None
        if tc.obs_low is not None:
            low, high = tc.obs_low, tc.obs_high
        elif group.obs_dim in OBSERVATION_SIZES:
            # the scenario's own defaults (two lanes for figure-eight-multilane), then the user's
            scenario = scenario_defaults(self.config.env)
            low, high = figure_eight_observation_bounds({**scenario, **self.config.env_config})
        else:
            raise ValueError(
                f"tile_coding.obs_low and tile_coding.obs_high are required for env "
                f"{self.config.env!r}: the default bounds are the figure-eight's (observation "
                f"sizes {list(OBSERVATION_SIZES)}), got {group.obs_dim} features"
            )
        check(
            len(low) == group.obs_dim,
            "tile_coding.obs_low",
            f"{group.obs_dim} bounds (one per observation feature)",
            len(low),
        )
        obs_coder = TileCoder(low, high, tc.bins, tc.tilings).to(self.device)
        action_coder = TileCoder(action_low[0], action_high[0], tc.action_bins, tc.tilings)
        return obs_coder, action_coder.to(self.device)

    @property
    def episode(self) -> int:
        return self.counters.episode

    @staticmethod
    def _check_scenario(
        config: MAPETSConfig, group: AgentGroupSpec, reward_fn: RewardFn | None
    ) -> None:
        """ValueError (one line) when the scenario's observation or size do not fit MA-PETS
        with ``config``: a ``reward_fn`` given twice (argument and
        ``config.reward_fn``) or while ``config.planner_reward`` leaves its defaults, no
        ``reward_fn`` for a scenario without a planner reward, or a planner / ensemble larger
        than the memory the device has available (:mod:`mapets_rl.planning.memory`)."""
        if reward_fn is not None and config.reward_fn:
            raise ValueError(
                f"reward_fn is given twice, reward_fn={config.reward_fn!r} in the config and "
                "MAPETS(config, reward_fn=...): give one"
            )
        section = config.planner_reward
        if (reward_fn is not None or config.reward_fn) and section is not None:
            changed = next(
                (k for k, v in section.to_dict().items() if v != getattr(type(section)(), k)),
                None,
            )
            if changed is not None:  # the scenario reward's settings would be ignored
                raise ValueError(
                    f"planner_reward.{changed}={getattr(section, changed)!r} configures the "
                    "scenario's planner reward, which a given reward_fn replaces: leave "
                    "planner_reward at its defaults"
                )
        if reward_fn is None and not config.reward_fn and section is None:
            raise ValueError(
                f"reward_fn is required for env {config.env!r}: the scenario supplies no "
                "planner reward (the figure-eight scenarios supply theirs); give "
                "reward_fn=package.module:function in the config, or "
                "MAPETS(config, reward_fn=..., termination_fn=...)"
            )
        planner, model = config.planner, config.model
        dims = (group.n_agents, group.obs_dim, group.action_dim)
        need = (
            planner.decision_bytes(*dims, model.hidden)
            + ensemble_bytes(*dims, model.hidden, model.ensemble_size)
            + dataset_bytes(*dims, model.buffer_size)
        )
        free = available_memory(config.device)
        if free is not None and need > free:
            raise ValueError(
                f"the planner, ensembles and datasets need about {need / 2**30:.1f} GiB on "
                f"{config.device} ({group.n_agents} agents x planner.population="
                f"{planner.population} x planner.particles={planner.particles}, model.hidden="
                f"{list(model.hidden)}, model.buffer_size={model.buffer_size}), more than the "
                f"{free / 2**30:.1f} GiB available: lower planner.population, "
                "planner.particles, model.hidden or model.buffer_size"
            )

    def make_loss(self, model: ProbabilisticEnsemble) -> LossModule:
        """The loss that fits the ensembles (Algorithm 1 line 4): the Gaussian NLL of eq. 9
        with the PETS log-variance bound penalty, each member on its own bootstrap resample.

        Override it to fit them with another loss: any torchrl ``LossModule`` that holds
        ``model`` as ``.model`` and whose ``forward`` reads a batch ``[n]`` of the ``"agents"``
        keys (``("agents", "observation")``, ``("agents", "action")``,
        ``("next", "agents", "observation")`` ``[n, I, *]`` and ``("agents", "mask")``
        ``[n, I]``, ``False`` on padding) and returns ``loss_*`` scalars (their sum is
        minimised by Adam) and optionally ``nll_per_member`` ``[I, B]`` (logged as
        ``model_nll``). The optimiser is built over its parameters.
        """
        return EnsembleNLLLoss(
            model,
            logvar_bound_coef=self.config.model.logvar_bound_coef,
            generator=self.bootstrap_generator,
        )

    def stateful_components(self) -> dict[str, Any]:
        return {
            "model": self.model,
            "optimizer": self.optimizer,
            "datasets": self.datasets,
            "counters": self.counters,
        }

    # ------------------------------------------------------------------ the loop
    def progress(self) -> tuple[int, int]:
        """``(episodes done, config.episodes)``: the loop of :meth:`train` runs while more are
        due (and a resume that asks for fewer episodes than were done is refused)."""
        return self.episode, self.config.episodes

    def train(
        self, on_episode_end: Callable[[dict[str, float]], None] | None = None
    ) -> list[dict[str, Any]]:
        """Algorithm 1: train (or continue) up to ``config.episodes`` episodes.

        Each episode is drawn from its own seeds (so a resumed run continues as an
        uninterrupted one), driven by the planner (or with random actions for the first
        ``random_episodes``), stored in every CAV's ``D(i)+`` and shared within ``d``; then
        every CAV's ensemble is refitted for the next episode. ``loop.end_iteration`` then
        sends the episode's metrics to ``results.json`` (training entries), the logger and
        ``on_episode_end``, and writes a checkpoint (after every episode).

        Returns:
            the run's per-episode entries ``{"frames", "metrics"}`` (as in ``results.json``).
        """
        cfg = self.config
        with self.training_loop(
            on_episode_end,
            eval_interval=None,
            checkpoint_interval=1,
            train_entries=True,
            label=f"{self.name} {cfg.env} d={cfg.comm.comm_range:g} seed {cfg.seed}",
            postfix=lambda m, fps: {k: f"{m[k]:.3g}" for k in ("agility", "safety") if k in m},
        ) as loop:
            while not loop.finished:
                episode = self.episode + 1
                self._seed_episode(episode)
                random_actions = episode <= cfg.random_episodes
                start = time.perf_counter()
                rollout = self.run_episode(random_actions)  # lines 5-15: act, observe
                act_time = time.perf_counter() - start
                metrics = {"episode": float(episode), "random": float(random_actions)}
                metrics.update(self.episode_metrics(rollout))
                metrics["nonfinite_rewards"] = float(self.planner.nonfinite_rewards.sum())
                metrics.update(self.plan_sharing_metrics(random_actions))
                metrics.update(self.store_and_share(rollout))  # lines 16-17: D(i)+, share
                start = time.perf_counter()
                metrics.update(self.train_models())  # line 4: refit every ensemble
                metrics["train_time"] = time.perf_counter() - start
                metrics["step_time"] = act_time / rollout.shape[0]
                self.frames += rollout.shape[0]
                self.counters.episode = episode
                loop.end_iteration(metrics)
        return self.results.train

    def plan_sharing_metrics(self, random_actions: bool) -> dict[str, float]:
        """Per step of the episode just driven, with ``comm.share_plans``: plans broadcast
        (``plan_messages``), their bytes (``plan_bytes``) and neighbour slots filled from a
        received plan (``plans_used``); empty otherwise (random episodes send none)."""
        sharing = self.plan_sharing
        if sharing is None:
            return {}
        steps = max(sharing.steps, 1) if not random_actions else 1
        messages = 0 if random_actions else sharing.broadcasts
        return {
            "plan_messages": messages / steps,
            "plan_bytes": messages * sharing.bytes_per_broadcast / steps,
            "plans_used": (0 if random_actions else sharing.plans_used) / steps,
        }

    def _seed_episode(self, episode: int) -> None:
        """Seed the env and every private random stream from ``(seed, episode)``."""
        # reduced below 2**62 so that every stream's seed fits a signed 64-bit integer
        base = (self.config.seed * 1_000_003 + episode * 7_919) % (1 << 62)
        self.env.set_seed(base)
        self.comm.set_seed(base + 1)
        self.plan_generator.manual_seed(base + 2)
        self.bootstrap_generator.manual_seed(base + 3)
        self.shuffle_generator.manual_seed(base + 4)

    def run_episode(self, random_actions: bool) -> TensorDictBase:
        """One episode until every CAV is done: ``[T]`` rollout (random or planned actions)."""
        self.on_evaluation_episode_start()
        if self.plan_sharing is not None:
            self.plan_sharing.reset_counts()
        self.planner.nonfinite_rewards.zero_()
        policy = self.policy
        if random_actions:
            policy = None if self.action_coder is None else self._random_on_grid
        with torch.no_grad():
            return self.env.rollout(
                MAX_STEPS, policy=policy, break_when_any_done=True, auto_cast_to_device=True
            )

    def _random_on_grid(self, tensordict: TensorDictBase) -> TensorDictBase:
        """Uniformly random actions snapped to the tile-coded action grid."""
        tensordict = self.env.rand_action(tensordict)
        action = tensordict.get(ACTION)
        return tensordict.set(ACTION, self.action_coder.quantise(action))

    def store_and_share(self, rollout: TensorDictBase) -> dict[str, float]:
        """Add every CAV's transitions of ``rollout`` to its ``D(i)+`` and exchange them with
        the CAVs within range at the episode's end (Algorithm 1 lines 16-17); the metrics
        include the minimum clique cover number of that exchange graph (``chi_bar(G_{d,k})``,
        paper Fig. 7; exact up to 32-node components, a greedy bound beyond).

        A CAV's transition of step ``t`` is kept when it was driving (``("agents", "mask")``),
        did not crash in that step (its next observation is then zeroed by the env) and its
        observed neighbours kept their identity (``neighbour_changed``, when the env reports
        it): a new leader makes the gap jump by up to 75 m, which inflates the model's
        normalisation and predicted noise although no dynamics caused it.
        """
        keep = rollout.get(MASK) & ~rollout.get(NEXT_TERMINATED).squeeze(-1)  # [T, I]
        changed = rollout.get(NEXT_NEIGHBOUR_CHANGED, None)
        driving = int(keep.sum())
        if changed is not None:
            keep = keep & ~changed.to(torch.bool)
        transitions = TensorDict(
            {
                "observation": rollout.get(OBS),
                "action": rollout.get(ACTION),
                "next_observation": rollout.get(NEXT_OBS),
            },
            batch_size=keep.shape,
        )
        self.datasets.add(transitions, mask=keep)
        graph = self.comm.episode_graph(rollout)
        stats = self.datasets.exchange(graph)
        return {
            "clique_cover_number": float(clique_cover_number(graph)),
            "transitions_stored": float(keep.sum()),
            "transitions_filtered": float(driving - int(keep.sum())),
            "transitions_shared": float(stats.transitions),
            "bytes_shared": float(stats.bytes),
            "dataset_size": self.datasets.sizes.float().mean().item(),
        }

    def train_models(self) -> dict[str, float]:
        """Refit every CAV's ensemble on its ``D(i)+`` (Algorithm 1 line 4).

        The datasets are laid out as one padded batch ``[N, I]`` (``N`` = the largest
        ``|D(i)+|``; ``mask`` is ``False`` on the padding of smaller datasets), so each
        minibatch trains all ``I x B`` members in one forward/backward. With
        ``model.holdout > 0`` the refit stops early on the held-out NLL
        (:func:`~mapets_rl.objectives.fit_ensemble`); ``model_epochs`` is how many epochs ran
        and ``model_holdout_nll`` the held-out NLL of the kept weights.
        """
        sizes = self.datasets.sizes
        if bool((sizes == 0).any()):
            return {}
        rows = int(sizes.max())
        # one shuffled pass: row j < |D(i)+| of agent i is a distinct transition of D(i)+
        flat = next(iter(self.datasets.iter_epoch(rows))).transpose(0, 1)  # [N, I]
        mask = torch.arange(rows, device=sizes.device)[:, None] < sizes[None, :]
        data = TensorDict(  # the "agents" layout every loss reads, entries [N, I, *]
            {
                OBS: flat["observation"],
                ACTION: flat["action"],
                NEXT_OBS: flat["next_observation"],
                MASK: mask,
            },
            batch_size=[rows],
        )
        model = self.config.model
        fit = fit_ensemble(
            self.loss,
            self.optimizer,
            data,
            epochs=model.epochs,
            batch_size=model.batch_size,
            generator=self.shuffle_generator,
            holdout=model.holdout,
            patience=model.patience,
            min_improvement=model.min_improvement,
        )
        curve = fit.train_nll.mean(dim=(1, 2))  # [epochs run]
        first = self.episode * model.epochs  # the episode's epoch steps (fewer when stopped)
        for epoch, nll in enumerate(curve.tolist()):
            log_scalars(self.logger, "model", {"nll": nll}, first + epoch + 1)
        metrics = {
            "model_nll_first_epoch": curve[0].item(),
            "model_nll": curve[-1].item(),
            "model_epochs": float(fit.epochs),
        }
        if fit.final_holdout_nll is not None:  # early stopping: the kept weights' held-out NLL
            metrics["model_holdout_nll"] = fit.final_holdout_nll.nanmean().item()
        return metrics

    def episode_metrics(self, rollout: TensorDictBase) -> dict[str, float]:
        """Runner metrics (reward, return, length, agility, safety, collisions, mean speed)."""
        out = super().episode_metrics(rollout)
        out["reward"] = masked_mean(rollout.get(NEXT_REWARD), rollout.get(MASK))
        return out

    # ------------------------------------------------------------------ evaluation
    def observation_transforms(self) -> list[Any]:
        """The tile-coded observation of the discretised variant (also on the video env)."""
        if self.obs_coder is None:
            return []
        return [TileCodedObservation(self.obs_coder, in_keys=[OBS])]

    def on_evaluation_episode_start(self) -> None:
        """Each episode (evaluated or trained) plans from a cold start: no warm start, no
        plans received."""
        self.planner.reset()
        if self.plan_sharing is not None:
            self.plan_sharing.reset()
