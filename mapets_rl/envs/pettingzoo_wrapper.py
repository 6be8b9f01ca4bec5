"""Any PettingZoo ``ParallelEnv`` as the TorchRL env every recipe expects, and the conventions a
scenario may follow to give the recipes more than that.

:func:`wrap_pettingzoo` wraps a ``ParallelEnv`` with torchrl's ``PettingZooWrapper`` (specs,
seeding, the group map): one group ``"agents"`` holding every agent of ``possible_agents`` (``I``
agents, in that order), ``use_mask=True`` and ``done_on_any=False``. The keys:

- ``("agents", "observation")`` ``[*, I, obs]``, ``("agents", "action")`` ``[*, I, act]``
  (discrete actions one-hot, or indices ``[*, I]`` with ``categorical_actions=True``),
  ``("agents", "reward")`` ``[*, I, 1]``, ``("agents", "done" | "terminated" | "truncated")``
  ``[*, I, 1]``, root ``done`` / ``terminated`` / ``truncated`` ``[*, 1]`` (all agents');
- ``("agents", "mask")`` ``[*, I]`` bool: False for an agent that left ``env.agents`` (crashed,
  finished); its entries are zero and its done flags True until the next reset;
- ``("agents", "position")`` ``[*, I, 2]`` float32 (metres): where each agent is, read by
  :class:`~mapets_rl.comm.CommunicationRange` (MA-PETS shares data with the agents within range
  ``d`` of one another). ``position=`` says where it comes from: the name of a per-agent info
  key (moved out of ``("agents", "info")``), or a callable ``position(parallel_env)`` returning
  the ``[I, 2]`` positions in the order of ``possible_agents`` after every reset and step;
  ``None`` for an env without positions (every recipe but MA-PETS runs without them);
- ``("agents", "info", key)`` ``[*, I, *shape]``: every other per-agent info the
  ``ParallelEnv`` returns (numbers or arrays; the keys of the first reset's infos, the same at
  every step).

Conventions a scenario may provide (none is required; a recipe that finds one uses it):

``neighbour_changed`` (per-agent info, bool or 0/1 scalar)
    True in a step where the agent's observed neighbours changed identity (a new car ahead).
    MA-PETS (``recipes/mapets.py``, ``store_and_share``) keeps such transitions out of its
    dynamics models' data: the jump in a gap is no dynamics the model could learn. The
    figure-eight reports it.
``traffic_velocity`` / ``traffic_comfort`` (per-agent info, float scalars)
    Traffic-wide means of the step; every recipe's training metrics report their masked mean
    as ``velocity`` / ``comfort`` (``Experiment.batch_metrics``). The freeway reports them.
``last_episode_metrics`` (attribute of the ``ParallelEnv``, ``dict[str, float]``)
    The scenario's metrics of the last episode that ended (figure-eight: agility, safety;
    freeway: velocity, comfort), set by the ``step`` that ends it. The wrapper forwards
    attribute reads to the ``ParallelEnv``, and ``Experiment.episode_metrics`` adds every
    number of it to each evaluation episode's metrics (results files, ``compare``).
a planner reward (a function; MA-PETS only)
    MA-PETS plans with a known reward on predicted observations: ``reward_fn(obs [..., S],
    action [..., A], next_obs [..., S]) -> reward [...]`` (float, vectorised over the leading
    dimensions: agents, candidates, particles) and optionally ``termination_fn(...) -> bool
    [...]`` (a predicted crash ends the particle's trajectory). Pass them as
    ``MAPETS(config, reward_fn=..., termination_fn=...)``, or name the reward in the config
    (``reward_fn=package.module:function``, imported when the config is built: the shell's
    way); the built-in scenarios register theirs with the scenario registry as a config
    section (``planner_reward``, a :class:`~mapets_rl.envs.PlannerReward` subclass whose fields
    are its settings, :class:`~mapets_rl.envs.registry.Scenario`), which MA-PETS uses when no
    ``reward_fn`` is given. MA-PETS also needs continuous actions (``Box`` action spaces).

A :class:`~mapets_rl.envs.TrafficParallelEnv` (the package's traffic scenarios and their
subclasses) goes through :class:`TrafficPettingZooWrapper`: the same entries, built from one
array per key of the scenario instead of torchrl's per-agent loop (faster than a highway-env
step with 8 agents), and a removed CAV's position stays where it last drove (the crash site)
where the stock path reports zeros.
"""

from __future__ import annotations

import warnings
from collections.abc import Callable
from typing import Any

