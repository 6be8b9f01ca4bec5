"""TorchRL environments of the scenarios: ``make_env(name, **config)``.

The PettingZoo envs are wrapped by torchrl's ``PettingZooWrapper`` (specs, seeding, reset, masks)
with one group ``"agents"`` and ``use_mask=True``: crashed CAVs stay in the batch with
``("agents", "mask") = False`` and ``("agents", "terminated") = True``. The wrapper reads
per-agent infos into ``("agents", "info", key)``; a ``RenameTransform`` moves the positions to
``("agents", "position")`` ``[*, I, 2]`` (metres), where the communication transform reads them.

``TrafficPettingZooWrapper`` only replaces the wrapper's per-step data path: the stock ``_step``
builds every agent's entries with a Python loop of small tensor copies (and deep-copies the info
dicts), which costs more than a highway-env step with 8 agents; here one array per key is copied
from the scenario. The outputs are the same as the stock wrapper's (dead agents: zero entries,
``terminated = truncated = done = True``, ``mask = False``; root flags = all agents').
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.envs import EnvBase, RenameTransform, TransformedEnv
from torchrl.envs.libs.pettingzoo import PettingZooWrapper

from mapets_rl.envs.parallel import FigureEightParallelEnv, FreewayParallelEnv, TrafficParallelEnv

SCENARIOS: dict[str, tuple[type[TrafficParallelEnv], dict[str, Any]]] = {
    "figure-eight": (FigureEightParallelEnv, {"lanes": 1}),
    "figure-eight-multilane": (FigureEightParallelEnv, {"lanes": 2, "n_cavs": 22}),
    "freeway": (FreewayParallelEnv, {}),
}
"""Scenario name -> (PettingZoo env class, default config)."""


class TrafficPettingZooWrapper(PettingZooWrapper):
    """``PettingZooWrapper`` for ``TrafficParallelEnv`` with a vectorised ``_step``."""

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        parallel_env: TrafficParallelEnv = self._env
        action_spec = self.input_spec["full_action_spec", "agents", "action"]
        joint = np.asarray(action_spec.to_numpy(tensordict.get(("agents", "action"))))
        obs, rewards, terminated, truncated, acting, info = parallel_env.step_joint(joint)
        device = self.device
        alive = torch.as_tensor(acting, device=device)
        terminated_t = torch.as_tensor(terminated, device=device).unsqueeze(-1)
        truncated_t = torch.as_tensor(truncated, device=device).unsqueeze(-1)
        done_t = terminated_t | truncated_t
        still = set(parallel_env.agents)
        group = {
            "observation": torch.as_tensor(obs, device=device) * alive[:, None],
            "reward": torch.as_tensor(rewards, device=device).unsqueeze(-1),
            "terminated": terminated_t,
            "truncated": truncated_t,
            "done": done_t,
            "mask": torch.tensor([a in still for a in parallel_env.possible_agents], device=device),
        }
        if not hasattr(self, "_info_dtypes"):
            info_spec = self.observation_spec["agents"].get("info", None)
            self._info_dtypes = (
                {} if info_spec is None else {k: info_spec[k].dtype for k in info_spec}
            )
        if self._info_dtypes:
            info_out = {}
            for key, value in parallel_env.info_arrays(info).items():
                value = torch.as_tensor(value, device=device)
                keep = alive.reshape(-1, *([1] * (value.ndim - 1)))
                info_out[key] = (value * keep).to(self._info_dtypes[key])
            group["info"] = TensorDict(info_out, batch_size=alive.shape, device=device)
        return TensorDict(
            {
                "agents": TensorDict(group, batch_size=alive.shape, device=device),
                "done": done_t.all().reshape(1),
                "terminated": terminated_t.all().reshape(1),
                "truncated": truncated_t.all().reshape(1),
            },
            batch_size=(),
            device=device,
        )


def make_parallel_env(name: str, **config: Any) -> TrafficParallelEnv:
    """The PettingZoo ``ParallelEnv`` of scenario ``name`` (see ``SCENARIOS``)."""
    if name not in SCENARIOS:
        raise ValueError(f"unknown scenario name {name!r}; choose one of {sorted(SCENARIOS)}")
    cls, defaults = SCENARIOS[name]
    return cls(**{**defaults, **config})


def make_env(
    name: str,
    seed: int | None = None,
    device: str = "cpu",
    categorical_actions: bool = False,
    **config: Any,
) -> EnvBase:
    """A TorchRL env of scenario ``name``: ``"figure-eight"``, ``"figure-eight-multilane"``
    or ``"freeway"``.

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
        device: torch device of the output tensors.
        categorical_actions: discrete actions as indices instead of one-hot (freeway).
        **config: scenario config (``FigureEightParallelEnv`` / ``FreewayParallelEnv`` args).
    """
    parallel_env = make_parallel_env(name, **config)
    base = TrafficPettingZooWrapper(
        env=parallel_env,
        group_map={"agents": list(parallel_env.possible_agents)},
        use_mask=True,
        categorical_actions=categorical_actions,
        done_on_any=False,
        seed=seed,
        device=device,
    )
    return TransformedEnv(
        base,
        RenameTransform(
            in_keys=[("agents", "info", "position")],
            out_keys=[("agents", "position")],
            create_copy=False,
        ),
    )
