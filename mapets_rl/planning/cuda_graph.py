"""Capture a planning step in a CUDA graph once, replay it at every decision.

On a GPU the planner's decision is thousands of small kernels (``H x Y`` model steps, each a
few GEMMs and elementwise ops) whose launch overhead can exceed their work. A CUDA graph
records the kernels of one call and replays them with one launch. The step must be a pure
tensor function of fixed-shape inputs with no host synchronisation (the CEM's accelerator
path runs every iteration and freezes ``mu, sigma`` instead of breaking early).

What a replay reads is fixed at capture: the inputs' static copies, the model's parameters and
buffers *at their addresses then*, and the generator's state (registered with the graph, so its
offset advances at every replay as eager calls would advance it). :class:`GraphedStep`
recaptures whenever the key (shapes, dtype) or the address of any tensor the step reads from
the model changes (a parameter replaced rather than updated in place, ``.to()`` another
device); in-place updates (an optimiser's step, ``load_state_dict``) are seen by the next replay.
"""

from __future__ import annotations

from collections.abc import Callable, Hashable, Sequence

import torch

__all__ = ["GraphedStep"]


class GraphedStep:
    """A function of fixed-shape CUDA tensors, captured once per key and replayed.

    Args:
        device: the CUDA device the step runs on.
        generator: the generator the step draws from (``None``: the device's default one).

    ``captures`` counts the captures so far (1 after the first call with a given key).
    """

    def __init__(self, device: torch.device, generator: torch.Generator | None = None) -> None:
        if device.type != "cuda":
            raise ValueError(f"GraphedStep needs a CUDA device, got {device}.")
        self.device = device
        self.generator = generator
        self.captures = 0
        self._key: Hashable = None
        self._graph: torch.cuda.CUDAGraph | None = None
        self._inputs: list[torch.Tensor] = []
        self._outputs: tuple[torch.Tensor, ...] = ()

    def _rng_state(self) -> torch.Tensor:
        if self.generator is not None:
            return self.generator.get_state()
        return torch.cuda.get_rng_state(self.device)

    def _set_rng_state(self, state: torch.Tensor) -> None:
        if self.generator is not None:
            self.generator.set_state(state)
        else:
            torch.cuda.set_rng_state(state, self.device)

    def _capture(self, fn: Callable[..., tuple[torch.Tensor, ...]], inputs: Sequence[torch.Tensor]):
        self._graph = None  # free the previous graph's pool before the new capture
        self._inputs = [x.clone() for x in inputs]
        # Warm up on a side stream (lazy cuBLAS/cuRAND initialisation must not be captured),
        # then rewind the generator so that the captured call draws what an eager one would.
        state = self._rng_state()
        side = torch.cuda.Stream(self.device)
        side.wait_stream(torch.cuda.current_stream(self.device))
        with torch.cuda.stream(side):
            fn(*self._inputs)
        torch.cuda.current_stream(self.device).wait_stream(side)
        self._set_rng_state(state)
        graph = torch.cuda.CUDAGraph()
        if self.generator is not None:
            graph.register_generator_state(self.generator)
        with torch.cuda.graph(graph):
            self._outputs = tuple(fn(*self._inputs))
        self._graph = graph
        self.captures += 1

    def __call__(
        self,
        fn: Callable[..., tuple[torch.Tensor, ...]],
        key: Hashable,
        inputs: Sequence[torch.Tensor],
    ) -> tuple[torch.Tensor, ...]:
        """``fn(*inputs)`` by graph replay (capturing first when ``key`` is new).

        Args:
            fn: maps the inputs to a tuple of tensors; pure apart from drawing from the
                generator; its shapes may depend only on ``key``.
            key: what identifies a capture (shapes, dtypes, addresses of tensors ``fn`` reads).
            inputs: CUDA tensors, copied into the graph's static inputs.

        Returns:
            Fresh copies of ``fn``'s outputs (the static ones are overwritten by the next replay).
        """
        if key != self._key or self._graph is None:
            self._key = None
            self._capture(fn, inputs)
            self._key = key
        for static, value in zip(self._inputs, inputs, strict=True):
            static.copy_(value)
        self._graph.replay()
        return tuple(out.clone() for out in self._outputs)
