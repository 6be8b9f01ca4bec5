"""The cross-entropy method over batched action sequences (MA-PETS Algorithm 1, lines 6-12).

A pure optimiser: it knows nothing of models, rewards or TensorDicts. Every planning problem
(agent ``i`` of env ``m``) keeps a Gaussian ``N(mu, sigma)`` over sequences ``[H, act]``; all
problems are iterated together, ``[I, M, Q, H, act]`` candidates per iteration.
"""

from __future__ import annotations

from collections.abc import Callable

import torch

__all__ = ["CEMOptimizer", "ScoreFn"]

#: ``score_fn(candidates [I, M, Q, H, act]) -> scores [I, M, Q]`` (higher is better).
ScoreFn = Callable[[torch.Tensor], torch.Tensor]


class CEMOptimizer:
    """Cross-entropy method with momentum and early stopping, batched over problems.

    Each iteration samples ``population`` candidates ``mu + sigma * noise`` clipped to the
    bounds, scores them, and refits ``mu <- alpha mu + (1 - alpha) mean(elites)`` (same for
    ``sigma``) to the ``elites`` best; it stops after ``iterations`` rounds or once every sigma
    is below ``epsilon``. The candidate noise is common to all problems of a call.

    The arguments are trusted (validated by :class:`~mapets_rl.planning.PlannerConfig` or
    :class:`~mapets_rl.planning.TrajectorySamplingCEM`).

    Args:
        population, elites, iterations, epsilon, alpha: ``Q, X, Y``, the early-stop threshold
            and the momentum.
        generator: random generator of the candidate noise.
        host_sync: read the early-stop test on the host each iteration (``None``: on the CPU
            only). Without it every iteration runs and mu / sigma freeze once every sigma is
            below epsilon: the same result, no device sync (for accelerators).
    """

    def __init__(
        self,
        population: int,
        elites: int,
        iterations: int,
        epsilon: float,
        alpha: float,
        generator: torch.Generator | None = None,
        host_sync: bool | None = None,
    ) -> None:
        self.population = population
        self.elites = elites
        self.iterations = iterations
        self.epsilon = epsilon
        self.alpha = alpha
        self.generator = generator
        self.host_sync = host_sync
        self._last_iterations: int | torch.Tensor = 0

    def optimize(
        self,
        score_fn: ScoreFn,
        initial_mean: torch.Tensor,
        action_low: torch.Tensor,
        action_high: torch.Tensor,
        anchors: torch.Tensor | None = None,
        keep_best: bool = False,
    ) -> torch.Tensor:
        """Run the CEM from ``initial_mean`` with sigma a quarter of the action range.

        Args:
            score_fn: maps candidates ``[I, M, Q, H, act]`` to scores ``[I, M, Q]``.
            initial_mean: ``[I, M, H, act]`` starting mean (e.g. the warm start).
            action_low / action_high: ``[I, 1, 1, act]`` bounds.
            anchors: optional ``[I, M, K, H, act]`` noise-free sequences scored in every
                iteration beside the sampled ones (and eligible as elites), plus the current
                mean itself (iCEM, Pinneri et al. 2020, adds the mean; a planner can add safe
                fallbacks such as "brake"). Within the bounds.
            keep_best: return the best-scoring sequence of all iterations instead of the final
                mean (iCEM's executed action).

        Returns:
            ``[I, M, H, act]`` the optimised mean (or best sequence). ``last_iterations`` holds
            the rounds run.
        """
        mu = initial_mean
        std = ((action_high - action_low) / 4).expand_as(mu).clone()
        low = action_low.unsqueeze(1)  # [I, 1, 1, 1, act]
        high = action_high.unsqueeze(1)
        shape = (self.population, *mu.shape[-2:])
        # On the CPU the early stop reads ``std.max()`` on the host each iteration. On an
        # accelerator that would be a device sync per iteration: there every iteration runs and
        # once every sigma is below epsilon mu and sigma are frozen, which gives the same mean.
        host_check = mu.device.type == "cpu" if self.host_sync is None else self.host_sync
        iterations: int | torch.Tensor = 0
        stopped = torch.zeros((), dtype=torch.bool, device=mu.device)
        best = best_score = None
        for _ in range(self.iterations):
            noise = torch.randn(shape, generator=self.generator, device=mu.device)
            candidates = torch.clamp(mu.unsqueeze(2) + std.unsqueeze(2) * noise, low, high)
            if anchors is not None:
                mean = torch.clamp(mu, action_low, action_high).unsqueeze(2)
                candidates = torch.cat([candidates, anchors, mean], dim=2)
            scores = score_fn(candidates)  # [I, M, Q (+ K + 1)]
            if keep_best:
                top, where = scores.max(dim=-1)  # [I, M]
                found = torch.gather(
                    candidates, 2, where[:, :, None, None, None].expand(-1, -1, 1, *shape[1:])
                ).squeeze(2)
                if best is None:
                    best, best_score = found, top
                else:
                    better = top > best_score
                    best = torch.where(better[:, :, None, None], found, best)
                    best_score = torch.maximum(top, best_score)
            elite_idx = scores.topk(self.elites, dim=-1).indices  # [I, M, X]
            elites = torch.gather(
                candidates, 2, elite_idx[..., None, None].expand(-1, -1, -1, *shape[1:])
            )
            new_mu = self.alpha * mu + (1 - self.alpha) * elites.mean(2)
            new_std = self.alpha * std + (1 - self.alpha) * elites.std(2, unbiased=False)
            if host_check:
                iterations += 1
                mu, std = new_mu, new_std
                if bool(std.max() < self.epsilon):
                    break
            else:
                iterations = iterations + (~stopped).long()
                mu = torch.where(stopped, mu, new_mu)
                std = torch.where(stopped, std, new_std)
                stopped = stopped | (std.max() < self.epsilon)
        self._last_iterations = iterations
        return best if keep_best else mu

    @property
    def last_iterations(self) -> int:
        """CEM iterations the last :meth:`optimize` ran (a host read on an accelerator)."""
        return int(self._last_iterations)
