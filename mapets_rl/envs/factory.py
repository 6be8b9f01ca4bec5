"""TorchRL environments of the built-in scenarios: ``make_env(name, **config)``.

The built-in scenarios are declared at the end of this module, where they register themselves
in the scenario registry (:mod:`mapets_rl.envs.registry`) with their PettingZoo env class, what
they change from its defaults and their gymnasium id.

The highway-env backend wraps each scenario's PettingZoo env with
:func:`~mapets_rl.envs.pettingzoo_wrapper.wrap_pettingzoo` (the layout and its conventions are
described there): crashed CAVs stay in the batch with ``("agents", "mask") = False``, positions
under ``("agents", "position")`` ``[*, I, 2]`` (metres); a crashed CAV's position stays where it
last drove (the crash site), not zero: ``(0, 0)`` is the crossing.
"""

from __future__ import annotations

import functools
from typing import Any

import torch
from torchrl.envs import EnvBase

from mapets_rl.envs.figure_eight import FigureEightPlannerReward
from mapets_rl.envs.freeway_merge import FreewayMergeParallelEnv
from mapets_rl.envs.parallel import FigureEightParallelEnv, FreewayParallelEnv, TrafficParallelEnv
from mapets_rl.envs.pettingzoo_wrapper import wrap_pettingzoo
from mapets_rl.envs.planner_reward import PlannerReward
from mapets_rl.envs.registry import builtin_envs, register_builtin, registered_scenario
from mapets_rl.envs.sumo_figure_eight import SumoFigureEightParallelEnv, import_sumo
from mapets_rl.envs.torch_freeway.env import TorchFreewayEnv
from mapets_rl.envs.validation import check_device, check_flag, check_seed

TORCH_BACKEND = {
    FreewayParallelEnv: FreewayParallelEnv.env_class,
    FreewayMergeParallelEnv: FreewayMergeParallelEnv.env_class,
}
"""PettingZoo env class of a scenario -> the highway-env scenario class the torch backend
simulates."""
TORCH_NAMES = ("freeway", "freeway-merge")


def make_parallel_env(name: str, **config: Any) -> TrafficParallelEnv:
    """The PettingZoo ``ParallelEnv`` of built-in scenario ``name`` (its env class built with
    the scenario's changes, then ``config``; see :mod:`mapets_rl.envs.registry`)."""
    scenario = registered_scenario(name)
    if scenario is None or scenario.parallel_env is None:
        raise ValueError(f"unknown scenario name {name!r}; choose one of {builtin_envs()}")
    return scenario.parallel_env(**{**scenario.changes, **config})


BACKENDS = ("highway-env", "torch", "sumo")
"""Simulators of the built-in scenarios: highway-env (every scenario; the reference), the
batched torch freeway (``freeway``, ``freeway-merge``) and SUMO (the figure-eights; the extra
``mapets-rl[sumo]``, :mod:`mapets_rl.envs.sumo_figure_eight`)."""
SUMO_NAMES = ("figure-eight", "figure-eight-multilane")
"""The scenarios ``backend="sumo"`` simulates."""
DTYPES = {"float32": torch.float32, "float64": torch.float64}
KERNELS = ("auto", "native", "torch")
"""``kernel`` of the batched freeway on a CPU (see :func:`make_env`)."""
FACTORY_KEYS = {
    "seed": "None or an integer in [0, 2**62 - 1] (the first reset's seed)",
    "device": "a device name such as 'cpu' or 'cuda:0' (of the output tensors)",
    "categorical_actions": "True or False (discrete actions as indices, not one-hot)",
    "render_mode": "None or 'rgb_array'",
}
""":func:`make_env`'s own keys of every built-in scenario (besides ``backend``), in words."""
TORCH_KEYS = {
    "num_envs": "None (one road) or an integer >= 1: roads simulated as one batch (torch)",
    "dtype": f"one of {list(DTYPES)}: the simulation's precision (torch)",
    "kernel": f"one of {list(KERNELS)}: the fused C++ kernel or torch ops on a CPU (torch)",
}
""":func:`make_env`'s keys of the batched freeway (``backend="torch"``), in words."""
PROBE = "?"
"""A value no scenario key accepts: the scenario's refusal of it says what the key accepts."""


