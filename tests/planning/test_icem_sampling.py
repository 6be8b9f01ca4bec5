"""iCEM's sampling options of the CEM planner: colored noise, elites kept across iterations and
shifted across decisions, population decay (Pinneri et al. 2020)."""

from __future__ import annotations

import math

import pytest
import torch
from tensordict import TensorDict

from mapets_rl.config import ConfigError
from mapets_rl.planning import PlannerConfig, TrajectorySamplingCEM
from mapets_rl.planning.cem import (
    CEMOptimizer,
    ICEMOptimizer,
    colored_noise,
    kept_elite_count,
    sample_sizes,
)
from tests.planning.test_planner import DT, RHO, quadratic_reward
from tests.planning.test_planner import ExactPointMass as PointMass


def point_mass_planner(seed: int = 0, **settings) -> TrajectorySamplingCEM:
    """iCEM (with every option off: the plain CEM's sequences) on the point mass."""
    options = dict(horizon=8, population=16, elites=4, iterations=3, particles=1)
    options.update(propagation="expectation", dtype="fp32", optimizer="icem", **settings)
    return TrajectorySamplingCEM(PointMass(), quadratic_reward, -20.0, 20.0, seed=seed, **options)


class Recorder:
    """Wraps ``optimizer.optimize`` to record every iteration's candidates and scores and the
    keyword arguments of each call."""

    def __init__(self, optimizer: ICEMOptimizer) -> None:
        self.calls: list[dict] = []
        self._optimize = optimizer.optimize
        optimizer.optimize = self

    def __call__(self, score_fn, *args, **kwargs):
        call = {"kwargs": kwargs, "candidates": [], "scores": []}
        self.calls.append(call)

        def score(candidates):
            scores = score_fn(candidates)
            call["candidates"].append(candidates)
            call["scores"].append(scores)
            return scores

        return self._optimize(score, *args, **kwargs)


