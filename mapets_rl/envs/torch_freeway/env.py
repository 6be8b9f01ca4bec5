"""TorchRL env of the batched freeway: ``make_env(name, backend="torch", num_envs=B)``.

The keys, shapes and dtypes are those of the highway-env backend's env (``make_env(name)``,
:class:`~mapets_rl.envs.TrafficPettingZooWrapper`) with the batch dimension in front:
``("agents", "observation")`` ``[B, I, 22 | 24]``, ``("agents", "action")`` one-hot
``[B, I, 4]`` (or indices ``[B, I]``), ``("agents", "reward" | "done" | "terminated" |
"truncated")`` ``[B, I, 1]``, ``("agents", "mask")`` ``[B, I]``, ``("agents", "position")``
``[B, I, 2]``, ``("agents", "info", ...)`` and the root flags ``[B, 1]``. ``num_envs=None``
gives one road with no batch dimension, a drop-in for the highway-env env (evaluation, video).

A road whose episode ended is reset inside the batch when torchrl passes ``"_reset"`` (partial
reset: collectors never wait for the slowest road). After every step, :attr:`last_episode_metrics`
holds the metrics of the most recent episode that ended (as the highway-env env reports them);
:meth:`pop_finished_episodes` returns every episode that ended since it was last called.

The shield and the action that ran. With ``shield=True`` the simulator replaces every move
that its model predicts to crash by Keep Lane before the step (``BatchedFreeway.shield``):
post-posed shielding (Alshiekh et al. 2018, "Safe Reinforcement Learning via Shielding"), in
the variant where the learner is updated with the action that ran. ``_step`` rewrites the
input tensordict, which torchrl's ``EnvBase.step`` passes to it and returns with its
``"next"`` (so a collector stores it): ``("agents", "action")`` becomes the executed action
(Keep Lane where the shield replaced a move) and the proposed one is kept beside it under
``("agents", "proposed_action")`` (:data:`PROPOSED_ACTION`, in the action spec's form, declared
in the state spec), so an off-policy critic is fitted to the action whose reward it sees, and a
learner may still read what was proposed (with ``("agents", "info", "shielded")``). The
paper's other option, an update with the unsafe proposal and a punishment, is the learner's
(``shield_penalty`` of MADDPG and Shapley AC, :mod:`mapets_rl.experiment.shield_punishment`): a
penalty added to the reward here would be charged to Keep Lane, the action stored.
Only the tensordict that ``step`` is given is rewritten: ``env.step``, ``env.rollout`` and a
torchrl ``Collector`` whose policy and env share a device (the experiment runner's) store the
executed action; a ``TransformedEnv``, or a collector that moves its data to the env's device,
steps a copy and stores the proposed action under ``("agents", "action")`` (then
``("next", "agents", "info", "shielded")`` says which moves ran as Keep Lane). The slanted
ramp lane's ``CL`` / ``CR`` (and the acceleration lane's, without ``ramp_forcing``) are stored
as played: there they are ``KL`` by the scenario's rules (the same motion and the same comfort
reward), so the critic learns their true value, and rewriting them would leave those actions
untrained although the policy can still choose them.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch
from tensordict import TensorDict, TensorDictBase
from torch.nn.functional import one_hot
from torchrl.data import Categorical, Composite, OneHot, Unbounded
from torchrl.envs import EnvBase

from mapets_rl.envs.freeway import KL, FreewayEnv
from mapets_rl.envs.freeway_merge import BEHAVIOUR_COUNTS, FreewayMergeEnv
from mapets_rl.envs.torch_freeway.highway_state import draw_scene
from mapets_rl.envs.torch_freeway.simulator import BatchedFreeway, StepResult, check_roads_fit
from mapets_rl.envs.traffic import require
from mapets_rl.envs.validation import (
    check_device,
    check_flag,
    check_one_hot,
    check_seed,
    is_integer,
)

UNSUPPORTED = {"stock_neighbour_search": False}
"""highway-env keys the torch backend cannot honour, with the one value it accepts."""
RENDER_KEYS = frozenset(
    {"screen_width", "screen_height", "scaling", "centering_position", "offscreen_rendering"}
    | {"real_time_rendering", "show_trajectories", "render_agent"}
)
"""Keys that only change how a road is drawn (passed to the highway-env viewer)."""
INFO_KEYS = ("distance", "speed", "collided", "traffic_velocity", "traffic_comfort")
ACTION = ("agents", "action")
PROPOSED_ACTION = ("agents", "proposed_action")
"""Where a shielded env keeps the CAVs' proposed action; ``ACTION`` holds the executed one."""