import numpy as np
import torch
from gymnasium import spaces
from pettingzoo import ParallelEnv
from tensordict import TensorDict, TensorDictBase
from torchrl.data import OneHot, Unbounded
from torchrl.envs import EnvBase
from torchrl.envs.libs.pettingzoo import PettingZooWrapper

from mapets_rl._console import pettingzoo_version_warning_ignored
from mapets_rl.envs.parallel import TrafficParallelEnv
from mapets_rl.envs.validation import check_device, check_flag, check_one_hot, check_seed

Position = str | Callable[[ParallelEnv], Any] | None
"""Where each agent's position comes from: a per-agent info key, a callable of the
``ParallelEnv`` returning ``[I, 2]``, or None (no ``("agents", "position")``)."""

POSITION = ("agents", "position")
STEP_PARTS = ("observations", "rewards", "terminations", "truncations", "infos")
"""What a ``ParallelEnv.step`` returns, in order: one dict per part, keyed by agent."""


def _described(value: object) -> str:
    """What ``value`` is, for a message: its type, and its length where it is a tuple."""
    if isinstance(value, tuple):
        return f"a tuple of {len(value)}"
    return f"a {type(value).__name__}"


def _info_keys(info: object) -> set[str]:
    """The keys of an agent's info dict (none for anything else), without ``"action_mask"``,
    which torchrl takes out of the dict it is given."""
    return set(info) - {"action_mask"} if isinstance(info, dict) else set()


def check_spaces(parallel_env: ParallelEnv) -> dict[str, tuple[int, ...]]:
    """The observation shape of every agent of ``possible_agents``; ValueError (one line, naming
    the agent) unless each observation space is a gymnasium ``Box`` (numbers the recipes feed to
    their networks), of one shape for all (they are stacked into one group), and each action
    space a ``Box`` or a ``Discrete``."""
    shapes = {}
    for agent in parallel_env.possible_agents:
        space = parallel_env.observation_space(agent)
        if not isinstance(space, spaces.Box):
            raise ValueError(
                f"observation_space({agent!r}) must be a gymnasium Box (the recipes read an "
                f"array of numbers per agent), got {space!r}"
            )
        action = parallel_env.action_space(agent)
        if not isinstance(action, spaces.Box | spaces.Discrete):
            raise ValueError(
                f"action_space({agent!r}) must be a gymnasium Box or Discrete, got {action!r}"
            )
        shapes[agent] = tuple(space.shape)
    if len(set(shapes.values())) > 1:
        raise ValueError(
            "every agent's observation_space must have one shape (the agents form one group), "
            f"got {shapes}"
        )
    return shapes