def make_env(
    name: str,
    seed: int | None = None,
    device: str = "cpu",
    categorical_actions: bool = False,
    backend: str = "highway-env",
    num_envs: int | None = None,
    dtype: str = "float32",
    kernel: str = "auto",
    **config: Any,
) -> EnvBase:
    """A TorchRL env of scenario ``name``: ``"figure-eight"``, ``"figure-eight-multilane"``,
    ``"freeway"``, ``"freeway-merge"`` (the freeway with an on-ramp), highway-env's own
    multi-agent scenes ``"highway-intersection"``, ``"highway-roundabout"``, ``"highway-merge"``
    and ``"highway-multi"`` (:mod:`mapets_rl.envs.highway_multi_agent`), or a registered one.

    Keys (group ``"agents"``, ``I`` CAVs): ``("agents","observation")`` ``[*, I, obs]``,
    ``("agents","action")`` ``[*, I, act]`` (figure-eight: target speed [+ lane flag];
    freeway: one-hot ``[*, I, 4]`` over KL, CL, CR, ES, or indices ``[*, I]`` with
    ``categorical_actions=True``), ``("agents","reward")`` ``[*, I, 1]``,
    ``("agents","done"|"terminated"|"truncated")`` ``[*, I, 1]``, ``("agents","mask")``
    ``[*, I]``, ``("agents","position")`` ``[*, I, 2]``, ``("agents","info", ...)`` and root
    ``done``/``terminated``/``truncated`` ``[*, 1]``.

    Args:
        name: scenario name.
        seed: seed of the first reset (``env.set_seed`` works as usual).
        device: torch device of the output tensors (and, with ``backend="torch"``, of the
            simulation).
        categorical_actions: discrete actions as indices instead of one-hot (freeway).
        backend: ``"highway-env"`` (default, every scenario), ``"torch"`` (``freeway`` and
            ``freeway-merge``: ``num_envs`` roads simulated as one tensor program,
            :class:`~mapets_rl.envs.torch_freeway.env.TorchFreewayEnv`) or ``"sumo"`` (the
            figure-eights on SUMO, :mod:`mapets_rl.envs.sumo_figure_eight`; needs
            ``pip install 'mapets-rl[sumo]'``).
        num_envs: with ``backend="torch"``, the number of roads ``B`` (env ``batch_size=[B]``);
            None: one road without a batch dimension.
        dtype: with ``backend="torch"``, the simulation's precision (``"float32"`` or
            ``"float64"``).
        kernel: with ``backend="torch"`` on a CPU, ``"auto"`` (the fused C++ kernel where it
            builds, else torch ops), ``"native"`` (the kernel, or an error) or ``"torch"``.
        **config: scenario config (``FigureEightParallelEnv`` / ``FreewayParallelEnv`` args).
    """
    if backend not in BACKENDS:
        raise ValueError(f"backend must be one of {list(BACKENDS)}, got {backend!r}")
    if backend == "sumo":
        import_sumo()  # without the extra: one line naming it, before any work
    unknown = sorted(set(config) - set(scenario_keys(name)) - {"render_mode"})
    if unknown:
        raise ValueError(
            f"unknown config key(s) {unknown} for scenario {name!r}; accepted keys: "
            f"{env_config_keys(name)}"
        )
    check_device(device)
    seed = check_seed(seed)
    categorical_actions = check_flag(categorical_actions, "categorical_actions")
    if backend in ("highway-env", "sumo"):
        if num_envs is not None or dtype != "float32" or kernel != "auto":
            raise ValueError(
                f"num_envs, dtype and kernel need backend='torch' (the {backend} backend "
                "simulates one road; batch it with torchrl's SerialEnv / ParallelEnv)"
            )
        if backend == "sumo" and name not in SUMO_NAMES:
            raise ValueError(
                f"backend='sumo' simulates {list(SUMO_NAMES)}, not {name!r}; use "
                "backend='highway-env'"
            )
        parallel_env = (
            SumoFigureEightParallelEnv(**{**registered_scenario(name).changes, **config})
            if backend == "sumo"
            else make_parallel_env(name, **config)
        )
        return wrap_pettingzoo(
            parallel_env,
            seed=seed,
            device=device,
            categorical_actions=categorical_actions,
        )
    scenario = registered_scenario(name)
    if scenario is None or scenario.parallel_env not in TORCH_BACKEND:
        raise ValueError(
            f"backend='torch' simulates {sorted(TORCH_NAMES)}, not {name!r}; use "
            "backend='highway-env'"
        )
    if dtype not in DTYPES:
        raise ValueError(f"dtype must be one of {list(DTYPES)}, got {dtype!r}")
    render_mode = config.pop("render_mode", None)
    return TorchFreewayEnv(
        TORCH_BACKEND[scenario.parallel_env],
        {**scenario.changes, **config},
        num_envs=num_envs,
        device=device,
        dtype=DTYPES[dtype],
        seed=seed,
        categorical_actions=categorical_actions,
        render_mode=render_mode,
        kernel=kernel,
    )


def _builtin(name: str) -> Any:
    """The registry's entry of built-in scenario ``name``; ValueError for another name."""
    scenario = registered_scenario(name)
    if scenario is None or scenario.parallel_env is None:
        raise ValueError(f"unknown scenario name {name!r}; choose one of {builtin_envs()}")
    return scenario


