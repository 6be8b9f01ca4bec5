"""TorchRL environments of the scenarios: ``make_env(name, **config)``.

The PettingZoo envs are wrapped by torchrl's ``PettingZooWrapper`` with one group ``"agents"``
and ``use_mask=True``: crashed CAVs stay in the batch with ``("agents", "mask") = False`` and
``("agents", "terminated") = True``. The wrapper reads per-agent infos into
``("agents", "info", key)``; a ``RenameTransform`` moves the positions to
``("agents", "position")`` ``[*, I, 2]`` (metres), where the communication transform reads them.
"""

from __future__ import annotations

from typing import Any

from torchrl.envs import EnvBase, RenameTransform, TransformedEnv
from torchrl.envs.libs.pettingzoo import PettingZooWrapper

from mapets_rl.envs.parallel import FigureEightParallelEnv, FreewayParallelEnv, TrafficParallelEnv

SCENARIOS: dict[str, tuple[type[TrafficParallelEnv], dict[str, Any]]] = {
    "figure-eight": (FigureEightParallelEnv, {"lanes": 1}),
    "figure-eight-multilane": (FigureEightParallelEnv, {"lanes": 2, "n_cavs": 22}),
    "freeway": (FreewayParallelEnv, {}),
}
"""Scenario name -> (PettingZoo env class, default config)."""


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
    base = PettingZooWrapper(
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