class AgentsPettingZooWrapper(PettingZooWrapper):
    """torchrl's ``PettingZooWrapper`` with the agents' positions under
    ``("agents", "position")`` ``[*, I, 2]`` (see the module docstring for ``position``).

    Build it with :func:`wrap_pettingzoo`, which sets the group map and checks the input.
    """

    def __init__(self, env: ParallelEnv, position: Position, **kwargs: Any) -> None:
        self.position = position
        self._obs_shapes = check_spaces(env)
        self._info_keys: dict[str, set[str]] | None = None
        super().__init__(env=env, **kwargs)  # its first reset is checked here (_reset_parallel)

    def _reset_parallel(self, **kwargs: Any) -> tuple[dict, dict]:
        """The ``ParallelEnv``'s reset, checked (:meth:`_check_output`); the first one (at
        construction) records each agent's info keys, which every later output must repeat."""
        out = self._env.reset(**kwargs)
        if not (isinstance(out, tuple) and len(out) == 2 and all(isinstance(d, dict) for d in out)):
            raise ValueError(
                "the env's reset must return (observations, infos), two dicts keyed by agent "
                f"(PettingZoo's ParallelEnv API since 1.22), got {_described(out)}"
            )
        observations, infos = out
        missing = [a for a in self._env.possible_agents if a not in observations]
        if missing:
            raise ValueError(
                f"the env's reset gives no observation of agent {missing[0]!r}: every agent of "
                "possible_agents starts an episode"
            )
        if self._info_keys is None:
            self._info_keys = {a: _info_keys(infos.get(a)) for a in self._env.possible_agents}
        self._check_output("reset", {"observations": observations, "infos": infos})
        return out

    def _step_parallel(self, tensordict: TensorDictBase) -> tuple[dict, dict, dict, dict, dict]:
        """The ``ParallelEnv``'s step, checked (:meth:`_check_output`)."""
        out = super()._step_parallel(tensordict)
        if not (isinstance(out, tuple) and len(out) == 5 and all(isinstance(d, dict) for d in out)):
            raise ValueError(
                f"the env's step must return ({', '.join(STEP_PARTS)}), five dicts keyed by "
                f"agent (PettingZoo's ParallelEnv API since 1.22), got {_described(out)}"
            )
        self._check_output("step", dict(zip(STEP_PARTS, out, strict=True)))
        return out

    def _check_output(self, call: str, parts: dict[str, dict]) -> None:
        """ValueError (one line, naming the agent and the key) unless every agent that ``call``
        (``"reset"`` or ``"step"``) observed is one of ``possible_agents``, has an observation
        of its space's shape and an entry in every other part, and the info keys of the first
        reset."""
        observations = parts["observations"]
        for agent, observation in observations.items():
            if agent not in self._obs_shapes:
                raise ValueError(
                    f"the env's {call} observes agent {agent!r}, which is not in possible_agents "
                    f"{list(self._obs_shapes)}"
                )
            if np.shape(observation) != self._obs_shapes[agent]:
                raise ValueError(
                    f"the env's {call} gives agent {agent!r} an observation of shape "
                    f"{list(np.shape(observation))}, its observation_space has "
                    f"{list(self._obs_shapes[agent])}"
                )
            for part, values in parts.items():
                if agent not in values:
                    raise ValueError(
                        f"the env's {call} gives agent {agent!r} an observation but no entry in "
                        f"its {part}"
                    )
            keys = _info_keys(parts["infos"][agent])
            if not isinstance(parts["infos"][agent], dict):
                raise ValueError(
                    f"the env's {call} gives agent {agent!r} an info that is no dict but "
                    f"{_described(parts['infos'][agent])}"
                )
            if keys != self._info_keys[agent]:
                raise ValueError(
                    f"the env's {call} gives agent {agent!r} the info keys {sorted(keys)}, its "
                    f"first reset gave {sorted(self._info_keys[agent])}: the per-agent info keys "
                    "must be the same at every reset and step"
                )

    def _build_env(self, env: ParallelEnv) -> ParallelEnv:
        """torchrl's, without its warning that it was tested with another PettingZoo version
        (``pyproject.toml`` pins the version our tests run with)."""
        with pettingzoo_version_warning_ignored():
            return super()._build_env(env)

    def _init_env(self) -> None:
        super()._init_env()
        group_spec = self.observation_spec["agents"]
        n_agents = len(self.group_map["agents"])
        if isinstance(self.position, str):
            info_keys = list(group_spec["info"].keys()) if "info" in group_spec.keys() else []
            if self.position not in info_keys:
                raise ValueError(
                    f"position={self.position!r} names no per-agent info of the env; its "
                    f"infos after a reset have the keys {info_keys}"
                )
            spec = group_spec["info", self.position]
            if spec.shape != (n_agents, 2):
                raise ValueError(
                    f"position={self.position!r} must give each of the {n_agents} agents an "
                    f"(x, y) position, shape [{n_agents}, 2]; got {list(spec.shape)}"
                )
            del group_spec["info"][self.position]
            if not group_spec["info"].keys():
                del group_spec["info"]
            group_spec["position"] = spec
        elif self.position is not None:  # called once here: a wrong shape fails at once
            group_spec["position"] = Unbounded(
                shape=self._callable_position().shape, dtype=torch.float32, device=self.device
            )

    def _with_position(self, tensordict: TensorDictBase) -> TensorDictBase:
        """Move or compute ``("agents", "position")`` in a reset's or step's output."""
        if isinstance(self.position, str):
            info = tensordict.get(("agents", "info"))
            tensordict.set(POSITION, info.pop(self.position))
            if not info.keys():
                del tensordict["agents", "info"]
        elif self.position is not None:
            tensordict.set(POSITION, self._callable_position())
        return tensordict

    def _callable_position(self) -> torch.Tensor:
        """``position(parallel_env)`` as a float32 tensor ``[I, 2]``; ValueError otherwise."""
        value = np.asarray(self.position(self._env), dtype=np.float32)
        shape = (len(self.group_map["agents"]), 2)
        if value.shape != shape:
            raise ValueError(
                f"position={self.position!r} must return the positions of the "
                f"{shape[0]} agents, shape {list(shape)}; got {list(value.shape)}"
            )
        return torch.as_tensor(value, device=self.device)

    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs: Any) -> TensorDictBase:
        return self._with_position(super()._reset(tensordict, **kwargs))

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        return self._with_position(super()._step(tensordict))


