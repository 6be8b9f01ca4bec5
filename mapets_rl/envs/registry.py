"""The scenario registry: every scenario name the library knows, and how to build it.

One registry serves the library, the recipes and the CLI:

- the built-in traffic scenarios register themselves when :mod:`mapets_rl.envs` is imported
  (:mod:`mapets_rl.envs.factory`, each with its PettingZoo env class, what it changes from that
  class's defaults and its gymnasium id; ``mapets_rl.envs.GYM_IDS`` is derived from them);
- :func:`register_env` adds a scenario to this process (re-exported by
  :mod:`mapets_rl.experiment`);
- installed packages declare scenarios in the entry-point group ``mapets_rl.scenarios``
  (``my-road = "mypackage.roads:make_my_road"``), found when a name is looked up; a name
  registered in this process (built-in or :func:`register_env`) wins over an installed one.

:func:`build_env` builds a scenario by name (``factory(**env_config)``), :func:`available_envs`
lists the names and :func:`scenario_defaults` gives the config a scenario runs with when its
``env_config`` leaves a key unset.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import TYPE_CHECKING, Any

from mapets_rl._entry_points import check_name, entry_points, load_entry_point

if TYPE_CHECKING:
    from pettingzoo import ParallelEnv
    from torchrl.envs import EnvBase

    from mapets_rl.envs.planner_reward import PlannerReward

SCENARIO_GROUP = "mapets_rl.scenarios"
"""Entry-point group of the scenarios that installed packages provide."""


@dataclass(frozen=True)
class Scenario:
    """A scenario registered in this process.

    Attributes:
        factory: ``factory(**env_config)`` returns the scenario's TorchRL env (the multi-agent
            ``"agents"`` layout).
        parallel_env: the PettingZoo env class of a built-in traffic scenario; None for a
            scenario registered with :func:`register_env`.
        changes: what a built-in scenario changes from its env class's defaults.
        gym_id: gymnasium id of a built-in scenario's raw (array-valued) highway-env env.
        planner_reward: the scenario's planner-reward settings, a
            :class:`~mapets_rl.envs.PlannerReward` config section class whose instances give
            the known reward (and termination) a model-based planner (MA-PETS) scores the
            scenario's predicted trajectories with (the figure-eight's:
            :class:`~mapets_rl.envs.FigureEightPlannerReward`); its fields are declared there,
            once, and MA-PETS' config holds an instance as its ``planner_reward`` section.
            None where the scenario has none (MA-PETS then needs a ``reward_fn``).
    """

    factory: Callable[..., EnvBase]
    parallel_env: type[ParallelEnv] | None = None
    changes: Mapping[str, Any] = field(default_factory=lambda: MappingProxyType({}))
    gym_id: str | None = None
    planner_reward: type[PlannerReward] | None = None

    @property
    def builtin(self) -> bool:
        """Whether the scenario is one of the package's own (registered by
        :func:`register_builtin`)."""
        return self.parallel_env is not None


_SCENARIOS: dict[str, Scenario] = {}
"""Scenario name -> the scenario registered in this process (built-in or ``register_env``)."""


def register_builtin(
    name: str,
    factory: Callable[..., EnvBase],
    parallel_env: type[ParallelEnv],
    gym_id: str,
    changes: Mapping[str, Any] | None = None,
    planner_reward: type[PlannerReward] | None = None,
) -> None:
    """Register one of the package's own traffic scenarios (``mapets_rl.envs.factory`` does on
    import): ``factory(**env_config)`` builds it, ``parallel_env`` is its PettingZoo env class,
    ``changes`` what the scenario changes from that class's defaults, ``gym_id`` its
    gymnasium id and ``planner_reward`` the section of settings of what a planner scores its
    trajectories with (see :class:`Scenario`). A name registered before raises ValueError."""
    check_name(name, "scenario")
    if name in _SCENARIOS:
        raise ValueError(f"scenario {name!r} is already registered")
    _SCENARIOS[name] = Scenario(
        factory,
        parallel_env,
        MappingProxyType(dict(changes or {})),
        gym_id,
        planner_reward,
    )


def register_env(name: str, factory: Callable[..., EnvBase], overwrite: bool = False) -> None:
    """Make scenario ``name`` available to every recipe and the CLI in this process:
    ``factory(**env_config)`` returns a torchrl EnvBase with the multi-agent ``"agents"``
    layout. (A package makes a scenario available to every process, ``mapets-rl resume``
    included, with an entry point in the group ``mapets_rl.scenarios``.)

    Registering a name that already exists (a built-in scenario, an installed one, or another
    factory under the same name) raises ValueError unless ``overwrite=True``; registering the
    same factory again is a no-op. ``name`` must be a non-empty string without path
    separators, ``..`` or control characters (it becomes part of the default run directory's
    name); ValueError otherwise.
    """
    check_name(name, "scenario")
    if not callable(factory):
        raise ValueError(
            f"factory must be callable (factory(**env_config) -> EnvBase), got "
            f"{type(factory).__name__} {factory!r}"
        )
    existing = _SCENARIOS.get(name)
    if existing is not None and existing.factory is factory:
        return
    if not overwrite:
        kind = (
            "a built-in scenario"
            if existing is not None and existing.builtin
            else "already registered"
            if existing is not None
            else "an installed scenario (entry point)"
            if name in _installed_envs()
            else None
        )
        if kind is not None:
            raise ValueError(
                f"scenario {name!r} is {kind}; pass overwrite=True to replace it "
                "or choose another name"
            )
    _SCENARIOS[name] = Scenario(factory)


def registered_scenario(name: str) -> Scenario | None:
    """The scenario registered in this process under ``name`` (built-in or
    :func:`register_env`); None for an installed scenario (loaded only when it is built) and
    for an unknown name."""
    return _SCENARIOS.get(name)


def builtin_envs() -> list[str]:
    """Names of the built-in scenarios (not replaced by :func:`register_env`), sorted."""
    return sorted(name for name, scenario in _SCENARIOS.items() if scenario.builtin)


def _installed_envs() -> tuple[str, ...]:
    """Scenario names of the entry-point group ``mapets_rl.scenarios``."""
    return tuple(entry_points(SCENARIO_GROUP))


def available_envs() -> list[str]:
    """Scenario names: the built-in ones, those registered in this process and those installed
    packages declare in the entry-point group ``mapets_rl.scenarios``, sorted."""
    return sorted(set(_SCENARIOS) | set(_installed_envs()))


def build_env(name: str, env_config: Mapping[str, Any] | None = None) -> EnvBase:
    """``factory(**env_config)`` of scenario ``name``: the scenario registered in this process
    (built-in or :func:`register_env`), else an installed one (entry point of the group
    ``mapets_rl.scenarios``); ValueError naming the available scenarios for an unknown name."""
    env_config = dict(env_config or {})
    scenario = _SCENARIOS.get(name)
    if scenario is not None:
        return scenario.factory(**env_config)
    if name in _installed_envs():
        factory = load_entry_point(SCENARIO_GROUP, name, "scenario")
        if not callable(factory):
            raise ValueError(
                f"scenario {name!r} ({entry_points(SCENARIO_GROUP)[name].value}) is not a "
                f"factory (factory(**env_config) -> EnvBase) but {type(factory).__name__}; "
                "the installed package that declares it is broken"
            )
        return factory(**env_config)
    raise ValueError(f"unknown scenario name {name!r}; choose one of {available_envs()}")


def scenario_defaults(name: str) -> dict[str, Any]:
    """The config a built-in scenario runs with when ``env_config`` leaves a key unset (its env
    class's defaults with the scenario's own changes); ``{}`` for other scenarios."""
    scenario = _SCENARIOS.get(name)
    if scenario is None or scenario.parallel_env is None:
        return {}
    return {**scenario.parallel_env.env_class.default_config(), **scenario.changes}
