"""The planner's rollout step compiled by ``torch.compile`` (inductor), with an eager fallback.

A decision of the cpu-sized planner is ``H x Y`` model steps of a few small GEMMs and dozens of
elementwise ops (the MLP's bias and SiLU, the PETS log-variance bounds, the particle update,
the known reward and termination): on a CPU the elementwise ops and their dispatch cost more
than the GEMMs. :class:`CompiledStep` hands the step
(:func:`~mapets_rl.planning.trajectory_sampling.propagate_step`) to inductor, which fuses them
into a few C++ loops around the GEMMs.

What compiles, when: one graph per distinct (shapes, dtypes, model, reward and termination
functions, propagation) of a step: a run whose batch shape does not change compiles once, at
its first decision (seconds; the time is kept in :attr:`CompiledStep.compile_seconds`).
Inductor caches the generated code on disk, so a later process with the same shapes compiles
faster: in a private directory of the user's own (:mod:`mapets_rl._compile_cache`, decided
again before the first compilation), never in the shared temporary directory. Where inductor
cannot run (no C++ compiler, or the first compilation fails) the step runs eagerly and a
warning says why (:attr:`CompiledStep.fallback_reason`).
"""

from __future__ import annotations

import logging
import os
import time
from collections.abc import Callable
from typing import Any

import torch

from mapets_rl._compile_cache import HEADERS_ENV, prepare_compile_cache
from mapets_rl.planning.trajectory_sampling import propagate_step

__all__ = ["CompiledStep", "compiler_unavailable"]

log = logging.getLogger(__name__)


def compiler_unavailable() -> str | None:
    """Why inductor's CPU backend cannot build here (one line), or ``None`` when it can: it
    needs a C++ compiler (``$CXX`` or ``c++`` / ``g++`` on the path)."""
    try:
        from torch._inductor.cpp_builder import get_cpp_compiler

        get_cpp_compiler()
    except Exception as err:  # noqa: BLE001 - any failure means "no compiler"
        return f"no C++ compiler for torch.compile's inductor backend ({type(err).__name__})"
    return None


def _signature(args: tuple[Any, ...]) -> tuple:
    """What a new compilation depends on: the tensors' shapes and dtypes, the other
    arguments' identities (model, functions) or values (strings, dtypes)."""
    out = []
    for arg in args:
        if isinstance(arg, torch.Tensor):
            out.append((tuple(arg.shape), arg.dtype, arg.device))
        elif arg is None or isinstance(arg, (str, torch.dtype)):
            out.append(arg)
        else:
            out.append(id(arg))
    return tuple(out)


class CompiledStep:
    """:func:`~mapets_rl.planning.trajectory_sampling.propagate_step` through
    ``torch.compile`` (static shapes), falling back to the eager step where it cannot compile.

    Same arguments and results as ``propagate_step``; the results equal the eager step's up
    to floating-point reassociation inside the fused loops
    (``tests/planning/test_compiled_planner.py`` states the tolerance).

    Attributes:
        compiles: distinct step signatures compiled so far (one per run at fixed shapes).
        compile_seconds: wall time of the first calls of those signatures (compilation
            included).
        fallback_reason: why the step runs eagerly (``None`` while it compiles).
        cache_dir: inductor's cache directory (private to this user).
    """

    def __init__(self) -> None:
        """Raises ValueError (one line) when ``TORCHINDUCTOR_CACHE_DIR`` names a directory
        that cannot hold compiled code safely (see :mod:`mapets_rl._compile_cache`)."""
        self.cache_dir = prepare_compile_cache()
        from torch._inductor import config as inductor_config

        inductor_config.cpp_cache_precompile_headers = os.environ.get(HEADERS_ENV) == "1"
        self.compiles = 0
        self.compile_seconds = 0.0
        self.fallback_reason = compiler_unavailable()
        self._seen: set[tuple] = set()
        self._compiled: Callable[..., Any] | None = None
        if self.fallback_reason is None:
            self._compiled = torch.compile(propagate_step, dynamic=False)
        else:
            self._fall_back(self.fallback_reason)

    def _fall_back(self, reason: str) -> None:
        self.fallback_reason = reason
        self._compiled = None
        log.warning("planner compile=True runs eagerly: %s.", reason)

    def __call__(self, *args: Any) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        if self._compiled is None:
            return propagate_step(*args)
        key = _signature(args)
        if key in self._seen:
            return self._compiled(*args)
        start = time.perf_counter()
        try:
            out = self._compiled(*args)
        except (ValueError, TypeError):
            raise  # the step's own input errors (e.g. a reward of the wrong shape)
        except Exception as err:  # noqa: BLE001 - inductor failures: plan eagerly instead
            root = err
            while root.__cause__ is not None:  # e.g. BackendCompilerFailed <- OSError
                root = root.__cause__
            self._fall_back(f"torch.compile failed: {type(root).__name__}: {root}".splitlines()[0])
            return propagate_step(*args)
        self.compile_seconds += time.perf_counter() - start
        self.compiles += 1
        self._seen.add(key)
        log.info(
            "planner step compiled in %.1f s (compile %d of this planner)",
            self.compile_seconds,
            self.compiles,
        )
        return out