class TrafficPettingZooWrapper(AgentsPettingZooWrapper):
    """:class:`AgentsPettingZooWrapper` for a ``TrafficParallelEnv`` with a vectorised data path
    (position: the info key ``"position"``).

    torchrl's ``_step``/``_reset`` build every agent's entries with a Python loop of small
    tensor copies (and deep-copy the info dicts). Here every output entry is one NumPy array of
    the scenario turned into a tensor without a copy (``torch.from_numpy``; on another device,
    one transfer), and the output TensorDicts are built without re-validating entries whose
    shapes, dtypes and device this class guarantees. The entries are the stock wrapper's (dead
    agents: zero entries except the position, ``terminated = truncated = done = True``,
    ``mask = False``; root flags = all agents'). Since ``_step`` always returns every reward
    and done key with its spec's shape and dtype, torchrl's per-step completion of missing
    done keys is skipped (it still runs, with the type checks, when ``run_type_checks`` is
    set).
    """

    def __init__(self, env: TrafficParallelEnv, **kwargs: Any) -> None:
        super().__init__(env, position="position", **kwargs)

    def _init_env(self) -> None:
        super()._init_env()
        group_spec = self.observation_spec["agents"]
        self._info_dtypes = {
            key: torch.empty((), dtype=group_spec["info", key].dtype).numpy().dtype
            for key in group_spec["info"]
        }
        self._agents_action_spec = self.input_spec["full_action_spec", "agents", "action"]
        self._group_size = torch.Size([len(self._env.possible_agents)])

    def _output(
        self,
        obs: np.ndarray,
        info: dict,
        acting: np.ndarray,
        terminated: np.ndarray,
        truncated: np.ndarray,
        reward: np.ndarray | None = None,
    ) -> TensorDict:
        """Output TensorDict from the scenario's arrays (all ``[I, ...]``, ``I`` CAVs; no reward
        entry at a reset); entries of agents that did not act are zeroed, except the position."""
        device, batch = self.device, self._group_size
        if device is None or device.type == "cpu":
            tensor = torch.from_numpy  # fresh arrays that nobody else writes to: no copy
        else:

            def tensor(array: np.ndarray) -> torch.Tensor:
                return torch.from_numpy(array).to(device)

        column = acting[:, None]
        done = terminated | truncated
        info_out = {}
        for key, value in self._env.info_arrays(info).items():
            if key != "position":
                value = (value * acting.reshape(-1, *([1] * (value.ndim - 1)))).astype(
                    self._info_dtypes[key], copy=False
                )
                info_out[key] = tensor(value)
            else:
                position = tensor(np.array(value, dtype=np.float32))
        group = {
            "observation": tensor(obs * column),
            "mask": tensor(~done),
            "position": position,
            "done": tensor(done[:, None]),
            "terminated": tensor(terminated[:, None]),
            "truncated": tensor(truncated[:, None]),
            "info": TensorDict._new_unsafe(info_out, batch_size=batch, device=device),
        }
        if reward is not None:
            group["reward"] = tensor(reward[:, None])
        return TensorDict._new_unsafe(
            {
                "agents": TensorDict._new_unsafe(group, batch_size=batch, device=device),
                "done": tensor(done.all(keepdims=True)),
                "terminated": tensor(terminated.all(keepdims=True)),
                "truncated": tensor(truncated.all(keepdims=True)),
            },
            batch_size=torch.Size(()),
            device=device,
        )

    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs: Any) -> TensorDictBase:
        if tensordict is not None:
            reset = tensordict.get("_reset", None)
            if reset is not None and not reset.all():
                raise RuntimeError("TrafficPettingZooWrapper resets all agents at once.")
        obs, info = self._env.reset_joint(**kwargs)
        n = len(self._env.possible_agents)
        false = np.zeros(n, dtype=bool)
        return self._output(obs, info, np.ones(n, dtype=bool), false, false.copy())

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        action_spec = self._agents_action_spec
        action = tensordict.get(("agents", "action"), None)
        if action is None:
            raise ValueError(
                "step needs the CAVs' actions under ('agents', 'action'); the tensordict has none"
            )
        if action.shape != action_spec.shape:
            raise ValueError(
                f"('agents', 'action') must have shape {list(action_spec.shape)}, "
                f"got {list(action.shape)}"
            )
        if isinstance(action_spec, OneHot):
            check_one_hot(action)
        joint = np.asarray(action_spec.to_numpy(action))
        obs, rewards, terminated, truncated, acting, info = self._env.step_joint(joint)
        return self._output(obs, info, acting, terminated, truncated, rewards)

    def _step_proc_data(self, next_tensordict_out: TensorDictBase) -> TensorDictBase:
        if self.run_type_checks:
            return super()._step_proc_data(next_tensordict_out)
        return next_tensordict_out


