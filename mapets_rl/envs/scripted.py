"""A scripted, crash-free CAV policy for the scenarios (demos, tests, communication studies)."""

from __future__ import annotations

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torchrl.data import OneHot
from torchrl.envs import EnvBase

from mapets_rl.envs.torch_freeway.env import TorchFreewayEnv
from mapets_rl.envs.traffic import MultiAgentTrafficEnv


def scenario_config(env: EnvBase) -> dict:
    """The scenario config of a (transformed) env made by ``make_env``, either backend."""
    base = env.base_env if hasattr(env, "base_env") else env
    if isinstance(base, TorchFreewayEnv):
        return dict(base.config)
    return dict(traffic_env(env).config)


def traffic_env(env: EnvBase) -> MultiAgentTrafficEnv:
    """The highway-env scenario inside a (transformed) env made by ``make_env``."""
    base = env.base_env if hasattr(env, "base_env") else env
    parallel = getattr(base, "_env", None)
    scenario = getattr(parallel, "env", None)
    if not isinstance(scenario, MultiAgentTrafficEnv):
        raise ValueError(
            "env must be a single (non-batched) env made by mapets_rl.envs.make_env, "
            f"got {type(env).__name__}"
        )
    return scenario


class ScriptedCAVPolicy(TensorDictModuleBase):
    """Drives every CAV like a careful human driver: IDM + first come, first served.

    Reads the simulator state of ``env`` (so it works on one unbatched env made by
    ``make_env``) and writes ``("agents", "action")``: on the figure-eight the target speed that
    makes each CAV follow IDM and yield at the crossing (never changing lanes); on the freeway
    Keep Lane for every CAV (on either backend, batched or not).
    """

    in_keys = [("agents", "observation")]
    out_keys = [("agents", "action")]

    def __init__(self, env: EnvBase) -> None:
        super().__init__()
        base = env.base_env if hasattr(env, "base_env") else env
        self.scenario = None if isinstance(base, TorchFreewayEnv) else traffic_env(env)
        self.action_spec = env.full_action_spec[("agents", "action")]

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        if self.scenario is None:  # the batched freeway: Keep Lane (0) for every CAV
            shape = self.action_spec.shape[:-1] if isinstance(self.action_spec, OneHot) else (
                self.action_spec.shape)  # fmt: skip
            action = torch.zeros(shape, dtype=torch.long)
        else:
            action = torch.as_tensor(self.scenario.scripted_action())
        if isinstance(self.action_spec, OneHot):
            action = torch.nn.functional.one_hot(action.long(), self.action_spec.shape[-1])
        tensordict.set(
            ("agents", "action"), action.to(self.action_spec.dtype).reshape(self.action_spec.shape)
        )
        return tensordict
