"""TorchRL environments of the built-in scenarios: ``make_env(name, **config)``.

The built-in scenarios are declared at the end of this module, where they register themselves
in the scenario registry (:mod:`mapets_rl.envs.registry`) with their PettingZoo env class, what
they change from its defaults and their gymnasium id.

The PettingZoo envs are wrapped by torchrl's ``PettingZooWrapper`` (specs, seeding, group map)
with one group ``"agents"`` and ``use_mask=True``: crashed CAVs stay in the batch with
``("agents", "mask") = False`` and ``("agents", "terminated") = True``. Per-agent infos go to
``("agents", "info", key)``, except the positions, which go to ``("agents", "position")``
``[*, I, 2]`` (metres), where the communication transform reads them. A crashed CAV's position
stays where it last drove (the crash site), not zero: ``(0, 0)`` is the crossing.

``TrafficPettingZooWrapper`` replaces the wrapper's data path: the stock ``_step``/``_reset``
build every agent's entries with a Python loop of small tensor copies (and deep-copy the info
dicts), which costs more than a highway-env step with 8 agents; here one array per key is copied
from the scenario. The entries are the same as the stock wrapper's (dead agents: zero entries
except the position,
``terminated = truncated = done = True``, ``mask = False``; root flags = all agents').
"""

from __future__ import annotations

import functools
from typing import Any

import numpy as np
import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import OneHot
from torchrl.envs import EnvBase
from torchrl.envs.libs.pettingzoo import PettingZooWrapper

from mapets_rl.envs.figure_eight import figure_eight_collision, figure_eight_reward
from mapets_rl.envs.freeway_merge import FreewayMergeParallelEnv
from mapets_rl.envs.parallel import FigureEightParallelEnv, FreewayParallelEnv, TrafficParallelEnv
from mapets_rl.envs.registry import builtin_envs, register_builtin, registered_scenario
from mapets_rl.envs.torch_freeway.env import TorchFreewayEnv
from mapets_rl.envs.validation import check_one_hot

TORCH_BACKEND = {
    FreewayParallelEnv: FreewayParallelEnv.env_class,
    FreewayMergeParallelEnv: FreewayMergeParallelEnv.env_class,
}
"""PettingZoo env class of a scenario -> the highway-env scenario class the torch backend
simulates."""
TORCH_NAMES = ("freeway", "freeway-merge")


class TrafficPettingZooWrapper(PettingZooWrapper):
    """``PettingZooWrapper`` for ``TrafficParallelEnv`` with a vectorised data path.

    Every output entry is one NumPy array of the scenario turned into a tensor without a copy
    (``torch.from_numpy``; on another device, one transfer), and the output TensorDicts are
    built without re-validating entries whose shapes, dtypes and device this class guarantees.
    Since ``_step`` always returns every reward and done key with its spec's shape and dtype,
    torchrl's per-step completion of missing done keys is skipped (it still runs, with the
    type checks, when ``run_type_checks`` is set).
    """

    def _init_env(self) -> None:
        super()._init_env()
        group_spec = self.observation_spec["agents"]
        position = group_spec["info", "position"]
        del group_spec["info"]["position"]
        group_spec["position"] = position
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


def make_parallel_env(name: str, **config: Any) -> TrafficParallelEnv:
    """The PettingZoo ``ParallelEnv`` of built-in scenario ``name`` (its env class built with
    the scenario's changes, then ``config``; see :mod:`mapets_rl.envs.registry`)."""
    scenario = registered_scenario(name)
    if scenario is None or scenario.parallel_env is None:
        raise ValueError(f"unknown scenario name {name!r}; choose one of {builtin_envs()}")
    return scenario.parallel_env(**{**scenario.changes, **config})


BACKENDS = ("highway-env", "torch")
"""Simulators of the built-in scenarios: highway-env (every scenario; the reference) and the
batched torch freeway (``freeway``, ``freeway-merge``)."""
DTYPES = {"float32": torch.float32, "float64": torch.float64}


