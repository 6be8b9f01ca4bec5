"""A scripted, crash-free CAV policy for the scenarios (demos, tests, communication studies)."""

from __future__ import annotations

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torchrl.data import OneHot
from torchrl.envs import EnvBase

from mapets_rl.envs.traffic import MultiAgentTrafficEnv


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
    Keep Lane for every CAV.
    """

    in_keys = [("agents", "observation")]
    out_keys = [("agents", "action")]

    def __init__(self, env: EnvBase) -> None:
        super().__init__()
        self.scenario = traffic_env(env)
        self.action_spec = env.full_action_spec[("agents", "action")]

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        action = torch.as_tensor(self.scenario.scripted_action())
        if isinstance(self.action_spec, OneHot):
            action = torch.nn.functional.one_hot(action.long(), self.action_spec.shape[-1])
        tensordict.set(
            ("agents", "action"), action.to(self.action_spec.dtype).reshape(self.action_spec.shape)
        )
        return tensordict