# ---------------------------------------------------------------- colored noise
@pytest.mark.parametrize("horizon", [25, 24])
@pytest.mark.parametrize("beta", [1.0, 2.0, 4.0])
def test_colored_noise_has_unit_variance_per_step_and_the_power_law_spectrum(horizon, beta):
    noise = colored_noise((20000, horizon, 2), beta, torch.Generator().manual_seed(0))
    assert noise.shape == (20000, horizon, 2)
    variance = noise.var(dim=0)  # [H, act]: 40000 draws per step
    assert float((variance - 1).abs().max()) < 0.04
    # Periodogram along the horizon: log power vs log frequency has slope -beta (the DC and
    # Nyquist bins excluded: they carry one real coefficient instead of two).
    power = torch.fft.rfft(noise.transpose(1, 2), dim=-1).abs().square().mean((0, 1))
    k = torch.arange(1, (horizon + 1) // 2)
    design = torch.stack([k.double().log(), torch.ones(len(k), dtype=torch.float64)], dim=1)
    fit = torch.linalg.lstsq(design, power[k].double().log().unsqueeze(-1)).solution
    assert fit[0].item() == pytest.approx(-beta, abs=0.05)
    # ... and neighbouring steps are correlated (white noise: not)
    lag1 = (noise[:, 1:] * noise[:, :-1]).mean().item()
    assert lag1 > 0.3


def test_white_noise_is_exactly_torch_randn():
    white = colored_noise((7, 5, 2), 0.0, torch.Generator().manual_seed(3))
    torch.testing.assert_close(
        white, torch.randn((7, 5, 2), generator=torch.Generator().manual_seed(3)), rtol=0, atol=0
    )


def reference_cem(score_fn, mean, low, high, q, x, iterations, alpha, gen):
    """The plain CEM as it was before the iCEM sampling options (host path, no anchors)."""
    mu, std = mean, ((high - low) / 4).expand_as(mean).clone()
    for _ in range(iterations):
        noise = torch.randn((q, *mu.shape[-2:]), generator=gen)
        candidates = torch.clamp(
            mu.unsqueeze(2) + std.unsqueeze(2) * noise, low.unsqueeze(1), high.unsqueeze(1)
        )
        idx = score_fn(candidates).topk(x, dim=-1).indices
        elites = torch.gather(
            candidates, 2, idx[..., None, None].expand(-1, -1, -1, *mu.shape[-2:])
        )
        mu = alpha * mu + (1 - alpha) * elites.mean(2)
        std = alpha * std + (1 - alpha) * elites.std(2, unbiased=False)
    return mu


def test_default_options_reproduce_the_plain_cem_exactly():
    def score(candidates):
        return -(candidates - 0.3).pow(2).sum(dim=(-1, -2))

    low, high = torch.zeros(2, 1, 1, 1), torch.ones(2, 1, 1, 1)
    mean = torch.full((2, 3, 6, 1), 0.5)
    config = PlannerConfig(population=12, elites=3, iterations=4, epsilon=1e-9)
    want = reference_cem(score, mean, low, high, 12, 3, 4, 0.1, torch.Generator().manual_seed(7))
    plain = config.make_optimizer(torch.Generator().manual_seed(7))
    assert type(plain) is CEMOptimizer and plain.sample_sizes == [12] * 4
    torch.testing.assert_close(plain.optimize(score, mean, low, high), want, rtol=0, atol=0)
    icem = ICEMOptimizer(
        12,
        3,
        4,
        1e-9,
        0.1,
        torch.Generator().manual_seed(7),
        noise_beta=config.noise_beta,
        keep_elites=config.keep_elites,
        population_decay=config.population_decay,
        keep_best=config.keep_best,
    )
    torch.testing.assert_close(icem.optimize(score, mean, low, high), want, rtol=0, atol=0)
    assert icem.last_elites is None and icem.sample_sizes == [12] * 4


def test_colored_noise_reaches_the_candidates_and_is_common_to_all_problems():
    planner = point_mass_planner(noise_beta=3.0, iterations=1, population=4000)
    record = Recorder(planner.optimizer)
    planner.plan(torch.tensor([[[0.5, 0.0]], [[-1.0, 0.3]]]))  # [M=2, I=1, obs]
    candidates = record.calls[0]["candidates"][0]  # [I, M, Q, H, act]; box centre 0, sigma 10
    noise = candidates / 10.0
    torch.testing.assert_close(noise[:, 0], noise[:, 1])
    steps = noise[0, 0, :, :, 0]  # [Q, H]
    assert float((steps.var(0) - 1).abs().max()) < 0.1  # none clipped at 2 sigma
    assert (steps[:, 1:] * steps[:, :-1]).mean().item() > 0.5


# ---------------------------------------------------------------- kept elites
def test_kept_elites_join_the_next_iteration_and_are_scored_again():
    seen: list[tuple[torch.Tensor, torch.Tensor]] = []
    calls = iter(range(100))

    def score(candidates):
        # a score that changes between iterations (like redrawn particle noise)
        shift = 0.05 * next(calls)
        scores = -(candidates - 0.3 - shift).abs().sum(dim=(-1, -2))
        seen.append((candidates, scores))
        return scores

    cem = ICEMOptimizer(16, 4, 3, 1e-9, 0.1, torch.Generator().manual_seed(1), keep_elites=0.5)
    assert cem.kept_elites == 2
    low, high = torch.zeros(1, 1, 1, 2), torch.ones(1, 1, 1, 2)
    cem.optimize(score, torch.full((1, 2, 5, 2), 0.5), low, high)
    assert [c.shape[2] for c, _ in seen] == [16, 18, 18]
    for (before, scores), (after, rescored) in zip(seen[:-1], seen[1:], strict=True):
        best = scores.topk(2, dim=-1).indices  # [I, M, 2]
        kept = torch.gather(before, 2, best[..., None, None].expand(-1, -1, -1, 5, 2))
        torch.testing.assert_close(after[:, :, -2:], kept, rtol=0, atol=0)
        assert not torch.equal(rescored[..., -2:], torch.gather(scores, 2, best))
    last, scores = seen[-1]
    best = scores.topk(2, dim=-1).indices
    kept = torch.gather(last, 2, best[..., None, None].expand(-1, -1, -1, 5, 2))
    torch.testing.assert_close(cem.last_elites, kept, rtol=0, atol=0)


def test_an_absent_initial_elite_never_wins_and_a_present_one_does():
    def distance_to_low(candidates):
        return -candidates.pow(2).sum(dim=(-1, -2))

    low, high = torch.zeros(1, 1, 1, 1), torch.ones(1, 1, 1, 1)
    mean = torch.full((1, 2, 10, 1), 0.5)
    optimum = torch.zeros(1, 2, 1, 10, 1)
    valid = torch.tensor([True, False]).view(1, 2, 1)
    cem = ICEMOptimizer(8, 2, 2, 1e-9, 0.1, torch.Generator().manual_seed(0), keep_best=True)
    best = cem.optimize(
        distance_to_low,
        mean,
        low,
        high,
        initial_elites=optimum,
        initial_valid=valid,
    )
    assert bool((best[0, 0] == 0).all())  # the present one is the optimum, kept as the best
    assert distance_to_low(best[:, 1:2].unsqueeze(2)).item() < -1e-3  # sampled ones miss it


def test_sync_free_path_keeps_the_same_elites_as_the_early_break():
    obs = torch.tensor([[[1.0, 0.0]], [[-1.0, 0.5]]])
    out = {}
    for sync in (True, False):
        planner = point_mass_planner(
            keep_elites=0.5, noise_beta=2.0, elites=3, alpha=0.0, iterations=8, epsilon=0.5
        )
        planner.optimizer.host_sync = sync
        # one decision: the sync-free path draws the noise of every iteration, so the
        # generator (and the next decision) differs after an early stop
        out[sync] = (planner.plan(obs), planner.warm_start_elites, planner.last_iterations)
    torch.testing.assert_close(out[True][0], out[False][0], rtol=0, atol=0)
    torch.testing.assert_close(out[True][1], out[False][1], rtol=0, atol=0)
    assert out[True][2] == out[False][2] < 8


# ---------------------------------------------------------------- shifted elites
def test_shifted_elites_join_the_next_decision_and_reset_clears_them():
    planner = point_mass_planner(keep_elites=0.5, anchor_candidates=True)
    assert planner.optimizer.kept_elites == 2
    record = Recorder(planner.optimizer)
    obs = torch.tensor([[[1.0, 0.5]], [[-1.0, 0.2]]])  # [M=2, I=1, obs]
    assert planner.warm_start_elites is None
    planner.plan(obs)
    first = record.calls[0]
    assert not bool(first["kwargs"]["initial_valid"].any())  # none yet: marked absent
    last = planner.optimizer.last_elites  # [I, M, K, H, act]
    shifted = planner.warm_start_elites  # [M, I, K, H, act]
    assert shifted.shape == (2, 1, 2, 8, 1)
    torch.testing.assert_close(shifted.transpose(0, 1)[:, :, :, :-1], last[:, :, :, 1:])
    torch.testing.assert_close(shifted.transpose(0, 1)[:, :, :, -1], last[:, :, :, -1])

    planner.plan(obs)
    second = record.calls[1]
    # sampled 16, anchors (stop, hold) and the mean 3, then the shifted elites 2
    assert [c.shape[2] for c in second["candidates"]] == [21, 21, 21]
    torch.testing.assert_close(
        second["candidates"][0][:, :, -2:], shifted.transpose(0, 1), rtol=0, atol=0
    )
    assert bool(second["kwargs"]["initial_valid"].all())

    td = TensorDict(
        {("agents", "observation"): obs, "is_init": torch.tensor([[True], [False]])}, [2]
    )
    planner(td)
    valid = record.calls[2]["kwargs"]["initial_valid"]
    assert valid.flatten().tolist() == [False, True]  # env 0 restarted: its elites are gone
    planner.reset()
    assert planner.warm_start_elites is None
    planner.plan(obs)
    assert not bool(record.calls[3]["kwargs"]["initial_valid"].any())


def test_without_shift_elites_nothing_is_carried_across_decisions():
    planner = point_mass_planner(keep_elites=0.5, shift_elites=False)
    record = Recorder(planner.optimizer)
    planner.plan(torch.tensor([[1.0, 0.5]]))
    planner.plan(torch.tensor([[1.0, 0.5]]))
    assert planner.warm_start_elites is None
    assert "initial_elites" not in record.calls[1]["kwargs"]
    assert [c.shape[2] for c in record.calls[1]["candidates"]] == [16, 18, 18]


# ---------------------------------------------------------------- population decay
def test_population_decay_shrinks_each_iteration_to_at_least_twice_the_elites():
    assert sample_sizes(32, 4, 5, 1.0) == [32] * 5
    assert sample_sizes(32, 4, 5, 2.0) == [32, 16, 8, 8, 8]
    assert sample_sizes(32, 4, 3, 1.25) == [32, 25, 20]
    assert sample_sizes(6, 4, 3, 2.0) == [6, 6, 6]  # 2X above Q: Q
    planner = point_mass_planner(population_decay=2.0, iterations=4, elites=2)
    record = Recorder(planner.optimizer)
    planner.plan(torch.tensor([[1.0, 0.5]]))
    assert [c.shape[2] for c in record.calls[0]["candidates"]] == [16, 8, 4, 4]


# ---------------------------------------------------------------- configuration
@pytest.mark.parametrize(
    ("field", "value", "allowed"),
    [
        ("noise_beta", -0.5, ">= 0"),
        ("noise_beta", math.nan, "finite"),
        ("keep_elites", 1.5, r"in \[0, 1\]"),
        ("keep_elites", -0.1, r"in \[0, 1\]"),
        ("population_decay", 0.9, ">= 1"),
        ("population_decay", math.inf, "finite"),
        ("shift_elites", "yes", "true or false"),
    ],
)
def test_bad_values_are_refused_naming_the_field(field, value, allowed):
    with pytest.raises(ConfigError, match=rf"{field} must be .*{allowed}"):
        PlannerConfig(**{field: value})
    with pytest.raises(ConfigError, match=field):
        point_mass_planner(**{field: value})


def test_defaults_are_the_plain_cem():
    config = PlannerConfig()
    assert (config.noise_beta, config.keep_elites, config.population_decay) == (0.0, 0.0, 1.0)
    assert kept_elite_count(0.0, 40) == 0
    assert kept_elite_count(0.3, 40) == 12 and kept_elite_count(0.1, 4) == 1


def test_ts1_layout_counts_the_extra_candidates():
    class TwoMembers(PointMass):
        ensemble_size = 2

    with pytest.raises(ValueError, match="17 candidates scored in a CEM iteration"):
        TrajectorySamplingCEM(
            TwoMembers(),
            quadratic_reward,
            -1.0,
            1.0,
            horizon=4,
            population=16,
            elites=4,
            particles=1,
            propagation="ts1",
            optimizer="icem",
            keep_elites=0.25,  # 16 + 1 rows: odd
        )


# ---------------------------------------------------------------- behaviour
def returns(s0: torch.Tensor, actions: torch.Tensor) -> torch.Tensor:
    """The planner's objective ``sum_t r`` of sequences ``actions [N, H]`` from ``s0 [N, 2]``."""
    pos, vel = s0[:, 0].double(), s0[:, 1].double()
    total = torch.zeros_like(pos)
    for a in actions.double().unbind(-1):
        pos, vel = pos + DT * vel, vel + DT * a
        total -= pos**2 + vel**2 + RHO * a**2
    return total


def lq_optimum(s0: torch.Tensor, horizon: int) -> torch.Tensor:
    """The optimal sequences ``[N, H]`` (unconstrained: inside [-20, 20] here), least squares
    on the stacked rollout ``s_{t+1} = A^{t+1} s0 + sum_k A^{t-k} B a_k``."""
    a_mat = torch.tensor([[1.0, DT], [0.0, 1.0]], dtype=torch.float64)
    b_vec = torch.tensor([[0.0], [DT]], dtype=torch.float64)
    powers = [torch.linalg.matrix_power(a_mat, t) for t in range(horizon + 1)]
    design = torch.zeros(3 * horizon, horizon, dtype=torch.float64)
    for t in range(horizon):
        for k in range(t + 1):
            design[2 * t : 2 * t + 2, k : k + 1] = powers[t - k] @ b_vec
    design[2 * horizon :] = RHO**0.5 * torch.eye(horizon, dtype=torch.float64)
    free = torch.stack(powers[1:]) @ s0.double().T  # [H, 2, N]
    target = torch.cat(
        [
            -free.permute(2, 0, 1).reshape(len(s0), -1),
            torch.zeros(len(s0), horizon, dtype=torch.float64),
        ],
        1,
    )
    return torch.linalg.lstsq(design.expand(len(s0), -1, -1), target.unsqueeze(-1)).solution[..., 0]


STARTS = torch.rand(16, 2, generator=torch.Generator().manual_seed(99)) * torch.tensor(
    [4.0, 2.0]
) - torch.tensor([2.0, 1.0])


def mean_regret(seeds: range, **settings) -> float:
    """Mean regret ``J* - J(plan)`` of one decision over 16 start states (envs) and seeds."""
    best = returns(STARTS, lq_optimum(STARTS, 25))
    regrets = []
    for seed in seeds:
        planner = point_mass_planner(seed, horizon=25, iterations=4, elites=4, **settings)
        planner.plan(STARTS[:, None])
        regrets.append(best - returns(STARTS, planner.last_solution[:, 0, :, 0]))
    return torch.cat(regrets).mean().item()


def test_icem_with_half_the_population_plans_at_least_as_well_as_cem():
    """Known optimum (finite-horizon LQ), iCEM's anchors and keep-best on in both."""
    icem = dict(anchor_candidates=True, keep_best=True)
    seeds = range(6)
    cem_full = mean_regret(seeds, population=32, **icem)
    cem_half = mean_regret(seeds, population=16, **icem)
    sampled = mean_regret(seeds, population=16, noise_beta=2.0, keep_elites=0.3, **icem)
    assert cem_half > 1.2 * cem_full  # halving the population costs the plain CEM
    assert sampled <= cem_full  # ... and colored noise and kept elites win it back


def closed_loop_cost(seeds: range, steps: int, **settings) -> float:
    """True cost of ``steps`` MPC steps from the 16 start states, summed, mean over seeds."""
    costs = []
    for seed in seeds:
        planner = point_mass_planner(seed, horizon=25, iterations=2, **settings)
        s = STARTS.clone()
        for _ in range(steps):
            a = planner.plan(s[:, None])[:, 0, 0]
            s = torch.stack([s[:, 0] + DT * s[:, 1], s[:, 1] + DT * a], dim=1)
            costs.append((s.pow(2).sum(-1) + RHO * a**2).sum().item())
    return sum(costs) / len(seeds)


def test_shifted_elites_and_colored_noise_with_half_the_population_beat_cem_in_closed_loop():
    """Plain CEM (the mean executed): the elites shifted across decisions carry the search."""
    seeds, steps = range(4), 15
    cem_full = closed_loop_cost(seeds, steps, population=32, elites=4)
    cem_half = closed_loop_cost(seeds, steps, population=16, elites=2)
    sampled = closed_loop_cost(
        seeds, steps, population=16, elites=2, noise_beta=2.0, keep_elites=0.5
    )
    assert cem_half > 1.2 * cem_full
    assert sampled <= cem_full