def scenario_keys(name: str) -> list[str]:
    """The config keys of built-in scenario ``name``'s own env class, sorted: a traffic
    scenario's ``user_keys()``; for highway-env's multi-agent scenes, the keys of the
    highway-env env's ``default_config()`` and ``controlled_vehicles`` (what the adapter
    accepts). ValueError for a name that is no built-in scenario."""
    env_class = _builtin(name).parallel_env.env_class
    if hasattr(env_class, "user_keys"):
        return list(env_class.user_keys())
    return sorted({*env_class.default_config(), "controlled_vehicles"})


def env_config_keys(name: str) -> list[str]:
    """Every key ``make_env(name, **config)`` (a run's ``env_config``) accepts, sorted:
    ``backend``, :data:`FACTORY_KEYS`, :data:`TORCH_KEYS` where the scenario runs batched,
    and :func:`scenario_keys`."""
    keys = {"backend", *FACTORY_KEYS, *scenario_keys(name)}
    return sorted(keys | (set(TORCH_KEYS) if has_batched_backend(name) else set()))


def _short(value: Any, width: int = 60) -> str:
    """``repr(value)``, cut to ``width`` characters with ``...``."""
    text = repr(value)
    return text if len(text) <= width else f"{text[: width - 3]}..."


def env_config_help(name: str) -> dict[str, str]:
    """Key -> what it accepts, in words, for every key of :func:`env_config_keys` (``name``'s
    defaults included). A scenario key's words are the scenario's own refusal of
    :data:`PROBE` (its ``validate_config``: one line naming the key and the allowed values),
    without the value; a key the scenario does not check (highway-env's own keys of its
    multi-agent scenes) shows its default only. ValueError for a name that is no built-in
    scenario."""
    scenario = _builtin(name)
    env_class = scenario.parallel_env.env_class
    own = scenario_keys(name)
    changes = {k: v for k, v in scenario.changes.items() if k in own}
    checked = hasattr(env_class, "resolved_config")
    defaults = (
        env_class.resolved_config(changes) if checked else {**env_class.default_config(), **changes}
    )
    backends = (
        ["highway-env", "torch"]
        if has_batched_backend(name)
        else ["highway-env", "sumo"]
        if name in SUMO_NAMES
        else ["highway-env"]
    )
    words = {"backend": f"one of {backends} (default 'highway-env')", **FACTORY_KEYS}
    if has_batched_backend(name):
        words.update(TORCH_KEYS)
    for key in own:
        allowed = ""
        if checked:
            try:
                env_class.resolved_config({**changes, key: PROBE})
            except (ValueError, TypeError) as err:
                message, head = str(err), f"{key} must be "
                if message.startswith(head) and ", got " in message:
                    allowed = f"{message[len(head) : message.rindex(', got ')]}; "
        words[key] = f"{allowed}default {_short(defaults.get(key))}"
    return dict(sorted(words.items()))


def has_batched_backend(name: str) -> bool:
    """Whether scenario ``name`` also runs as a batched env (``backend="torch"``)."""
    scenario = registered_scenario(name)
    return scenario is not None and scenario.parallel_env in TORCH_BACKEND


def _register_builtin(
    name: str,
    parallel_env: type[TrafficParallelEnv],
    gym_id: str,
    changes: dict[str, Any] | None = None,
    planner_reward: type[PlannerReward] | None = None,
) -> None:
    """Register built-in scenario ``name``: ``parallel_env`` with ``changes`` to its defaults,
    built by :func:`make_env`, raw env registered with gymnasium as ``gym_id``, and the
    planner reward section it brings (if any)."""
    register_builtin(
        name, functools.partial(make_env, name), parallel_env, gym_id, changes, planner_reward
    )


# The one place the built-in scenarios and their defaults are declared: make_env, build_env,
# the recipes, the CLI, compare and the gymnasium ids (mapets_rl.envs.GYM_IDS) read them from
# the registry.
_register_builtin(
    "figure-eight",
    FigureEightParallelEnv,
    "mapets_rl/FigureEight-v0",
    planner_reward=FigureEightPlannerReward,
)
_register_builtin(
    "figure-eight-multilane",
    FigureEightParallelEnv,
    "mapets_rl/FigureEightMultiLane-v0",
    {"lanes": 2, "n_cavs": 22, "horizon": 400},
    planner_reward=FigureEightPlannerReward,
)
_register_builtin("freeway", FreewayParallelEnv, "mapets_rl/Freeway-v0")
_register_builtin("freeway-merge", FreewayMergeParallelEnv, "mapets_rl/FreewayMerge-v0")