def check_device(device: object) -> None:
    """ValueError unless ``device`` names a torch device this machine has (``"cpu"``,
    ``"cuda"`` / ``"cuda:N"`` with a GPU N, ...), before anything is built."""
    if isinstance(device, bool) or not isinstance(device, (str, torch.device)):
        raise ValueError(f"device must be a device name such as 'cpu' or 'cuda:0', got {device!r}")
    try:
        parsed = torch.device(device)
    except RuntimeError as err:
        raise ValueError(f"device must be a torch device name, got {device!r} ({err})") from None
    if parsed.type == "cuda" and (
        not torch.cuda.is_available() or (parsed.index or 0) >= torch.cuda.device_count()
    ):
        raise ValueError(
            f"device={device!r}: no such CUDA device here ({torch.cuda.device_count()} GPUs)"
        )


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
    ``"freeway"`` or ``"freeway-merge"`` (the freeway with an on-ramp).

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
        backend: ``"highway-env"`` (default, every scenario) or ``"torch"`` (``freeway`` and
            ``freeway-merge``: ``num_envs`` roads simulated as one tensor program,
            :class:`~mapets_rl.envs.torch_freeway.env.TorchFreewayEnv`).
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
    check_device(device)
    if backend == "highway-env":
        if num_envs is not None or dtype != "float32" or kernel != "auto":
            raise ValueError(
                "num_envs, dtype and kernel need backend='torch' (the highway-env backend "
                "simulates one road; batch it with torchrl's SerialEnv / ParallelEnv)"
            )
        return wrap_parallel_env(
            make_parallel_env(name, **config),
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


def wrap_parallel_env(
    parallel_env: TrafficParallelEnv,
    seed: int | None = None,
    device: str = "cpu",
    categorical_actions: bool = False,
) -> EnvBase:
    """The TorchRL env of a traffic ``ParallelEnv``: what :func:`make_env` returns for the
    built-in scenarios, and what a custom scenario's factory returns (``register_env`` or an
    entry point of ``mapets_rl.scenarios``).

    One group ``"agents"``, crashed CAVs masked (``("agents", "mask")``), positions under
    ``("agents", "position")`` ``[*, I, 2]`` where :class:`~mapets_rl.comm.CommunicationRange`
    reads them (torchrl's stock ``PettingZooWrapper`` leaves them in
    ``("agents", "info", "position")``, so MA-PETS' communication cannot find them).

    Args:
        parallel_env: a :class:`~mapets_rl.envs.TrafficParallelEnv` (any subclass).
        seed: seed of the first reset.
        device: torch device of the output tensors.
        categorical_actions: discrete actions as indices instead of one-hot.
    """
    if not isinstance(parallel_env, TrafficParallelEnv):
        raise ValueError(
            "parallel_env must be a mapets_rl.envs.TrafficParallelEnv (wrap your "
            f"MultiAgentTrafficEnv in one first), got {type(parallel_env).__name__}"
        )
    return TrafficPettingZooWrapper(
        env=parallel_env,
        group_map={"agents": list(parallel_env.possible_agents)},
        use_mask=True,
        categorical_actions=categorical_actions,
        done_on_any=False,
        seed=seed,
        device=device,
    )


_FIGURE_EIGHT_PLANNER = {
    "planner_reward": figure_eight_reward,
    "planner_termination": figure_eight_collision,
}
"""What a model-based planner scores figure-eight trajectories with (the registry's
``planner_reward`` / ``planner_termination``)."""


def _register_builtin(
    name: str,
    parallel_env: type[TrafficParallelEnv],
    gym_id: str,
    changes: dict[str, Any] | None = None,
    **planner: Any,
) -> None:
    """Register built-in scenario ``name``: ``parallel_env`` with ``changes`` to its defaults,
    built by :func:`make_env`, raw env registered with gymnasium as ``gym_id``, and the
    ``planner_reward`` / ``planner_termination`` it brings (if any)."""
    register_builtin(
        name, functools.partial(make_env, name), parallel_env, gym_id, changes, **planner
    )


# The one place the built-in scenarios and their defaults are declared: make_env, build_env,
# the recipes, the CLI, compare and the gymnasium ids (mapets_rl.envs.GYM_IDS) read them from
# the registry.
_register_builtin(
    "figure-eight", FigureEightParallelEnv, "mapets_rl/FigureEight-v0", **_FIGURE_EIGHT_PLANNER
)
_register_builtin(
    "figure-eight-multilane",
    FigureEightParallelEnv,
    "mapets_rl/FigureEightMultiLane-v0",
    {"lanes": 2, "n_cavs": 22, "horizon": 400},
    **_FIGURE_EIGHT_PLANNER,
)
_register_builtin("freeway", FreewayParallelEnv, "mapets_rl/Freeway-v0")
_register_builtin("freeway-merge", FreewayMergeParallelEnv, "mapets_rl/FreewayMerge-v0")
