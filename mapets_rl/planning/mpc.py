"""The MA-PETS planner as a policy module: CEM + trajectory sampling, warm-started MPC.

:class:`TrajectorySamplingCEM` reads observations from a TensorDict and writes actions. It keeps
the warm start and composes the two pieces it is made of, as mbrl-lib splits PETS:
:class:`~mapets_rl.planning.CEMOptimizer` (the optimiser over ``[I, M, Q, H, act]``) and
:func:`~mapets_rl.planning.trajectory_sampling_returns` (the scores of candidate sequences).
All agents (and all envs of a batched env) are planned by one batched tensor program; the only
Python loops are over CEM iterations and horizon steps.
"""

from __future__ import annotations

import contextlib
import logging
import warnings
from collections.abc import Sequence
from typing import Any

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from tensordict.utils import NestedKey

from mapets_rl.memory import check_memory
from mapets_rl.modules.tensor_checks import as_mask, check_finite, check_real, get_tensor
from mapets_rl.planning.cem import CEMOptimizer, kept_elite_count
from mapets_rl.planning.compiled import CompiledStep
from mapets_rl.planning.config import PlannerConfig
from mapets_rl.planning.cuda_graph import GraphedStep
from mapets_rl.planning.precision import resolve_dtype
from mapets_rl.planning.trajectory_sampling import (
    DynamicsModel,
    RewardFn,
    StepFn,
    TerminationFn,
    expected_trajectory,
    propagate_step,
    trajectory_sampling_returns,
)

__all__ = ["TrajectorySamplingCEM"]

log = logging.getLogger(__name__)


_TORCH_DTYPES = {torch.float32: "fp32", torch.bfloat16: "bf16"}
_CONFIG_FIELDS = frozenset(PlannerConfig.field_names())


def _planner_config(config: PlannerConfig | None, settings: dict[str, Any]) -> PlannerConfig:
    """``config`` (default: ``PlannerConfig()``) with ``settings`` replacing its fields,
    validated by :class:`PlannerConfig`; a torch ``dtype`` is read as its name."""
    known = PlannerConfig.field_names()
    unknown = sorted(set(settings) - set(known))
    if unknown:
        raise TypeError(
            f"TrajectorySamplingCEM got unknown planner setting(s) {unknown}; the settings "
            f"are the PlannerConfig fields {list(known)}."
        )
    dtype = settings.get("dtype")
    if isinstance(dtype, torch.dtype):
        if dtype not in _TORCH_DTYPES:
            raise ValueError(f"dtype must be torch.float32 or torch.bfloat16, got {dtype}.")
        settings = {**settings, "dtype": _TORCH_DTYPES[dtype]}
    config = PlannerConfig() if config is None else config
    return config.replace(**settings) if settings else config


def _model_device(model: DynamicsModel, bounds: object) -> torch.device:
    """The device of ``model``'s tensors (a module's parameters/buffers), else of ``bounds``."""
    if isinstance(model, torch.nn.Module):
        for tensor in (*model.parameters(), *model.buffers()):
            return tensor.device
    return torch.as_tensor(bounds).device