def wrap_pettingzoo(
    parallel_env: ParallelEnv,
    position: Position = "position",
    seed: int | None = None,
    device: str = "cpu",
    categorical_actions: bool = False,
) -> EnvBase:
    """The TorchRL env of any PettingZoo ``ParallelEnv``, with the layout every recipe reads:
    group ``"agents"``, ``("agents", "mask")``, ``("agents", "position")`` and per-agent infos
    (see the module docstring). :func:`~mapets_rl.envs.make_env` returns it for the built-in
    scenarios; a custom scenario's factory returns it too (``register_env`` or an entry point of
    ``mapets_rl.scenarios``).

    Args:
        parallel_env: a PettingZoo ``ParallelEnv`` (a :class:`~mapets_rl.envs.TrafficParallelEnv`
            takes the vectorised :class:`TrafficPettingZooWrapper`).
        position: where each agent's ``(x, y)`` position comes from: the name of a per-agent
            info key (default ``"position"``, what a ``TrafficParallelEnv`` reports), a callable
            ``position(parallel_env) -> [I, 2]`` (agents in ``possible_agents`` order) called
            after every reset and step, or None for no position.
        seed: seed of the first reset.
        device: torch device of the output tensors.
        categorical_actions: discrete actions as indices instead of one-hot.

    Raises:
        ValueError: ``parallel_env`` is not a ``ParallelEnv``; ``position`` is not a string, a
            callable or None, names no per-agent info, or gives no ``[I, 2]`` positions;
            ``device``, ``seed`` or ``categorical_actions`` is not one; an observation space is
            not a ``Box`` (or the agents' differ in shape), an action space neither a ``Box``
            nor a ``Discrete`` (:func:`check_spaces`); and, at the reset the construction does
            and at every later reset and step, an output off PettingZoo's ``ParallelEnv`` API
            (naming the agent and the key: a reward, termination, truncation or info missing
            for an observed agent, info keys other than the first reset's, an observation
            unlike its space, an agent not in ``possible_agents``, an old-API ``reset`` or a
            ``step`` of other than five dicts).
    """
    if not isinstance(parallel_env, ParallelEnv):
        raise ValueError(
            "parallel_env must be a pettingzoo.ParallelEnv (convert an AEC env with "
            "pettingzoo.utils.conversions.aec_to_parallel), got "
            f"{type(parallel_env).__name__}"
        )
    if not (position is None or isinstance(position, str) or callable(position)):
        raise ValueError(
            "position must be a per-agent info key (str), a callable "
            f"position(parallel_env) -> [I, 2] or None, got {type(position).__name__}"
        )
    check_device(device)
    seed = check_seed(seed)
    categorical_actions = check_flag(categorical_actions, "categorical_actions")
    kwargs = {
        "group_map": {"agents": list(parallel_env.possible_agents)},
        "use_mask": True,
        "categorical_actions": categorical_actions,
        "done_on_any": False,
        "seed": seed,
        "device": device,
    }
    if isinstance(parallel_env, TrafficParallelEnv):
        if position != "position":
            raise ValueError(
                "position must be 'position' for a TrafficParallelEnv (its CAVs' positions are "
                f"that info key), got {position!r}"
            )
        return TrafficPettingZooWrapper(parallel_env, **kwargs)
    return AgentsPettingZooWrapper(parallel_env, position, **kwargs)


def wrap_parallel_env(
    parallel_env: TrafficParallelEnv,
    seed: int | None = None,
    device: str = "cpu",
    categorical_actions: bool = False,
) -> EnvBase:
    """Deprecated name of :func:`wrap_pettingzoo` (kept for one release; DeprecationWarning)."""
    warnings.warn(
        "mapets_rl.envs.wrap_parallel_env is deprecated and will be removed in the next "
        "release; use mapets_rl.envs.wrap_pettingzoo (any PettingZoo ParallelEnv)",
        DeprecationWarning,
        stacklevel=2,
    )
    return wrap_pettingzoo(
        parallel_env, seed=seed, device=device, categorical_actions=categorical_actions
    )