def scenario_config(env_class: type[FreewayEnv], config: dict[str, Any]) -> dict[str, Any]:
    """The full, validated config of ``env_class`` with the user's ``config`` (the highway-env
    scenario's own checks; ValueError naming the key), refusing what the torch backend cannot
    honour."""
    for key, value in UNSUPPORTED.items():
        if config.get(key, value) != value:
            raise ValueError(
                f"{key}={config[key]!r} is a highway-env implementation switch the torch "
                f"backend cannot honour (only {value!r}); use backend='highway-env'"
            )
    merged = env_class.resolved_config(config)
    require(
        merged["n_cavs"] >= 1,
        f"cav_ratio={merged['cav_ratio']} with n_vehicles={merged['n_vehicles']} gives no CAV; "
        "the multi-agent env needs cav_ratio * n_vehicles >= 0.5",
    )
    return merged


class TorchFreewayEnv(EnvBase):
    """``B`` roads of ``freeway`` or ``freeway-merge`` as one TorchRL env (module docstring).

    Args:
        env_class: :class:`~mapets_rl.envs.FreewayEnv` or
            :class:`~mapets_rl.envs.FreewayMergeEnv` (the scenario whose config, checks and
            defaults apply).
        config: scenario config keys (as for the highway-env backend).
        num_envs: ``B`` roads, or None for one road without a batch dimension.
        device: where the roads are simulated and the outputs live.
        dtype: float precision of the simulation (float32; float64 for calibration).
        seed: seed of the first reset (``set_seed`` works as usual).
        categorical_actions: actions as indices ``[.., I]`` instead of one-hot ``[.., I, 4]``.
        render_mode: None or ``"rgb_array"`` (draws road 0 with highway-env's viewer).
        kernel: how a CPU simulator steps (``"auto"``, ``"native"``, ``"torch"``; see
            :class:`~mapets_rl.envs.torch_freeway.simulator.BatchedFreeway`).

    With ``shield=True`` a step leaves the executed action under ``("agents", "action")`` and
    the proposed one under ``("agents", "proposed_action")`` (post-posed shielding, the
    learner updated with the action that ran: module docstring).
    """

    def __init__(
        self,
        env_class: type[FreewayEnv],
        config: dict[str, Any] | None = None,
        num_envs: int | None = None,
        device: torch.device | str = "cpu",
        dtype: torch.dtype = torch.float32,
        seed: int | None = None,
        categorical_actions: bool = False,
        render_mode: str | None = None,
        kernel: str = "auto",
    ) -> None:
        require(
            num_envs is None or (is_integer(num_envs) and num_envs >= 1),
            f"num_envs must be an integer >= 1 (or None for one unbatched road), got {num_envs!r}",
        )
        num_envs = None if num_envs is None else int(num_envs)
        device = check_device(device)
        seed = check_seed(seed)
        categorical_actions = check_flag(categorical_actions, "categorical_actions")
        require(
            dtype in (torch.float32, torch.float64),
            f"dtype must be torch.float32 or torch.float64, got {dtype!r}",
        )
        require(
            render_mode in (None, "rgb_array"),
            f"render_mode must be None or 'rgb_array', got {render_mode!r}",
        )
        config = dict(config or {})
        self.render_config = {k: v for k, v in config.items() if k in RENDER_KEYS}
        self.scenario_class = env_class
        self.config = scenario_config(env_class, config)
        self.render_mode = render_mode
        merge = issubclass(env_class, FreewayMergeEnv)
        check_roads_fit(self.config, merge, num_envs or 1, device, dtype, "num_envs")
        batch = torch.Size([] if num_envs is None else [num_envs])
        super().__init__(device=device, batch_size=batch)
        self.sim = BatchedFreeway(
            self.config,
            merge=merge,
            num_roads=num_envs or 1,
            device=self.device,
            dtype=dtype,
            seed=0 if seed is None else seed,
            kernel=kernel,
        )
        self.categorical_actions = categorical_actions
        self.info_keys = INFO_KEYS + (("shielded",) if self.config["shield"] else ())
        self.last_episode_metrics: dict[str, float] = {}
        self._finished: list[dict[str, float]] = []
        self._viewer_env: FreewayEnv | None = None
        self._make_specs()
        if seed is not None:
            self.set_seed(seed)

    # --- specs ---------------------------------------------------------------------------------
    def _make_specs(self) -> None:
        batch, n = self.batch_size, self.sim.n_cavs
        group = (*batch, n)
        dev = self.device

        def unbounded(*shape: int) -> Unbounded:
            return Unbounded(shape=torch.Size(shape), dtype=torch.float32, device=dev)

        def flag(*shape: int) -> Categorical:
            return Categorical(2, shape=torch.Size(shape), dtype=torch.bool, device=dev)

        info = Composite(
            {key: unbounded(*group) for key in self.info_keys},
            shape=torch.Size(group),
            device=dev,
        )
        self.observation_spec = Composite(
            agents=Composite(
                observation=unbounded(*group, self.sim.obs_dim),
                mask=flag(*group),
                info=info,
                position=unbounded(*group, 2),
                shape=torch.Size(group),
                device=dev,
            ),
            shape=batch,
            device=dev,
        )
        if self.categorical_actions:
            action = Categorical(4, shape=torch.Size(group), dtype=torch.int64, device=dev)
        else:
            action = OneHot(4, shape=torch.Size((*group, 4)), dtype=torch.int64, device=dev)
        self.action_spec = Composite(
            agents=Composite(action=action, shape=torch.Size(group), device=dev),
            shape=batch,
            device=dev,
        )
        if self.config["shield"]:
            self.state_spec = Composite(
                agents=Composite(
                    proposed_action=action.clone(), shape=torch.Size(group), device=dev
                ),
                shape=batch,
                device=dev,
            )
        self.reward_spec = Composite(
            agents=Composite(reward=unbounded(*group, 1), shape=torch.Size(group), device=dev),
            shape=batch,
            device=dev,
        )
        flags = {key: flag(*group, 1) for key in ("done", "terminated", "truncated")}
        self.done_spec = Composite(
            {key: flag(*batch, 1) for key in ("done", "terminated", "truncated")},
            agents=Composite(flags, shape=torch.Size(group), device=dev),
            shape=batch,
            device=dev,
        )

    # --- torchrl hooks ---------------------------------------------------------------------------
    def _set_seed(self, seed: int | None) -> None:
        self.sim.generator.manual_seed(0 if seed is None else int(seed))

    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs: Any) -> TensorDictBase:
        mask = torch.ones(self.sim.n_roads, dtype=torch.bool, device=self.device)
        if tensordict is not None:
            reset = tensordict.get("_reset", None)
            if reset is not None:
                mask = self._roads_to_reset(reset, "_reset", 1)
            elif (reset := tensordict.get(("agents", "_reset"), None)) is not None:
                mask = self._roads_to_reset(reset, "('agents', '_reset')", self.sim.n_cavs)
        self.sim.reset(mask)
        acting = self.sim.state["agents"].get("alive")
        false = torch.zeros_like(acting)
        zeros = torch.zeros(acting.shape, dtype=torch.float32, device=self.device)
        speed = self.sim.state["bodies"].get("speed").gather(1, self.sim.state["agents"]["slot"])
        info = {key: zeros for key in self.info_keys}
        info["speed"] = speed.float()
        return self._output(self.sim.observe(acting), info, acting, false, false)

    def _roads_to_reset(self, reset: Any, key: str, per_road: int) -> torch.Tensor:
        """The roads ``[B]`` that a partial reset's ``key`` asks for: a bool tensor of
        ``B * per_road`` entries (``[B]`` or ``[B, 1]`` at the root, ``[B, I]`` or ``[B, I, 1]``
        per agent; a road resets where any of its entries is True)."""
        roads = self.sim.n_roads
        if (
            not isinstance(reset, torch.Tensor)
            or reset.dtype != torch.bool
            or reset.numel() != roads * per_road
            or reset.shape[:1] != (roads,)
        ):
            shape = f"[{roads}]" if per_road == 1 else f"[{roads}, {per_road}]"
            got = (
                f"dtype {reset.dtype}, shape {list(reset.shape)}"
                if isinstance(reset, torch.Tensor)
                else type(reset).__name__
            )
            raise ValueError(
                f"{key} must be a bool tensor {shape} (one entry per road"
                f"{'' if per_road == 1 else ' and CAV'}, True where it resets), got {got}"
            )
        return reset.reshape(roads, -1).any(-1).to(self.device)

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        action = tensordict.get(ACTION, None)
        if action is None:
            raise ValueError(
                "step needs the CAVs' actions under ('agents', 'action'); the tensordict has none"
            )
        spec = self.full_action_spec[ACTION]
        if action.shape != spec.shape:
            raise ValueError(
                f"('agents', 'action') must have shape {list(spec.shape)}, got {list(action.shape)}"
            )
        if self.categorical_actions:
            require(
                not action.dtype.is_floating_point and action.dtype != torch.bool,
                f"('agents', 'action') must hold integer indices (KL, CL, CR, ES), got "
                f"dtype {action.dtype}",
            )
            index = action
        else:
            check_one_hot(action)
            index = (action.to(torch.int8) if action.dtype == torch.bool else action).argmax(-1)
        require(
            bool(((index >= 0) & (index <= 3)).all()),
            "('agents', 'action') values must be integers in [0, 3] (KL, CL, CR, ES)",
        )
        result = self.sim.step(index.reshape(self.sim.n_roads, -1))
        if self.config["shield"]:
            self._record_executed(tensordict, action, index, result.shielded)
        self._record_episodes(result)
        terminated = ~result.alive
        truncated = torch.where(result.acting, result.truncated.unsqueeze(-1) & ~terminated, True)
        speed = self.sim.state["bodies"].get("speed").gather(1, self.sim.state["agents"]["slot"])
        acting = result.acting.float()
        info = {
            "distance": result.distance.float() * acting,
            "speed": (speed * result.alive).float() * acting,
            "collided": result.collided.float() * acting,
            "traffic_velocity": result.traffic_velocity.float().unsqueeze(-1) * acting,
            "traffic_comfort": result.traffic_comfort.float().unsqueeze(-1) * acting,
        }
        if self.config["shield"]:
            info["shielded"] = result.shielded.float() * acting
        return self._output(
            result.observation, info, result.acting, terminated, truncated, result.reward
        )

    def _output(
        self,
        observation: torch.Tensor,
        info: dict[str, torch.Tensor],
        acting: torch.Tensor,
        terminated: torch.Tensor,
        truncated: torch.Tensor,
        reward: torch.Tensor | None = None,
    ) -> TensorDict:
        """The output TensorDict from ``[R, I, ...]`` tensors (``R`` roads), reshaped to the
        env's batch."""
        batch = self.batch_size
        group = torch.Size((*batch, self.sim.n_cavs))
        dev = self.device

        def shaped(value: torch.Tensor, *tail: int) -> torch.Tensor:
            return value.reshape(*group, *tail)

        done = terminated | truncated
        entries = {
            "observation": shaped(observation, self.sim.obs_dim),
            "mask": shaped(~done),
            "position": shaped(self.sim.positions().float(), 2),
            "done": shaped(done, 1),
            "terminated": shaped(terminated, 1),
            "truncated": shaped(truncated, 1),
            "info": TensorDict._new_unsafe(
                {key: shaped(value) for key, value in info.items()}, batch_size=group, device=dev
            ),
        }
        if reward is not None:
            entries["reward"] = shaped(reward.float(), 1)
        root = {
            "done": done.all(-1).reshape(*batch, 1),
            "terminated": terminated.all(-1).reshape(*batch, 1),
            "truncated": truncated.all(-1).reshape(*batch, 1),
        }
        agents = TensorDict._new_unsafe(entries, batch_size=group, device=dev)
        return TensorDict._new_unsafe({"agents": agents, **root}, batch_size=batch, device=dev)

    def _record_executed(
        self,
        tensordict: TensorDictBase,
        proposed: torch.Tensor,
        index: torch.Tensor,
        replaced: torch.Tensor,
    ) -> None:
        """Write the executed action into ``tensordict`` under :data:`ACTION` (Keep Lane where
        the shield replaced a move, ``replaced [R, I]``, else the ``proposed`` action
        ``[*batch, I, 4]`` one-hot or ``[*batch, I]`` indices, in its dtype, the policy's) and
        the proposed decisions ``index [*batch, I]`` under :data:`PROPOSED_ACTION`, in the
        form and dtype of its spec (int64: a collector preallocates that key from the spec)."""
        replaced = replaced.reshape(index.shape)
        spec = self.full_state_spec[PROPOSED_ACTION]
        if self.categorical_actions:
            executed = torch.where(replaced, KL, proposed)
            tensordict.set(PROPOSED_ACTION, index.to(spec.dtype))
        else:
            keep = (torch.arange(proposed.shape[-1], device=proposed.device) == KL).to(proposed)
            executed = torch.where(replaced.unsqueeze(-1), keep, proposed)
            tensordict.set(PROPOSED_ACTION, one_hot(index, proposed.shape[-1]).to(spec.dtype))
        tensordict.set(ACTION, executed)

    # --- episodes ------------------------------------------------------------------------------
    def _record_episodes(self, result: StepResult) -> None:
        ended = (result.truncated | result.terminated).nonzero().squeeze(-1).tolist()
        if not ended:
            return
        metrics = {k: v.cpu() for k, v in self.sim.episode_metrics().items()}
        for road in ended:
            episode = {key: float(value[road]) for key, value in metrics.items()}
            for key in ("collisions", "ramp_stuck", "shielded", *BEHAVIOUR_COUNTS):
                if key in episode:
                    episode[key] = int(episode[key])
            self._finished.append(episode)
        self.last_episode_metrics = self._finished[-1]
        del self._finished[: -max(self.sim.n_roads * 16, 1024)]

    def pop_finished_episodes(self) -> list[dict[str, float]]:
        """The metrics of every episode that ended since the last call (roads in index order
        within a step; at most the last ``max(16 B, 1024)`` are kept)."""
        finished, self._finished = self._finished, []
        return finished

    # --- branching ----------------------------------------------------------------------------
    def snapshot(self) -> TensorDict:
        """The whole state of every road (the random generator's included), for :meth:`restore`:
        the same state and actions give the same next state, bit for bit."""
        return self.sim.snapshot()

    def restore(self, snapshot: TensorDict) -> TensorDictBase:
        """Return every road to ``snapshot`` and give the observation there (the output of a
        reset at that state, with ``done`` where the episode had ended)."""
        self.sim.restore(snapshot)
        agents = self.sim.state["agents"]
        alive = agents.get("alive")
        steps = self.sim.state.get("steps")
        truncated_road = steps >= int(self.config["horizon"])
        terminated = ~alive
        truncated = torch.where(alive, truncated_road.unsqueeze(-1), True)
        zeros = torch.zeros(alive.shape, dtype=torch.float32, device=self.device)
        info = {key: zeros for key in self.info_keys}
        return self._output(self.sim.observe(alive), info, alive, terminated, truncated)

    # --- rendering ----------------------------------------------------------------------------
    def render(self) -> np.ndarray | None:
        """Road 0 drawn by highway-env's viewer (``render_mode="rgb_array"``): an RGB frame
        ``[H, W, 3]``; None without a render mode."""
        if self.render_mode is None:
            return None
        if self._viewer_env is None:
            user = {k: self.config[k] for k in self.scenario_class.user_keys()}
            self._viewer_env = self.scenario_class(
                {**user, **self.render_config}, render_mode="rgb_array"
            )
            self._viewer_env.reset(seed=0)
        draw_scene(self.sim, 0, self._viewer_env)
        return self._viewer_env.render()

    def close(self, *, raise_if_closed: bool = True) -> None:
        if self._viewer_env is not None:
            self._viewer_env.close()
            self._viewer_env = None
        super().close(raise_if_closed=raise_if_closed)
