"""Planner configuration and the MA-PETS size presets: the paper's and a CPU-sized one."""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence
from typing import Any

import torch

from mapets_rl.config import ConfigSection, check
from mapets_rl.models.config import EnsembleConfig
from mapets_rl.planning.cem import CEMOptimizer, ICEMOptimizer, kept_elite_count, sample_sizes
from mapets_rl.planning.memory import planner_bytes
from mapets_rl.planning.precision import DTYPE_CHOICES
from mapets_rl.planning.trajectory_sampling import PROPAGATIONS, particle_layout_error

__all__ = [
    "OPTIMIZERS",
    "PlannerConfig",
    "Preset",
    "PAPER_PRESET",
    "CPU_PRESET",
    "PRESETS",
    "PROPAGATIONS",
]

OPTIMIZERS = ("cem", "icem")
"""The optimisers a :class:`PlannerConfig` names: the paper's CEM and iCEM."""
ICEM_DEFAULTS: dict[str, Any] = {
    "anchor_candidates": False,
    "keep_best": False,
    "noise_beta": 0.0,
    "keep_elites": 0.0,
    "population_decay": 1.0,
}
"""iCEM's fields and their values under ``optimizer="cem"`` (every option off)."""


@dataclasses.dataclass(frozen=True)
class PlannerConfig(ConfigSection):
    """CEM sizes and propagation of the MA-PETS planner (Table II); the ensemble it plans with
    is :class:`~mapets_rl.models.EnsembleConfig`.

    Attributes:
        horizon: MPC horizon ``w`` (>= 1).
        population: CEM candidates ``Q`` (>= 1).
        elites: CEM elites ``X`` (1 <= X <= Q).
        iterations: max CEM iterations ``Y`` (>= 1).
        particles: TS particles ``P`` per candidate (>= 1); ``ts_inf`` needs ``P`` to be a
            multiple of the ensemble size ``B`` (checked where both are known, e.g.
            ``MAPETSConfig``, and by :class:`~mapets_rl.planning.TrajectorySamplingCEM`).
        propagation: ``"ts_inf"``, ``"ts1"`` or ``"expectation"``.
        epsilon: CEM stops early once every sampling std is below it (> 0).
        alpha: momentum of the CEM update, ``new = alpha * old + (1 - alpha) * elites``
            (in [0, 1)).
        dtype: compute dtype of the ensemble forward while planning: ``"auto"`` (bf16 on
            CPUs with AVX512-BF16/AMX and on CUDA devices with bf16, fp32 elsewhere),
            ``"fp32"`` or ``"bf16"``.
        optimizer: ``"cem"``, the paper's CEM (:class:`~mapets_rl.planning.CEMOptimizer`;
            iCEM's fields below must keep their defaults), or ``"icem"``
            (:class:`~mapets_rl.planning.ICEMOptimizer` with the options below; with every
            option off it plans the same sequences as ``"cem"``). The cpu preset's is
            ``"icem"``. A config file written before this field names none: it is read as
            ``"icem"`` when one of iCEM's fields is set (:meth:`upgrade_dict`).
        anchor_candidates: also score the current mean, "stop" (the constant sequence at the
            lowest action) and "hold" (the warm start's first action held) in every CEM
            iteration (iCEM's fallbacks; see :class:`~mapets_rl.planning.TrajectorySamplingCEM`).
        keep_best: execute the best-scoring sequence of all iterations instead of the final CEM
            mean (iCEM).
        noise_beta: colored candidate noise (iCEM): the noise along the horizon has a power
            spectrum ``~1/f^noise_beta`` and unit variance per step (>= 0; 0: white noise, the
            paper's CEM; iCEM uses 2-4 for horizons of 25-30 steps, larger is smoother).
        keep_elites: fraction (in [0, 1]) of the ``X`` elites that iteration ``k`` hands to
            iteration ``k + 1``: ``K = max(1, round(keep_elites * X))`` best sequences join
            its candidates and are scored again under its particle noise (0: none). With
            ``shift_elites`` the last iteration's ``K`` also reach the next decision (iCEM).
        shift_elites: with ``keep_elites``, the last decision's kept elites, shifted by one step
            (their last action repeated), join the next decision's first iteration; reset like
            the warm start (:meth:`~mapets_rl.planning.TrajectorySamplingCEM.reset`,
            ``is_init``).
        population_decay: iteration ``k`` samples ``max(min(2 X, Q), floor(Q / decay^k))``
            candidates (iCEM's decay; >= 1; 1: ``Q`` at every iteration).
        cuda_graph: capture the whole optimisation of a decision (all CEM iterations and
            rollouts) in a CUDA graph on the first call and replay it at the next ones
            (:class:`~mapets_rl.planning.cuda_graph.GraphedStep`; recaptured when the
            observation's batch shape, a planner setting or the address of a model tensor
            changes). CUDA devices only; the same random numbers and decisions as eager
            planning, fewer kernel launches.
        compile: run each rollout step through ``torch.compile`` (inductor), which fuses its
            elementwise ops into a few loops around the GEMMs
            (:class:`~mapets_rl.planning.compiled.CompiledStep`): compiled once per run at its
            first decision (seconds), equal to eager planning up to floating-point
            reassociation; eager, with a warning, where no C++ compiler is found. CPU planning
            only: on an accelerator the step stays eager (use ``cuda_graph`` there).
    """

    horizon: int = dataclasses.field(default=25, metadata={"unit": "steps"})
    population: int = 400
    elites: int = 40
    iterations: int = 5
    particles: int = 20
    propagation: str = "ts_inf"
    epsilon: float = 1e-3
    alpha: float = 0.1
    dtype: str = "auto"
    optimizer: str = "cem"
    anchor_candidates: bool = False
    keep_best: bool = False
    noise_beta: float = 0.0
    keep_elites: float = 0.0
    shift_elites: bool = True
    population_decay: float = 1.0
    cuda_graph: bool = False
    compile: bool = False

    def __post_init__(self) -> None:
        super().__post_init__()
        for name in ("horizon", "population", "iterations", "particles"):
            check(getattr(self, name) >= 1, name, ">= 1", getattr(self, name))
        check(
            1 <= self.elites <= self.population,
            "elites",
            f"in [1, population={self.population}]",
            self.elites,
        )
        check(
            self.propagation in PROPAGATIONS,
            "propagation",
            f"one of {list(PROPAGATIONS)}",
            self.propagation,
        )
        check(self.epsilon > 0, "epsilon", "> 0", self.epsilon)
        check(0.0 <= self.alpha < 1.0, "alpha", "in [0, 1)", self.alpha)
        check(self.noise_beta >= 0.0, "noise_beta", ">= 0 (0: white noise)", self.noise_beta)
        check(0.0 <= self.keep_elites <= 1.0, "keep_elites", "in [0, 1]", self.keep_elites)
        check(self.population_decay >= 1.0, "population_decay", ">= 1", self.population_decay)
        check(self.dtype in DTYPE_CHOICES, "dtype", f"one of {list(DTYPE_CHOICES)}", self.dtype)
        check(
            self.optimizer in OPTIMIZERS, "optimizer", f"one of {list(OPTIMIZERS)}", self.optimizer
        )
        options = self.icem_options() if self.optimizer == "cem" else []
        if options:
            first = options[0]
            check(
                False,
                first,
                f"{ICEM_DEFAULTS[first]!r} with optimizer='cem' ({', '.join(options)}: iCEM's "
                "options; set optimizer='icem' to use them)",
                getattr(self, first),
            )

    def icem_options(self) -> list[str]:
        """The iCEM fields that are not at their ``"cem"`` values (:data:`ICEM_DEFAULTS`)."""
        return [name for name, off in ICEM_DEFAULTS.items() if getattr(self, name) != off]

    @classmethod
    def upgrade_dict(cls, data: Mapping[str, Any]) -> dict[str, Any]:
        """The fields of a planner section written before ``optimizer`` existed (which chose
        iCEM when one of its options was set), naming ``"icem"`` when one of them is set; a
        section without them keeps the default or its preset's optimiser (the same
        sequences), and one that names its optimiser is kept."""
        out = dict(data)
        if "optimizer" not in out and any(
            out.get(k, off) != off for k, off in ICEM_DEFAULTS.items()
        ):
            out["optimizer"] = "icem"
        return out

    def make_optimizer(self, generator: torch.Generator | None = None) -> CEMOptimizer:
        """The optimiser :attr:`optimizer` names: the paper's
        :class:`~mapets_rl.planning.CEMOptimizer` or an
        :class:`~mapets_rl.planning.ICEMOptimizer` with iCEM's options, drawing its candidate
        noise from ``generator``."""
        sizes = (self.population, self.elites, self.iterations, self.epsilon, self.alpha)
        if self.optimizer == "cem":
            return CEMOptimizer(*sizes, generator)
        return ICEMOptimizer(
            *sizes,
            generator,
            noise_beta=self.noise_beta,
            keep_elites=self.keep_elites,
            population_decay=self.population_decay,
            keep_best=self.keep_best,
        )

    def candidates_per_iteration(self) -> list[int]:
        """Candidates one CEM iteration scores, per iteration: the sampled ones (decaying with
        ``population_decay``), the anchors and the mean (3 with ``anchor_candidates``) and the
        kept elites (at the first iteration the previous decision's, with ``shift_elites``)."""
        extra = 3 if self.anchor_candidates else 0
        kept = kept_elite_count(self.keep_elites, self.elites)
        first = kept if self.shift_elites else 0
        sizes = sample_sizes(self.population, self.elites, self.iterations, self.population_decay)
        return [n + extra + (kept if k else first) for k, n in enumerate(sizes)]

    def decision_bytes(
        self, n_agents: int, obs_dim: int, action_dim: int, hidden: Sequence[int]
    ) -> int:
        """Bytes of the largest tensors of one planning decision (fp32 upper bound,
        :func:`~mapets_rl.planning.memory.planner_bytes`) with the most candidates an iteration
        scores (:meth:`candidates_per_iteration`: the population plus anchors and kept
        elites), for ``n_agents`` agents of ``obs_dim`` / ``action_dim`` and a model of hidden
        sizes ``hidden``: the one estimate the planner and MA-PETS check."""
        return planner_bytes(
            n_agents,
            obs_dim,
            action_dim,
            tuple(hidden),
            max(self.candidates_per_iteration()),
            self.particles,
            self.horizon,
        )

    def layout_error(self, members: int) -> str | None:
        """Why the particles cannot be split over ``members`` ensemble members (one line), or
        ``None``: :func:`~mapets_rl.planning.trajectory_sampling.particle_layout_error` for the
        ``population`` and for every iteration's number of scored candidates
        (:meth:`candidates_per_iteration`, which ``ts1`` splits too)."""
        error = particle_layout_error(self.propagation, self.particles, self.population, members)
        if error is not None:
            return error
        for candidates in sorted(set(self.candidates_per_iteration())):
            error = particle_layout_error(self.propagation, self.particles, candidates, members)
            if error is not None:
                return (
                    f"{error} (population {self.population} plus the anchors and kept elites: "
                    f"{candidates} candidates scored in a CEM iteration)"
                )
        return None


