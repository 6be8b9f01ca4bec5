"""The cross-entropy method over batched action sequences (MA-PETS Algorithm 1, lines 6-12).

A pure optimiser: it knows nothing of models, rewards or TensorDicts. Every planning problem
(agent ``i`` of env ``m``) keeps a Gaussian ``N(mu, sigma)`` over sequences ``[H, act]``; all
problems are iterated together, ``[I, M, Q, H, act]`` candidates per iteration.

Two classes, as mbrl-lib's ``trajectory_opt`` splits them: :class:`CEMOptimizer`, the plain CEM
of the MA-PETS paper, and :class:`ICEMOptimizer`, which adds the options of iCEM (Pinneri et
al. 2020, "Sample-efficient cross-entropy method for real-time planning"): noise-free anchor
candidates, keep-best, colored (temporally correlated) candidate noise, elites kept across
iterations (and handed to the next decision by the planner) and a decaying population. With
every option off the two return the same sequences for the same generator state.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import torch

from mapets_rl.modules.arguments import finite_number

__all__ = [
    "CEMOptimizer",
    "ICEMOptimizer",
    "ScoreFn",
    "colored_noise",
    "kept_elite_count",
    "sample_sizes",
]

#: ``score_fn(candidates [I, M, Q, H, act]) -> scores [I, M, Q]`` (higher is better).
ScoreFn = Callable[[torch.Tensor], torch.Tensor]


def colored_noise(
    shape: tuple[int, int, int],
    beta: float,
    generator: torch.Generator | None = None,
    device: torch.device | str | None = None,
) -> torch.Tensor:
    """Standard Gaussian noise ``[N, H, act]`` whose power spectrum along ``H`` is ``~1/f^beta``.

    ``beta = 0`` is white noise, exactly ``torch.randn(shape)``; ``beta = 2`` is Brownian-like
    ("red"), larger is smoother (iCEM uses 2-4 for a horizon of 25-30 steps). For ``beta > 0``
    white Gaussian Fourier coefficients ``[N, act, H // 2 + 1]`` (one draw of ``[2, N, act,
    H // 2 + 1]`` from ``generator``: real and imaginary parts) are scaled by ``k^(-beta/2)``
    at frequency index ``k`` (``k = 0`` scaled as ``k = 1``, iCEM's / ``colorednoise``'s low
    cutoff ``1/H``), transformed back with ``irfft`` and divided by the process's exact
    standard deviation: every step has unit variance (the process is stationary and periodic
    over ``H``). ``beta`` must be a finite number >= 0 (ValueError otherwise).
    """
    beta = finite_number("beta", beta, minimum=0)
    if beta == 0:
        return torch.randn(shape, generator=generator, device=device)
    n, horizon, act = shape
    bins = horizon // 2 + 1
    k = torch.arange(bins, device=device, dtype=torch.float32).clamp_(min=1.0)
    scale = k.pow(-beta / 2)  # <= 1: no overflow for any beta
    imag = scale.clone()
    imag[0] = 0.0  # the mean (DC) and, for even H, the Nyquist bin are real
    if horizon % 2 == 0:
        imag[-1] = 0.0
    # Var x_t = (|DC|^2 + 2 sum_{0<k<H/2} (re_k^2 + im_k^2) + [H even] |Nyquist|^2) / H^2.
    twice = torch.ones(bins, device=device)
    twice[1 : (horizon + 1) // 2] = 2.0
    std = (twice * (scale.square() + imag.square())).sum().sqrt() / horizon
    coeffs = torch.randn((2, n, act, bins), generator=generator, device=device)
    spectrum = torch.complex(coeffs[0] * (scale / std), coeffs[1] * (imag / std))
    return torch.fft.irfft(spectrum, n=horizon, dim=-1).transpose(-1, -2)  # [N, H, act]


def kept_elite_count(keep_elites: float, elites: int) -> int:
    """Elites kept per iteration for the fraction ``keep_elites`` of ``elites``:
    ``max(1, round(keep_elites * elites))`` if the fraction is positive, else 0."""
    return max(1, round(keep_elites * elites)) if keep_elites > 0 else 0


def sample_sizes(population: int, elites: int, iterations: int, decay: float) -> list[int]:
    """Sampled candidates per iteration ``k``: ``max(min(2 X, Q), floor(Q / decay^k))`` (iCEM's
    population decay; ``decay = 1``: ``Q`` at every iteration). Fixed per ``k``: shape-static."""
    floor = min(2 * elites, population)
    return [max(floor, _decayed(population, decay, k)) for k in range(iterations)]


def _decayed(population: int, decay: float, k: int) -> int:
    """``floor(population / decay^k)``; 0 where ``decay^k`` overflows a float (a decay of
    ``1e200`` at ``k = 2``: the population has decayed to nothing)."""
    try:
        return math.floor(population / decay**k)
    except OverflowError:
        return 0


class CEMOptimizer:
    """Cross-entropy method with momentum and early stopping, batched over problems.

    Each iteration samples ``population`` candidates ``mu + sigma * noise`` (white Gaussian
    noise) clipped to the bounds, scores them, and refits ``mu <- alpha mu + (1 - alpha)
    mean(elites)`` (same for ``sigma``) to the ``elites`` best; it stops after ``iterations``
    rounds or once every sigma is below ``epsilon``. The candidate noise is common to all
    problems of a call.

    The arguments are trusted (validated by :class:`~mapets_rl.planning.PlannerConfig`, which
    builds the optimiser: :meth:`~mapets_rl.planning.PlannerConfig.make_optimizer`).

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

    @property
    def sample_sizes(self) -> list[int]:
        """Sampled candidates per iteration: ``population`` each."""
        return [self.population] * self.iterations

    def optimize(
        self,
        score_fn: ScoreFn,
        initial_mean: torch.Tensor,
        action_low: torch.Tensor,
        action_high: torch.Tensor,
    ) -> torch.Tensor:
        """Run the CEM from ``initial_mean`` with sigma a quarter of the action range.

        Args:
            score_fn: maps candidates ``[I, M, C, H, act]`` to scores ``[I, M, C]``.
            initial_mean: ``[I, M, H, act]`` starting mean (e.g. the warm start).
            action_low / action_high: ``[I, 1, 1, act]`` bounds.

        Returns:
            ``[I, M, H, act]`` the optimised mean; :attr:`last_iterations` holds the rounds run.
        """
        mu = initial_mean
        std = ((action_high - action_low) / 4).expand_as(mu).clone()
        low = action_low.unsqueeze(1)  # [I, 1, 1, 1, act]
        high = action_high.unsqueeze(1)
        seq = mu.shape[-2:]  # (H, act)
        # On the CPU the early stop reads ``std.max()`` on the host each iteration. On an
        # accelerator that would be a device sync per iteration: there every iteration runs and
        # once every sigma is below epsilon mu and sigma are frozen, which gives the same mean.
        host_check = mu.device.type == "cpu" if self.host_sync is None else self.host_sync
        iterations: int | torch.Tensor = 0
        stopped = torch.zeros((), dtype=torch.bool, device=mu.device)
        for samples in self.sample_sizes:
            noise = self._noise((samples, *seq), mu.device)
            candidates = torch.clamp(mu.unsqueeze(2) + std.unsqueeze(2) * noise, low, high)
            candidates = self._add_candidates(candidates, mu, action_low, action_high)
            scores = self._score(score_fn, candidates)  # [I, M, C]
            elite_idx = scores.topk(self.elites, dim=-1).indices  # [I, M, X], best first
            elites = torch.gather(
                candidates, 2, elite_idx[..., None, None].expand(-1, -1, -1, *seq)
            )
            new_mu = self.alpha * mu + (1 - self.alpha) * elites.mean(2)
            new_std = self.alpha * std + (1 - self.alpha) * elites.std(2, unbiased=False)
            if host_check:
                iterations += 1
                mu, std = new_mu, new_std
                self._keep_elites(elites, None)
                if bool(std.max() < self.epsilon):
                    break
            else:
                iterations = iterations + (~stopped).long()
                mu = torch.where(stopped, mu, new_mu)
                std = torch.where(stopped, std, new_std)
                self._keep_elites(elites, stopped)
                stopped = stopped | (std.max() < self.epsilon)
        self._last_iterations = iterations
        return mu

    @property
    def last_iterations(self) -> int:
        """CEM iterations the last :meth:`optimize` ran (a host read on an accelerator)."""
        return int(self._last_iterations)

    def _noise(self, shape: tuple[int, int, int], device: torch.device) -> torch.Tensor:
        """The candidate noise ``[N, H, act]`` of one iteration: white Gaussian."""
        return torch.randn(shape, generator=self.generator, device=device)

    def _add_candidates(
        self,
        sampled: torch.Tensor,
        mu: torch.Tensor,
        action_low: torch.Tensor,
        action_high: torch.Tensor,
    ) -> torch.Tensor:
        """The candidates ``[I, M, C, H, act]`` an iteration scores: the sampled ones."""
        return sampled

    def _score(self, score_fn: ScoreFn, candidates: torch.Tensor) -> torch.Tensor:
        """``score_fn(candidates)``, ``[I, M, C]``."""
        return score_fn(candidates)

    def _keep_elites(self, elites: torch.Tensor, stopped: torch.Tensor | None) -> None:
        """See the iteration's elites ``[I, M, X, H, act]`` (best first) after the refit;
        ``stopped`` (bool ``[]``, sync-free path only) whether the CEM had stopped before it."""


class ICEMOptimizer(CEMOptimizer):
    """The CEM with iCEM's options (Pinneri et al. 2020).

    Args:
        population, elites, iterations, epsilon, alpha, generator, host_sync: see
            :class:`CEMOptimizer`.
        noise_beta: exponent of the candidate noise's power spectrum along the horizon,
            ``~1/f^beta`` (:func:`colored_noise`; 0: white noise).
        keep_elites: fraction of the ``X`` elites of iteration ``k`` (the best first) added to
            iteration ``k + 1``'s candidates, ``K = max(1, round(keep_elites * X))`` of them
            (0: none). They are scored again with the new candidates: the particle noise is
            redrawn every iteration and candidates are compared under common random numbers,
            so an old score would not be comparable (this is also what iCEM does). The last
            iteration's ``K`` best are left in :attr:`last_elites`.
        population_decay: iteration ``k`` samples ``max(min(2 X, Q), floor(Q / decay^k))``
            candidates (:func:`sample_sizes`; 1: ``Q`` every iteration).
        keep_best: return the best-scoring sequence of all iterations instead of the final
            mean (iCEM's executed action).
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
        *,
        noise_beta: float = 0.0,
        keep_elites: float = 0.0,
        population_decay: float = 1.0,
        keep_best: bool = False,
    ) -> None:
        super().__init__(population, elites, iterations, epsilon, alpha, generator, host_sync)
        self.noise_beta = noise_beta
        self.keep_elites = keep_elites
        self.population_decay = population_decay
        self.keep_best = keep_best
        self.last_elites: torch.Tensor | None = None
        # the state of one optimize call, read and written by the hooks of its iterations
        self._anchors: torch.Tensor | None = None
        self._kept: torch.Tensor | None = None
        self._valid: torch.Tensor | None = None
        self._best: torch.Tensor | None = None
        self._best_score: torch.Tensor | None = None

    @property
    def kept_elites(self) -> int:
        """``K``: elites carried from one iteration to the next (0 without ``keep_elites``)."""
        return kept_elite_count(self.keep_elites, self.elites)

    @property
    def sample_sizes(self) -> list[int]:
        """Sampled candidates per iteration (``population`` each without a decay)."""
        return sample_sizes(self.population, self.elites, self.iterations, self.population_decay)

    def optimize(
        self,
        score_fn: ScoreFn,
        initial_mean: torch.Tensor,
        action_low: torch.Tensor,
        action_high: torch.Tensor,
        anchors: torch.Tensor | None = None,
        initial_elites: torch.Tensor | None = None,
        initial_valid: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """Run the CEM from ``initial_mean`` with sigma a quarter of the action range.

        Iteration ``k`` scores ``[I, M, N_k (+ K_a + 1) (+ K), H, act]`` candidates: ``N_k``
        sampled ones (:attr:`sample_sizes`), then the anchors and the mean, then the elites
        kept from iteration ``k - 1`` (or, at ``k = 0``, ``initial_elites``).

        Args:
            score_fn, initial_mean, action_low, action_high: see :meth:`CEMOptimizer.optimize`.
            anchors: optional ``[I, M, K_a, H, act]`` noise-free sequences scored in every
                iteration beside the sampled ones (and eligible as elites), plus the current
                mean itself (iCEM adds the mean; a planner can add safe fallbacks such as
                "brake"). Within the bounds.
            initial_elites: optional ``[I, M, K0, H, act]`` sequences within the bounds that
                join the first iteration's candidates (e.g. the previous decision's kept
                elites shifted by one step).
            initial_valid: optional bool, broadcastable to ``[I, M, K0]``: ``False`` marks an
                initial elite as absent (it scores ``-inf``; a fixed shape for CUDA graphs).

        Returns:
            ``[I, M, H, act]`` the optimised mean (the best sequence with ``keep_best``).
            ``last_iterations`` holds the rounds run, ``last_elites`` the ``[I, M, K, H, act]``
            best candidates of the last round run, best first (``None`` without
            ``keep_elites``).
        """
        self._anchors, self._kept, self._valid = anchors, initial_elites, initial_valid
        self._best = self._best_score = None
        mu = super().optimize(score_fn, initial_mean, action_low, action_high)
        self.last_elites = self._kept if self.kept_elites else None
        best = self._best
        self._anchors = self._kept = self._valid = self._best = self._best_score = None
        return best if self.keep_best else mu

    def _noise(self, shape: tuple[int, int, int], device: torch.device) -> torch.Tensor:
        """Colored noise (:func:`colored_noise`; exactly ``torch.randn`` at ``beta = 0``)."""
        return colored_noise(shape, self.noise_beta, self.generator, device)

    def _add_candidates(
        self,
        sampled: torch.Tensor,
        mu: torch.Tensor,
        action_low: torch.Tensor,
        action_high: torch.Tensor,
    ) -> torch.Tensor:
        """The sampled candidates, then the anchors and the clipped mean, then the kept
        elites."""
        candidates = sampled
        if self._anchors is not None:
            mean = torch.clamp(mu, action_low, action_high).unsqueeze(2)
            candidates = torch.cat([candidates, self._anchors, mean], dim=2)
        if self._kept is not None:
            candidates = torch.cat([candidates, self._kept], dim=2)
        return candidates

    def _score(self, score_fn: ScoreFn, candidates: torch.Tensor) -> torch.Tensor:
        """The scores, ``-inf`` for the absent initial elites (first iteration), and the best
        candidate so far with ``keep_best``."""
        scores = score_fn(candidates)
        if self._valid is not None:
            extra = self._kept.shape[2]
            head, tail = scores[..., :-extra], scores[..., -extra:]
            scores = torch.cat([head, tail.masked_fill(~self._valid, float("-inf"))], dim=-1)
            self._valid = None
        if self.keep_best:
            seq = candidates.shape[-2:]
            top, where = scores.max(dim=-1)  # [I, M]
            found = torch.gather(
                candidates, 2, where[:, :, None, None, None].expand(-1, -1, 1, *seq)
            ).squeeze(2)
            if self._best is None:
                self._best, self._best_score = found, top
            else:
                better = top > self._best_score
                self._best = torch.where(better[:, :, None, None], found, self._best)
                self._best_score = torch.maximum(top, self._best_score)
        return scores

    def _keep_elites(self, elites: torch.Tensor, stopped: torch.Tensor | None) -> None:
        """Carry the ``K`` best to the next iteration; on the sync-free path they freeze with
        mu once the CEM has stopped (the same :attr:`last_elites` as the early break)."""
        count = self.kept_elites
        new_kept = elites[:, :, :count] if count else None
        if stopped is None or new_kept is None:
            self._kept = new_kept
            return
        kept = self._kept
        frozen = kept is not None and kept.shape == new_kept.shape
        self._kept = torch.where(stopped, kept, new_kept) if frozen else new_kept