class TrajectorySamplingCEM(TensorDictModuleBase):
    """Batched multi-agent PETS planner: CEM over action sequences scored by TS rollouts.

    Reads ``("agents", "observation")`` ``[*, I, obs]`` and writes ``("agents", "action")``
    ``[*, I, act]`` (``*`` may be empty or the batch of a batched env). For each agent
    ``i`` the planner keeps a Gaussian ``N(mu, sigma)`` over ``w``-step action sequences
    ``[w, act]`` and iterates (Algorithm 1, lines 6-12):

    1. sample ``Q`` candidates, clipped to the action bounds;
    2. propagate ``P`` particles per candidate through agent ``i``'s ensemble
       (``ts_inf``: particle ``p`` always uses member ``p mod B``; ``ts1``: members re-drawn
       at every step; ``expectation``: one deterministic trajectory through the ensemble mean);
    3. score ``J = 1/P sum_p sum_t r(s_{p,t}, a_t, s_{p,t+1})`` (eq. 10); with a
       ``termination_fn`` a particle's sum stops after the step at which it predicts a
       termination (that step's reward counts, later ones do not, as mbrl-lib's
       ``ModelEnv``); NaN scores -> -inf; non-finite predicted rewards are counted per agent
       in the ``nonfinite_rewards`` buffer ``[I]`` (a warning names the agents once);
    4. refit ``mu, sigma`` to the ``X`` best candidates with momentum ``alpha``:
       ``mu <- alpha mu + (1 - alpha) mean(elites)`` (same for sigma);

    for at most ``iterations`` rounds, stopping early once every sigma is below ``epsilon``.
    The first action of ``mu`` is executed (line 13) and ``mu`` shifted by one step warm-starts
    the next call. Call :meth:`reset` at episode start (an ``"is_init"`` entry ``[*, 1]`` in the
    input, as written by torchrl's ``InitTracker``, resets the matching envs automatically).

    iCEM's options (Pinneri et al. 2020; all off by default, see
    :class:`~mapets_rl.planning.PlannerConfig`; with any of them on the planner optimises with
    an :class:`~mapets_rl.planning.ICEMOptimizer`): anchor candidates and keep-best; colored
    candidate noise (``noise_beta``); ``K`` elites kept from each iteration for the next
    (``keep_elites``) and the last iteration's ``K``, shifted by one step, added to the next
    decision's first iteration (``shift_elites``; state ``warm_start_elites``
    ``[*, I, K, w, act]``, reset with the warm start); a decaying population
    (``population_decay``). The warm start (mean and elites) lives in memory only: it is not
    part of ``state_dict`` or any checkpoint.

    Random numbers are common to all agents and envs of a call (every planning problem sees
    the same candidate noise and particle noise), so agent ``i``'s decision in a batched call
    equals a single-agent call with the same seed; problems are independent, so this changes
    no agent's marginal behaviour. The particle noise is also common to the candidates of one
    CEM iteration (particle ``p`` draws the same standard-normal noise whichever candidate it
    follows): candidates are compared under common random numbers, so that elite selection
    ranks action sequences rather than noise draws.

    Args:
        model: the agents' dynamics, any :class:`~mapets_rl.planning.DynamicsModel` (e.g. a
            :class:`~mapets_rl.models.ProbabilisticEnsemble`).
        reward_fn: vectorized known reward ``(obs, action, next_obs) -> reward``, shapes
            ``[..., obs]``, ``[..., act]``, ``[..., obs]`` -> ``[...]``.
        termination_fn: optional vectorized known termination ``(obs, action, next_obs) ->
            done`` (same shapes, bool): a predicted termination (a crash) ends the particle.
            Both functions are dry-called on a dummy batch at construction: a wrong output
            shape raises ``ValueError`` before any planning.
        action_low / action_high: bounds, scalars or ``[act]`` / ``[I, act]`` tensors,
            ``low < high`` elementwise.
        config: the planner's settings (:class:`~mapets_rl.planning.PlannerConfig`, Table II
            names ``w, Q, X, Y, P``; default: its defaults, the paper's sizes). Every setting
            is declared, defaulted and validated there, once. The planner keeps it, frozen, in
            :attr:`config`: a setting changes only by replacing the whole config,
            ``planner.config = planner.config.replace(elites=8)`` (validated again); setting a
            field on the planner (``planner.elites = 8``) raises AttributeError. The config
            chooses the optimiser (:meth:`~mapets_rl.planning.PlannerConfig.make_optimizer`:
            the paper's CEM, or iCEM's with its options on), kept in ``optimizer``.
        **settings: :class:`~mapets_rl.planning.PlannerConfig` fields that replace the
            config's (``horizon=3, population=8``); ``dtype`` may also be ``torch.float32`` /
            ``torch.bfloat16``. The planner keeps the resolved compute dtype and the reason
            for it in ``dtype`` / ``dtype_reason`` (states, rewards and CEM statistics stay
            float32).
        seed / generator: reproducible randomness (``generator`` wins if both are given).
        observation_key / action_key / is_init_key: TensorDict keys.
    """

    def __init__(
        self,
        model: DynamicsModel,
        reward_fn: RewardFn,
        action_low: float | Sequence[float] | torch.Tensor,
        action_high: float | Sequence[float] | torch.Tensor,
        config: PlannerConfig | None = None,
        *,
        seed: int | None = None,
        generator: torch.Generator | None = None,
        termination_fn: TerminationFn | None = None,
        observation_key: NestedKey = ("agents", "observation"),
        action_key: NestedKey = ("agents", "action"),
        is_init_key: NestedKey = "is_init",
        **settings: Any,
    ) -> None:
        if not isinstance(model, DynamicsModel):
            raise ValueError(
                "model must provide n_agents, obs_dim, action_dim, ensemble_size and "
                f"predict(obs, action, dtype) (DynamicsModel), got {type(model).__name__}."
            )
        if not callable(reward_fn):
            raise ValueError("reward_fn must be callable (obs, action, next_obs) -> reward.")
        if termination_fn is not None and not callable(termination_fn):
            raise ValueError("termination_fn must be callable (obs, action, next_obs) -> done.")
        config = _planner_config(config, settings)
        device = _model_device(model, action_low)
        low = torch.as_tensor(action_low, dtype=torch.float32, device=device)
        high = torch.as_tensor(action_high, dtype=torch.float32, device=device)
        for name, bound in (("action_low", low), ("action_high", high)):
            if not bool(torch.isfinite(bound).all()):
                raise ValueError(
                    f"{name} must be finite in every dimension (CEM samples around the centre "
                    f"of the box), got {bound.tolist()}."
                )
        act = model.action_dim
        try:
            low, high = (torch.broadcast_to(b, (model.n_agents, act)).clone() for b in (low, high))
        except RuntimeError as err:
            raise ValueError(
                f"action_low/action_high must broadcast to [n_agents={model.n_agents}, "
                f"action_dim={act}], got {tuple(low.shape)} and {tuple(high.shape)}."
            ) from err
        if not bool((low < high).all()):
            raise ValueError("action_low must be < action_high in every dimension.")
        super().__init__()
        self.model = model
        self.reward_fn = reward_fn
        self.termination_fn = termination_fn
        if generator is None and seed is not None:
            generator = torch.Generator(device=device)
            generator.manual_seed(seed)
        self.generator = generator
        self.in_keys = [observation_key]
        self.out_keys = [action_key]
        self.is_init_key = is_init_key
        self._with_schedule = False  # whether this call's _optimize inputs hold a schedule
        # Bounds as [I, 1, 1, act] so they broadcast over [I, M, (Q,) H, act].
        self.register_buffer("action_low", low[:, None, None, :])
        self.register_buffer("action_high", high[:, None, None, :])
        self._mean: torch.Tensor | None = None  # [I, M, H, act] warm start
        self._solution: torch.Tensor | None = None  # [I, M, H, act] last optimised mean
        # With keep_elites and shift_elites: the last decision's kept elites shifted by one
        # step [I, M, K, H, act] (the next call ignores those of envs it resets).
        self._elites: torch.Tensor | None = None
        self._batch_shape: torch.Size | None = None
        self._warned_nonfinite = False
        self.register_buffer(
            "nonfinite_rewards", torch.zeros(model.n_agents, dtype=torch.long, device=device)
        )
        self._config: PlannerConfig | None = None
        self._graphed: GraphedStep | None = None
        self._step: StepFn = propagate_step
        self.config = config
        self._check_model_fns(device)

    def __setattr__(self, name: str, value: Any) -> None:
        """Refuse to set a :class:`PlannerConfig` field as an attribute (``planner.elites =
        50``): the settings change only as a whole, validated, through :attr:`config`."""
        if name in _CONFIG_FIELDS:
            raise AttributeError(
                f"{name} is a PlannerConfig setting, not an attribute of the planner: replace "
                f"the config, validated, with planner.config = planner.config.replace({name}=...)"
            )
        super().__setattr__(name, value)

    @property
    def config(self) -> PlannerConfig:
        """The planner's settings (a frozen :class:`~mapets_rl.planning.PlannerConfig`)."""
        return self._config

    @config.setter
    def config(self, config: PlannerConfig) -> None:
        """Plan with ``config`` from the next decision on (``planner.config =
        planner.config.replace(elites=8)``; the PlannerConfig has validated its own fields).
        Checked here against the model and the device: the particle layout over the ensemble,
        ``cuda_graph`` on a CUDA device and the memory of one decision (ValueError). Builds the
        optimiser (:meth:`PlannerConfig.make_optimizer`) and the rollout step; a new horizon
        forgets the warm start (:meth:`reset`)."""
        if not isinstance(config, PlannerConfig):
            raise TypeError(f"config must be a PlannerConfig, got {type(config).__name__}.")
        model, device = self.model, self.action_low.device
        layout = config.layout_error(model.ensemble_size)
        if layout is not None:
            raise ValueError(f"{layout}.")
        if config.cuda_graph and device.type != "cuda":
            raise ValueError(
                f"cuda_graph=True needs the model on a CUDA device, got it on {device} "
                "(move the model with .cuda() first, or leave cuda_graph False)."
            )
        check_memory(  # a planner built from the Python API gets the estimate MA-PETS makes
            config.decision_bytes(
                model.n_agents, model.obs_dim, model.action_dim, getattr(model, "hidden", ())
            ),
            device,
            f"the tensors of one planner decision (population={config.population} x particles="
            f"{config.particles} x horizon={config.horizon}, {model.n_agents} agents)",
            "lower population, particles or horizon",
        )
        self._dtype, self.dtype_reason = resolve_dtype(config.dtype, device)
        previous = self._config
        if previous is None or previous.cuda_graph != config.cuda_graph:
            self._graphed = GraphedStep(device, self.generator) if config.cuda_graph else None
        if previous is None or previous.compile != config.compile:
            # compile fuses a CPU step; on an accelerator cuda_graph is the tool (inductor's GPU
            # backend is not tested here), so the step stays eager there.
            compiled = config.compile and device.type == "cpu"
            if config.compile and not compiled:
                log.info(
                    "planner compile applies to CPU planning; the %s step runs eagerly", device
                )
            self._step = CompiledStep() if compiled else propagate_step
        if previous is not None and previous.horizon != config.horizon:
            self.reset()
        self._optimizer = config.make_optimizer(self.generator)
        self._config = config

    @property
    def dtype(self) -> torch.dtype:
        """The compute dtype of the ensemble forward (``config.dtype`` resolved on the model's
        device; why: :attr:`dtype_reason`)."""
        return self._dtype

    def _check_model_fns(self, device: torch.device) -> None:
        """Dry-call ``reward_fn`` (and ``termination_fn``) on a dummy batch ``[I, 2, *]``: a
        wrong output shape or dtype fails here, before any episode runs."""
        model = self.model
        obs = torch.zeros(model.n_agents, 2, model.obs_dim, device=device)
        action = self.action_low[:, 0].expand(-1, 2, -1)
        expected = (model.n_agents, 2)
        for name, fn in (("reward_fn", self.reward_fn), ("termination_fn", self.termination_fn)):
            if fn is None:
                continue
            out = fn(obs, action, obs)
            if not isinstance(out, torch.Tensor) or tuple(out.shape) != expected:
                shape = tuple(out.shape) if isinstance(out, torch.Tensor) else type(out).__name__
                raise ValueError(
                    f"{name} must map obs [..., {model.obs_dim}], action "
                    f"[..., {model.action_dim}], next_obs [..., {model.obs_dim}] to a tensor "
                    f"[...]; on inputs [{model.n_agents}, 2, *] it returned {shape}."
                )
            if name == "termination_fn" and out.dtype != torch.bool:
                raise ValueError(f"termination_fn must return a bool tensor, got {out.dtype}.")

    def _warn_nonfinite(self) -> None:
        """Warn once (per planner) naming the agents whose predicted rewards were NaN/inf."""
        if self._warned_nonfinite or not bool(self.nonfinite_rewards.any()):
            return
        self._warned_nonfinite = True
        agents = torch.nonzero(self.nonfinite_rewards).flatten().tolist()
        warnings.warn(
            f"reward_fn returned NaN or inf on predicted trajectories of agent(s) {agents} "
            f"({int(self.nonfinite_rewards.sum())} rewards so far); such candidates score -inf. "
            "See the planner's nonfinite_rewards counter.",
            RuntimeWarning,
            stacklevel=4,
        )

    # ------------------------------------------------------------------ state
    def reset(self) -> None:
        """Forget the warm start (call at episode start)."""
        self._mean = None
        self._solution = None
        self._elites = None
        self._batch_shape = None

    def _to_batch_layout(self, plan: torch.Tensor | None) -> torch.Tensor | None:
        """``[I, M, H, act]`` -> ``[*, I, H, act]``."""
        if plan is None:
            return None
        return plan.transpose(0, 1).reshape(
            *self._batch_shape, self.model.n_agents, self.config.horizon, self.model.action_dim
        )

    @property
    def optimizer(self) -> CEMOptimizer:
        """The optimiser that ``config.optimizer`` names, built with the config (a
        :class:`~mapets_rl.planning.CEMOptimizer` or its ICEMOptimizer subclass)."""
        return self._optimizer

    @property
    def last_iterations(self) -> int:
        """CEM iterations run by the last call (early stopping may cut them short)."""
        return self._optimizer.last_iterations

    @property
    def warm_start_mean(self) -> torch.Tensor | None:
        """The shifted plan that seeds the next call, ``[*, I, horizon, act]`` (or ``None``)."""
        return self._to_batch_layout(self._mean)

    @property
    def warm_start_elites(self) -> torch.Tensor | None:
        """The last decision's kept elites shifted by one step, which join the next call's
        first CEM iteration (except in envs it resets by ``is_init``): ``[*, I, K, horizon,
        act]``; ``None`` before the first call, after :meth:`reset` and without ``keep_elites``
        / ``shift_elites``."""
        if self._elites is None:
            return None
        return self._elites.transpose(0, 1).reshape(
            *self._batch_shape, *self._elites.shape[:1], *self._elites.shape[2:]
        )

    def _schedule_layout(
        self, schedule: torch.Tensor | None, batch_shape: torch.Size
    ) -> torch.Tensor | None:
        """``[*, I, H, obs]`` -> ``[I, M, H, obs]`` float32, checked (None stays None)."""
        if schedule is None:
            return None
        n_agents, obs_dim, horizon = self.model.n_agents, self.model.obs_dim, self.config.horizon
        expected = (*batch_shape, n_agents, horizon, obs_dim)
        if tuple(schedule.shape) != expected:
            raise ValueError(
                f"schedule must be shaped {list(expected)} ([*, n_agents, horizon, obs_dim], "
                f"NaN where the model predicts), got {list(schedule.shape)}."
            )
        check_real("schedule", schedule, f"{list(expected)}")
        if bool(torch.isinf(schedule).any()):
            raise ValueError("schedule must hold finite values or NaN (no inf).")
        return schedule.reshape(-1, n_agents, horizon, obs_dim).transpose(0, 1).float()

    def expected_states(
        self,
        obs: torch.Tensor,
        schedule: torch.Tensor | None = None,
        sequences: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """The states the last call's optimised sequences lead to through the members' mean
        (no noise; :func:`~mapets_rl.planning.expected_trajectory`): what each agent expects of
        its own plan, e.g. to broadcast it.

        Args:
            obs: ``[*, I, obs]`` the observations of that call; schedule: its schedule.
            sequences: ``[*, I, H, act]`` action sequences to roll instead of the optimised
                ones (e.g. :attr:`last_solution` with some agents' actions overruled).

        Returns:
            ``[*, I, H, obs]`` (index ``t``: the state after step ``t``).
        """
        if self._solution is None:
            raise RuntimeError("expected_states needs a plan first: call plan() or forward().")
        n_agents, obs_dim = self.model.n_agents, self.model.obs_dim
        obs_p = obs.reshape(-1, n_agents, obs_dim).transpose(0, 1).float()
        known = self._schedule_layout(schedule, obs.shape[:-2])
        solution = self._solution
        if sequences is not None:
            if tuple(sequences.shape) != tuple(self.last_solution.shape):
                raise ValueError(
                    f"sequences must be shaped like last_solution "
                    f"{list(self.last_solution.shape)}, got {list(sequences.shape)}"
                )
            solution = sequences.reshape(-1, n_agents, *solution.shape[2:])  # [M, I, H, act]
            solution = solution.transpose(0, 1).to(self._solution.dtype)
        frozen = getattr(self.model, "frozen_parameters", None)
        with frozen(self.dtype) if frozen is not None else contextlib.nullcontext():
            states = expected_trajectory(
                self.model, obs_p, solution, dtype=self.dtype, schedule=known
            )
        return states.transpose(0, 1).reshape(*obs.shape[:-2], n_agents, -1, obs_dim)

    @property
    def last_solution(self) -> torch.Tensor | None:
        """The last call's optimised mean sequence, ``[*, I, horizon, act]`` (or ``None``)."""
        return self._to_batch_layout(self._solution)

    @property
    def cuda_graph(self) -> bool:
        """Whether decisions replay a captured CUDA graph."""
        return self._graphed is not None

    @property
    def compiled_step(self) -> CompiledStep | None:
        """The compiled rollout step (``compile=True``; its ``compiles``, ``compile_seconds``
        and ``fallback_reason``), else ``None``."""
        return self._step if isinstance(self._step, CompiledStep) else None

    @property
    def graph_captures(self) -> int:
        """CUDA-graph captures so far (0 without ``cuda_graph``)."""
        return 0 if self._graphed is None else self._graphed.captures

    def _anchors(self, mean: torch.Tensor) -> torch.Tensor:
        """``[I, M, 2, H, act]`` the noise-free fallbacks scored in every CEM iteration: the
        constant sequence at ``action_low`` (on the figure-eight: stop, keep the lane) and the
        warm start ``mean [I, M, H, act]``'s first action held for the whole horizon."""
        horizon = self.config.horizon
        low = self.action_low.expand(-1, mean.shape[1], horizon, -1)
        hold = mean[:, :, :1].expand(-1, -1, horizon, -1)
        return torch.stack([low, hold], dim=2)

    def _initial_mean(self, envs: int) -> torch.Tensor:
        """``[I, M, H, act]`` centre of the action box."""
        centre = (self.action_low + self.action_high) / 2  # [I, 1, 1, act]
        return centre.expand(-1, envs, self.config.horizon, -1).clone()

    def _shifted_elites(self, envs: int, reset: torch.Tensor | None) -> tuple[torch.Tensor, ...]:
        """The previous decision's shifted elites ``[I, M, K, H, act]`` and whether each env
        has them, bool ``[1, M, 1]`` (not those ``reset [1, M, 1, 1]`` restarts); ``()``
        without ``keep_elites`` / ``shift_elites``. Before the first decision (or after a change
        of ``K``) placeholders of the same shape, all absent: the shapes stay fixed."""
        config = self.config
        kept = kept_elite_count(config.keep_elites, config.elites) if config.shift_elites else 0
        if not kept:
            self._elites = None
            return ()
        device = self._mean.device
        if self._elites is None or self._elites.shape[2] != kept:
            self._elites = self._mean.unsqueeze(2).expand(-1, -1, kept, -1, -1).clone()
            return self._elites, torch.zeros(1, envs, 1, dtype=torch.bool, device=device)
        if reset is None:
            return self._elites, torch.ones(1, envs, 1, dtype=torch.bool, device=device)
        return self._elites, ~reset.view(1, envs, 1)

    def _optimize(
        self, obs: torch.Tensor, mean: torch.Tensor, *extra: torch.Tensor
    ) -> tuple[torch.Tensor, ...]:
        """One decision's CEM from the warm start: a pure tensor function (what a CUDA graph
        captures).

        Args:
            obs: ``[I, M, obs]`` start states; mean: ``[I, M, H, act]`` warm start.
            extra: the schedule ``[I, M, H, obs]`` first when this call has one, then with
                ``keep_elites`` (and ``shift_elites``) the previous decision's kept elites
                shifted by one step ``[I, M, K, H, act]`` and which envs have them (bool
                ``[1, M, 1]``); they join the first CEM iteration.

        Returns:
            ``[I, M, H, act]`` the optimised sequences, ``[I]`` the non-finite predicted
            rewards counted while scoring them and, with ``keep_elites``, the last iteration's
            kept elites ``[I, M, K, H, act]``.
        """
        nonfinite = torch.zeros_like(self.nonfinite_rewards)
        schedule = extra[0] if self._with_schedule else None
        shifted = extra[1:] if self._with_schedule else extra

        def score(candidates: torch.Tensor) -> torch.Tensor:
            nonlocal nonfinite
            scores, counted = trajectory_sampling_returns(
                self.model,
                obs,
                candidates,
                self.reward_fn,
                termination_fn=self.termination_fn,
                propagation=self.config.propagation,
                particles=self.config.particles,
                dtype=self.dtype,
                generator=self.generator,
                step=self._step,
                schedule=schedule,
            )
            nonfinite = nonfinite + counted
            return scores

        icem: dict[str, torch.Tensor] = {}  # ICEMOptimizer's inputs (its options are on)
        if self.config.anchor_candidates:
            icem["anchors"] = self._anchors(mean)
        if shifted:
            icem["initial_elites"], icem["initial_valid"] = shifted
        frozen = getattr(self.model, "frozen_parameters", None)  # optional (DynamicsModel)
        with frozen(self.dtype) if frozen is not None else contextlib.nullcontext():
            mu = self._optimizer.optimize(score, mean, self.action_low, self.action_high, **icem)
        return (mu, nonfinite, self._optimizer.last_elites) if shifted else (mu, nonfinite)

    def _graph_key(self, obs: torch.Tensor) -> tuple:
        """What a captured decision depends on beyond its inputs' values: shapes, settings,
        the score functions and the addresses of every parameter and buffer it reads."""
        tensors = (*self.parameters(), *self.buffers())
        return (
            tuple(obs.shape),
            self._with_schedule,
            self.config,
            self.dtype,
            id(self.reward_fn),
            id(self.termination_fn),
            tuple(t.data_ptr() for t in tensors),
        )

    # ------------------------------------------------------------------ TensorDict API
    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        model = self.model
        expected = f"[*, n_agents={model.n_agents}, obs_dim={model.obs_dim}]"
        obs = get_tensor(tensordict, self.in_keys[0], expected, type(self).__name__)
        is_init = tensordict.get(self.is_init_key, None)
        tensordict.set(self.out_keys[0], self.plan(obs, is_init=is_init))
        return tensordict

    @torch.no_grad()
    def plan(
        self,
        obs: torch.Tensor,
        is_init: torch.Tensor | None = None,
        schedule: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """Plan one decision for every agent.

        Args:
            obs: ``[*, I, obs]`` current observations (real, finite).
            is_init: optional ``[*]`` / ``[*, 1]`` bool; ``True`` resets that env's warm start.
            schedule: optional ``[*, I, H, obs]`` known values of the predicted states'
                features (index ``t``: the state after step ``t``; NaN where the model
                predicts), e.g. a neighbour's speeds from its broadcast plan: every particle's
                predicted state takes them (:func:`~mapets_rl.planning.propagate_step`).

        Returns:
            ``[*, I, act]`` first actions of the optimised sequences, within the bounds.

        The inputs are checked here, once per call (one host sync for the finiteness of
        ``obs``); the CEM iterations run unchecked.
        """
        model = self.model
        n_agents, obs_dim = model.n_agents, model.obs_dim
        expected = f"[*, n_agents={n_agents}, obs_dim={obs_dim}]"
        check_real("observation", obs, expected)
        if obs.ndim < 2 or obs.shape[-2:] != (n_agents, obs_dim):
            raise ValueError(f"observation must be shaped {expected}, got {tuple(obs.shape)}.")
        check_finite("observation", obs, agent_dim=-2)
        batch_shape = obs.shape[:-2]
        if is_init is not None:
            if tuple(is_init.shape) not in (tuple(batch_shape), (*batch_shape, 1)):
                raise ValueError(
                    f"is_init must have shape {list(batch_shape)} or {[*batch_shape, 1]} (one "
                    f"flag per env of the observation {list(obs.shape)}), got "
                    f"{list(is_init.shape)}."
                )
            is_init = as_mask("is_init", is_init, f"{[*batch_shape, 1]}")
        obs_p = obs.reshape(-1, n_agents, obs_dim).transpose(0, 1).float()  # [I, M, obs]
        envs = obs_p.shape[1]
        known = self._schedule_layout(schedule, batch_shape)
        reset = None
        if self._mean is None or self._batch_shape != batch_shape:
            self._mean = self._initial_mean(envs)
            self._elites = None
            self._batch_shape = batch_shape
        elif is_init is not None:
            reset = is_init.reshape(envs).view(1, envs, 1, 1)
            self._mean = torch.where(reset, self._initial_mean(envs), self._mean)
        shifted = self._shifted_elites(envs, reset)
        self._with_schedule = known is not None
        inputs = (obs_p, self._mean, *(() if known is None else (known,)), *shifted)
        if self._graphed is None:
            mu, nonfinite, *elites = self._optimize(*inputs)
        else:
            mu, nonfinite, *elites = self._graphed(self._optimize, self._graph_key(obs_p), inputs)
        self.nonfinite_rewards += nonfinite
        self._warn_nonfinite()
        self._solution = mu
        action = torch.clamp(mu[:, :, 0], self.action_low[:, 0], self.action_high[:, 0])
        # Warm start: shift the plan by one step, pad with the centre of the box.
        self._mean = torch.cat([mu[:, :, 1:], self._initial_mean(envs)[:, :, :1]], dim=2)
        if shifted:
            # The kept elites shifted by one step, padded by repeating their last action: a
            # whole sequence that was good stays one (holding its final action is its most
            # plausible continuation, and the centre is already the shifted mean's pad).
            (last,) = elites
            self._elites = torch.cat([last[:, :, :, 1:], last[:, :, :, -1:]], dim=3)
        else:
            self._elites = None
        return action.transpose(0, 1).reshape(*batch_shape, n_agents, model.action_dim)