@dataclasses.dataclass(frozen=True)
class Preset:
    """A named choice of planner and ensemble sizes."""

    planner: PlannerConfig
    model: EnsembleConfig


#: MA-PETS Table II (w=25, Q=400, X=40, Y=5, P=20, B=5, 3x300 hidden, 5 training epochs): ~0.37
#: TFLOP per agent and decision, a GPU workload.
PAPER_PRESET = Preset(planner=PlannerConfig(), model=EnsembleConfig())

#: Scaled down for a 2-core CPU: w=25, Q=8, X=4, Y=2, P=5, B=5, 3x64 hidden. The horizon stays
#: the paper's 2.5 s, long enough to brake from 13.89 m/s at -6 m/s^2 (2.3 s); the CEM is
#: narrowed instead ((Q + 3 anchors) x w x Y = 550 model rows per particle and agent-decision).
#: The model trains 30 epochs after each episode: 5 are 40-80 gradient steps at this size and
#: leave the model underestimating fast closing; the training NLL flattens by ~30. iCEM's anchor
#: candidates and keep-best are on (the paper preset keeps the plain CEM): with them the
#: planner is as safe at Q = 8 or 16 as at Q = 32 on both figure-eights, with the exact model and
#: with the learned ones (iCEM's colored noise costs two-lane safety, so it stays off). Each
#: rollout step is compiled (``compile``; eager where no C++ compiler is found). See
#: docs/results/ (performance.md: timings; ablations.md: safety against model rows; mapets.md:
#: the NLL curve).
CPU_PRESET = Preset(
    planner=PlannerConfig(
        horizon=25,
        population=8,
        elites=4,
        iterations=2,
        particles=5,
        optimizer="icem",
        anchor_candidates=True,
        keep_best=True,
        compile=True,
    ),
    model=EnsembleConfig(ensemble_size=5, hidden=[64, 64, 64], epochs=30),
)

PRESETS: dict[str, Preset] = {"paper": PAPER_PRESET, "cpu": CPU_PRESET}
