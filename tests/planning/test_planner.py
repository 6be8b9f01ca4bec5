"""TrajectorySamplingCEM on problems with known answers (point mass, exact linear dynamics)."""

import warnings

import pytest
import torch
from tensordict import TensorDict
from torchrl.collectors import Collector
from torchrl.data import Bounded, Categorical, Composite, Unbounded
from torchrl.envs import EnvBase, InitTracker, TransformedEnv
from torchrl.envs.utils import check_env_specs

from mapets_rl.config import ConfigError
from mapets_rl.models import EnsembleConfig, ProbabilisticEnsemble
from mapets_rl.planning import (
    CPU_PRESET,
    PAPER_PRESET,
    CEMOptimizer,
    DynamicsModel,
    ICEMOptimizer,
    PlannerConfig,
    TrajectorySamplingCEM,
    trajectory_sampling_returns,
)

DT = 0.1
RHO = 0.1


def point_mass_matrix(gain: float = 1.0) -> torch.Tensor:
    """Delta map M with delta = M [pos, vel, a]: pos' = pos + dt vel, vel' = vel + dt gain a."""
    return torch.tensor([[0.0, DT, 0.0], [0.0, 0.0, DT * gain]])


@torch.no_grad()
def linear_ensemble(matrices: list[torch.Tensor], members: int = 5) -> ProbabilisticEnsemble:
    """An ensemble whose every member predicts delta = M_i [s, a] exactly, with ~zero variance.

    Uses silu(z) - silu(-z) = z: hidden units hold (z, -z), so the MLP is exactly linear.
    """
    n_agents = len(matrices)
    out, inp = matrices[0].shape
    width = 2 * out
    model = ProbabilisticEnsemble(
        out, inp - out, n_agents, members, (width, width), init_min_logvar=-40.0
    )
    eye = torch.eye(out)
    mid = torch.cat([torch.cat([eye, -eye], 1), torch.cat([-eye, eye], 1)], 0)
    last = torch.zeros(width, 2 * out)
    last[:, :out] = torch.cat([eye, -eye], 0)
    for i, m in enumerate(matrices):
        model.weights[0][i] = torch.cat([m.T, -m.T], 1)
        model.weights[1][i] = mid
        model.weights[2][i] = last
    for bias in model.biases:
        bias.zero_()
    model.biases[2][..., out:] = -60.0
    return model


def quadratic_reward(obs, action, next_obs):
    """r = -(|s'|^2 + rho a^2)."""
    return -(next_obs.pow(2).sum(-1) + RHO * action.pow(2).sum(-1))


def lq_optimal_first_action(s0: torch.Tensor, gain: float, horizon: int) -> float:
    """Unconstrained finite-horizon LQ optimum by least squares on the stacked rollout."""
    a_mat = torch.tensor([[1.0, DT], [0.0, 1.0]], dtype=torch.float64)
    b_vec = torch.tensor([[0.0], [DT * gain]], dtype=torch.float64)
    rows, rhs = [], []
    for t in range(horizon):  # s_{t+1} = A^{t+1} s0 + sum_k A^{t-k} B a_k
        row = torch.zeros(2, horizon, dtype=torch.float64)
        for k in range(t + 1):
            row[:, k : k + 1] = torch.linalg.matrix_power(a_mat, t - k) @ b_vec
        rows.append(row)
        rhs.append(-torch.linalg.matrix_power(a_mat, t + 1) @ s0.double())
    design = torch.cat(rows + [RHO**0.5 * torch.eye(horizon, dtype=torch.float64)], 0)
    target = torch.cat(rhs + [torch.zeros(horizon, dtype=torch.float64)], 0)
    return torch.linalg.lstsq(design, target.unsqueeze(-1)).solution[0, 0].item()


PLAN = dict(horizon=5, population=200, elites=20, iterations=8, particles=5)


def make_planner(model, **kwargs):
    options = {**PLAN, "seed": 0, **kwargs}
    return TrajectorySamplingCEM(model, quadratic_reward, -20.0, 20.0, **options)


@pytest.mark.parametrize("dtype", [torch.float32, torch.bfloat16])
@pytest.mark.parametrize("propagation", ["ts_inf", "ts1", "expectation"])
def test_optimal_first_action(dtype, propagation):
    gains = [1.0, 2.0]
    model = linear_ensemble([point_mass_matrix(g) for g in gains])
    obs = torch.tensor([[1.0, 0.5], [-2.0, 1.0]])
    planner = make_planner(model, dtype=dtype, propagation=propagation)
    action = planner(TensorDict({("agents", "observation"): obs}))["agents", "action"]
    assert action.shape == (2, 1)
    for i, gain in enumerate(gains):
        best = lq_optimal_first_action(obs[i], gain, PLAN["horizon"])
        assert abs(best) > 1.0  # non-trivial optimum
        assert action[i, 0].item() == pytest.approx(best, abs=0.06 * abs(best) + 0.05)


def test_batched_agents_equal_single_agent_calls():
    gains = [1.0, 0.5, 2.0]
    obs = torch.tensor([[1.0, 0.5], [-2.0, 1.0], [0.3, -0.7]])
    batched = make_planner(linear_ensemble([point_mass_matrix(g) for g in gains]), seed=3)
    joint = batched.plan(obs)
    for i, gain in enumerate(gains):
        single = make_planner(linear_ensemble([point_mass_matrix(gain)]), seed=3)
        torch.testing.assert_close(single.plan(obs[i : i + 1]), joint[i : i + 1])


def test_env_batch_and_warm_start_shift():
    model = linear_ensemble([point_mass_matrix(), point_mass_matrix(0.5)])
    planner = make_planner(model)
    obs = torch.randn(3, 2, 2)  # [envs, I, obs]
    action = planner.plan(obs)
    assert action.shape == (3, 2, 1)
    solution, warm = planner.last_solution, planner.warm_start_mean
    assert warm.shape == solution.shape == (3, 2, PLAN["horizon"], 1)
    torch.testing.assert_close(action, solution[..., 0, :])
    torch.testing.assert_close(warm[..., :-1, :], solution[..., 1:, :])
    assert bool((warm[..., -1, :] == 0.0).all())  # centre of [-20, 20]
    planner.reset()
    assert planner.warm_start_mean is None


def push_up(obs, action, next_obs):
    return action.sum(-1)


def test_is_init_resets_only_that_env():
    planner = TrajectorySamplingCEM(
        linear_ensemble([point_mass_matrix()]), push_up, -1.0, 1.0, seed=0, **PLAN
    )
    obs = torch.randn(2, 1, 2)
    planner.plan(obs)  # converges to +1 everywhere: warm start ~ [1, ..., 1, 0]
    assert bool((planner.warm_start_mean[..., :-1, :] > 0.9).all())
    # With heavy momentum one iteration barely moves the mean: the result reveals the start.
    planner.config = planner.config.replace(alpha=0.99, iterations=1)
    td = TensorDict(
        {("agents", "observation"): obs, "is_init": torch.tensor([[True], [False]])}, [2]
    )
    action = planner(td)["agents", "action"]
    assert abs(action[0].item()) < 0.05  # restarted from the centre of the box
    assert action[1].item() > 0.9  # kept its warm start


def test_early_stop_when_std_collapses():
    model = linear_ensemble([point_mass_matrix()])
    obs = torch.tensor([[1.0, 0.0]])
    stop = make_planner(model, elites=1, alpha=0.0, iterations=5)
    stop.plan(obs)
    assert stop.last_iterations == 1
    full = make_planner(model, iterations=5)
    full.plan(obs)
    assert full.last_iterations == 5


@pytest.mark.parametrize(("elites", "stops_after"), [(1, 1), (3, 3), (5, 4)])
def test_sync_free_early_stop_freezes_the_same_plan(elites, stops_after):
    """Without host syncs (the accelerator path) every iteration runs but the plan freezes
    once sigma collapses: same actions and iteration count as the early break."""
    model = linear_ensemble([point_mass_matrix(), point_mass_matrix(2.0)])
    obs = torch.tensor([[1.0, 0.0], [-1.0, 0.5]])
    plans = {}
    for sync in (True, False):
        planner = make_planner(model, elites=elites, alpha=0.0, iterations=8, epsilon=0.5)
        planner.optimizer.host_sync = sync
        plans[sync] = (planner.plan(obs), planner.last_solution, planner.last_iterations)
    torch.testing.assert_close(plans[True][0], plans[False][0])
    torch.testing.assert_close(plans[True][1], plans[False][1])
    assert plans[True][2] == plans[False][2] == stops_after


def test_actions_clipped_and_nan_safe():
    model = linear_ensemble([point_mass_matrix()])
    planner = TrajectorySamplingCEM(model, push_up, -1.0, 1.0, seed=0, **PLAN)
    action = planner.plan(torch.zeros(1, 2))
    assert action.item() <= 1.0 and action.item() > 0.95

    def nan_above_half(obs, action, next_obs):
        r = -(action.sum(-1) - 0.8).pow(2)
        return torch.where(action.sum(-1) > 0.5, torch.nan, r)

    planner = TrajectorySamplingCEM(model, nan_above_half, -1.0, 1.0, seed=0, **PLAN)
    with pytest.warns(RuntimeWarning, match=r"agent\(s\) \[0\]"):
        action = planner.plan(torch.zeros(1, 2))
    assert torch.isfinite(action).all()
    assert 0.3 < action.item() <= 0.5


def test_bad_input():
    model = linear_ensemble([point_mass_matrix()])
    cases = [
        (dict(elites=300), "elites"),
        (dict(horizon=0), "horizon"),
        (dict(iterations=0), "iterations"),
        (dict(particles=-1), "particles"),
        (dict(particles=7), "particles"),
        (dict(propagation="ts2"), "propagation"),
        (dict(alpha=1.0), "alpha"),
        (dict(epsilon=0.0), "epsilon"),
    ]
    for kwargs, name in cases:
        with pytest.raises(ValueError, match=name):
            make_planner(model, **kwargs)
    with pytest.raises(ValueError, match="action_low"):
        TrajectorySamplingCEM(model, quadratic_reward, 1.0, 1.0, **PLAN)
    with pytest.raises(ValueError, match="action_low"):
        TrajectorySamplingCEM(model, quadratic_reward, [0.0, 0.0], [1.0, 1.0], **PLAN)
    planner = make_planner(model)
    with pytest.raises(ValueError, match="observation"):
        planner.plan(torch.zeros(1, 3))
    with pytest.raises(ValueError, match="observation"):
        planner.plan(torch.zeros(2))
    # the sections validate their own fields; particles vs ensemble_size spans two sections
    # and is checked by MAPETSConfig and by the TrajectorySamplingCEM constructor (above)
    with pytest.raises(ValueError, match="particles"):
        PlannerConfig(particles=0)
    with pytest.raises(ValueError, match="ensemble_size"):
        EnsembleConfig(ensemble_size=0)
    with pytest.raises(ValueError, match="elites"):
        PlannerConfig(elites=500)


@pytest.mark.parametrize("field", PlannerConfig.field_names())
def test_a_built_planner_refuses_setting_a_config_field(field):
    planner = make_planner(linear_ensemble([point_mass_matrix()]), population=8, elites=4)
    before = planner.config
    with pytest.raises(AttributeError, match=rf"{field} is a PlannerConfig setting"):
        setattr(planner, field, getattr(before, field))
    assert planner.config is before


def test_a_replaced_config_is_validated_and_used_from_the_next_decision():
    model = linear_ensemble([point_mass_matrix()])
    planner = make_planner(model, population=8, elites=4)
    with pytest.raises(ConfigError, match=r"elites must be in \[1, population=8\], got 50"):
        planner.config = planner.config.replace(elites=50)
    with pytest.raises(ConfigError, match="population must be >= 1, got 0"):
        planner.config = planner.config.replace(population=0)
    with pytest.raises(ValueError, match=r"particles \(7\) must be divisible"):
        planner.config = planner.config.replace(particles=7)
    assert (planner.config.population, planner.config.elites) == (8, 4)  # unchanged
    obs = torch.tensor([[1.0, 0.0]])
    planner.plan(obs)
    planner.config = planner.config.replace(population=16, iterations=2, horizon=3)
    assert planner.warm_start_mean is None  # a new horizon forgets the warm start
    planner.plan(obs)
    assert planner.last_solution.shape == (1, 3, 1) and planner.last_iterations == 2
    assert planner.optimizer.population == 16


def test_the_config_names_the_optimizer_class():
    model = linear_ensemble([point_mass_matrix()])
    plain = make_planner(model)
    assert plain.config.optimizer == "cem" and type(plain.optimizer) is CEMOptimizer
    assert type(make_planner(model, optimizer="icem").optimizer) is ICEMOptimizer
    for option in (
        {"anchor_candidates": True},
        {"keep_best": True},
        {"noise_beta": 2.0},
        {"keep_elites": 0.5},
        {"population_decay": 2.0},
    ):
        assert type(make_planner(model, optimizer="icem", **option).optimizer) is ICEMOptimizer
        (name,) = option
        with pytest.raises(ConfigError, match=rf"^{name} must be .* with optimizer='cem'"):
            make_planner(model, **option)
    plain.config = plain.config.replace(optimizer="icem", keep_best=True)
    assert type(plain.optimizer) is ICEMOptimizer and plain.optimizer.keep_best


def test_icem_with_every_option_off_equals_the_plain_cem():
    def score(candidates):
        return -(candidates - 0.3).pow(2).sum(dim=(-1, -2))

    low, high = torch.zeros(2, 1, 1, 1), torch.ones(2, 1, 1, 1)
    mean = torch.full((2, 3, 6, 1), 0.5)
    results = [
        optimizer(12, 3, 4, 1e-9, 0.1, torch.Generator().manual_seed(7)).optimize(
            score, mean, low, high
        )
        for optimizer in (CEMOptimizer, ICEMOptimizer)
    ]
    torch.testing.assert_close(results[0], results[1], rtol=0, atol=0)


def test_presets_build_planner_and_model():
    for preset in (PAPER_PRESET, CPU_PRESET):
        model = ProbabilisticEnsemble(7, 1, 2, **preset.model.model_kwargs())
        planner = TrajectorySamplingCEM(model, quadratic_reward, 0.0, 13.89, preset.planner)
        assert planner.config == preset.planner
        assert model.hidden == tuple(preset.model.hidden)


def test_nan_observation_of_one_agent_is_refused_naming_it():
    """A NaN observation is refused at plan entry, naming the agent (issue 23): planned, it
    used to yield a finite action and a warning that blamed reward_fn. The envs zero a crashed
    CAV's observation, so no valid rollout feeds one."""
    model = linear_ensemble([point_mass_matrix(), point_mass_matrix(2.0)])
    obs = torch.tensor([[1.0, 0.5], [-2.0, 1.0]])
    planner = make_planner(model)
    clean = planner.plan(obs)
    broken = obs.clone()
    broken[0, 1] = torch.nan  # e.g. a crashed agent's stale observation
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # refused before any rollout: no reward_fn warning
        with pytest.raises(ValueError, match=r"observation contains NaN .* agent\(s\) \[0\]"):
            planner.plan(broken)
    assert planner.nonfinite_rewards.sum() == 0
    torch.testing.assert_close(make_planner(model).plan(obs), clean)  # the clean one plans


def test_shared_weights_model_plans_like_per_agent_copies():
    shared = ProbabilisticEnsemble(
        2, 1, 2, ensemble_size=5, hidden=(8, 8), share_across_agents=True
    )
    per_agent = ProbabilisticEnsemble(2, 1, 2, ensemble_size=5, hidden=(8, 8))
    state = {k: v.expand_as(per_agent.state_dict()[k]) for k, v in shared.state_dict().items()}
    per_agent.load_state_dict(state)
    obs = torch.tensor([[1.0, 0.5], [-2.0, 1.0]])
    torch.testing.assert_close(make_planner(shared).plan(obs), make_planner(per_agent).plan(obs))


class PointMassEnv(EnvBase):
    """I independent point masses (pos, vel) with the dynamics of ``point_mass_matrix``."""

    def __init__(self, gains: list[float]):
        super().__init__(batch_size=torch.Size([]))
        self.gains = torch.tensor(gains)
        n = len(gains)
        self.full_observation_spec = Composite(
            agents=Composite(observation=Unbounded(shape=(n, 2)), shape=(n,))
        )
        self.full_action_spec = Composite(
            agents=Composite(action=Bounded(-20.0, 20.0, shape=(n, 1)), shape=(n,))
        )
        self.full_reward_spec = Composite(
            agents=Composite(reward=Unbounded(shape=(n, 1)), shape=(n,))
        )
        self.full_done_spec = Composite(
            done=Categorical(2, shape=(1,), dtype=torch.bool),
            terminated=Categorical(2, shape=(1,), dtype=torch.bool),
        )

    def _reset(self, tensordict):
        self.state = torch.stack([torch.ones(len(self.gains)), torch.zeros(len(self.gains))], -1)
        agents = TensorDict({"observation": self.state.clone()}, [len(self.gains)])
        return TensorDict({"agents": agents})

    def _step(self, tensordict):
        action = tensordict["agents", "action"]
        pos, vel = self.state.unbind(-1)
        nxt = torch.stack([pos + DT * vel, vel + DT * self.gains * action[:, 0]], -1)
        reward = quadratic_reward(self.state, action, nxt)
        self.state = nxt
        false = torch.zeros(1, dtype=torch.bool)
        agents = TensorDict(
            {"observation": nxt.clone(), "reward": reward.unsqueeze(-1)}, [len(self.gains)]
        )
        return TensorDict({"agents": agents, "done": false, "terminated": false.clone()})

    def _set_seed(self, seed):
        return seed


def test_collector_drives_planner():
    gains = [1.0, 2.0]
    env = TransformedEnv(PointMassEnv(gains), InitTracker())  # "is_init" resets warm starts
    check_env_specs(env)
    planner = make_planner(linear_ensemble([point_mass_matrix(g) for g in gains]))
    collector = Collector(env, planner, frames_per_batch=20, total_frames=20)
    batch = next(iter(collector))
    collector.shutdown()
    assert batch["agents", "action"].shape == (20, 2, 1)
    positions = batch["next", "agents", "observation"][..., 0].abs()
    assert bool((positions[-1] < 0.75 * positions[0]).all())  # the planner drives both to 0


WALL = 5.0


def crossed_wall(obs, action, next_obs):
    """The point mass reaches the wall at position 5 in this step (a crash)."""
    return (obs[..., 0] < WALL) & (next_obs[..., 0] >= WALL)


def speed_reward(obs, action, next_obs):
    """Speed, minus 50 in the step that crashes into the wall."""
    return next_obs[..., 1] - 50.0 * crossed_wall(obs, action, next_obs).float()


def rollout_positions(obs: torch.Tensor, plan: torch.Tensor, gain: float) -> torch.Tensor:
    """Exact point-mass positions ``[H]`` of the action sequence ``plan`` ``[H, 1]``."""
    pos, vel, out = obs[0].item(), obs[1].item(), []
    for a in plan[:, 0].tolist():
        pos, vel = pos + DT * vel, vel + DT * gain * a
        out.append(pos)
    return torch.tensor(out)


@pytest.mark.parametrize("propagation", ["ts_inf", "expectation"])
def test_predicted_crash_ends_the_particle_so_braking_beats_a_faster_crash(propagation):
    # 5 m before a wall at 10 m/s; |a| <= 5 changes the speed by up to 5 m/s per step. Full
    # throttle crashes at step 4, after which a model that ignores the crash keeps collecting
    # speed reward; staying short of the wall caps the summed speed below 50.
    gain, obs = 10.0, torch.tensor([[0.0, 10.0]])
    model = linear_ensemble([point_mass_matrix(gain)])
    options = dict(PLAN, horizon=10, iterations=10, seed=0, propagation=propagation)
    ending = TrajectorySamplingCEM(
        model, speed_reward, -5.0, 5.0, termination_fn=crossed_wall, **options
    )
    action = ending.plan(obs)
    assert action.item() < -1.0  # brakes at once
    assert rollout_positions(obs[0], ending.last_solution[0], gain).max() < WALL
    # Without the termination the same planner drives into the wall at full throttle.
    ignoring = TrajectorySamplingCEM(model, speed_reward, -5.0, 5.0, **options)
    assert ignoring.plan(obs).item() > 2.0
    assert rollout_positions(obs[0], ignoring.last_solution[0], gain).max() > WALL


def test_candidates_are_scored_under_common_particle_noise():
    model = linear_ensemble([point_mass_matrix()])
    with torch.no_grad():
        model.biases[2][..., 2:] = 0.0  # unit predicted variance: particles really differ
    obs = torch.tensor([[[1.0, 0.5]]])  # [I=1, M=1, obs]
    same = torch.full((1, 1, 6, PLAN["horizon"], 1), 0.7)  # six identical candidates
    generator = torch.Generator().manual_seed(0)
    with torch.no_grad():
        scores, again = (
            trajectory_sampling_returns(
                model, obs, same, quadratic_reward, particles=5, generator=generator
            )[0]
            for _ in range(2)
        )
    # identical candidates, identical scores (up to float rounding) ...
    torch.testing.assert_close(scores, scores[..., :1].expand_as(scores))
    # ... although the noise matters: the next call's draw scores them differently
    assert (again - scores).abs().min() > 1e-2


class ExactPointMass:
    """An exact point-mass simulator: a :class:`DynamicsModel` that is no ensemble (B = 1)."""

    n_agents, obs_dim, action_dim, ensemble_size = 1, 2, 1, 1

    def predict(self, obs, action, dtype=torch.float32):
        mean = torch.cat([DT * obs[..., 1:2], DT * action], dim=-1)
        return mean, torch.full_like(mean, -60.0)


def test_plans_with_any_dynamics_model_not_only_an_ensemble():
    model = ExactPointMass()
    assert isinstance(model, DynamicsModel) and not isinstance(model, torch.nn.Module)
    obs = torch.tensor([[1.0, 0.5]])
    action = make_planner(model).plan(obs)
    best = lq_optimal_first_action(obs[0], 1.0, PLAN["horizon"])
    assert action[0, 0].item() == pytest.approx(best, abs=0.06 * abs(best) + 0.05)
    with pytest.raises(ValueError, match="DynamicsModel"):
        TrajectorySamplingCEM(object(), quadratic_reward, -1.0, 1.0)


def test_reward_fn_of_the_wrong_shape_fails_at_construction():
    model = linear_ensemble([point_mass_matrix(), point_mass_matrix()])
    with pytest.raises(ValueError, match=r"reward_fn must map .* returned \(2, 2, 2\)"):
        TrajectorySamplingCEM(model, lambda s, a, n: n, -1.0, 1.0, **PLAN)
    with pytest.raises(ValueError, match="termination_fn must return a bool"):
        TrajectorySamplingCEM(
            model, quadratic_reward, -1.0, 1.0, termination_fn=lambda s, a, n: n[..., 0], **PLAN
        )


def test_nonfinite_predicted_rewards_are_counted_and_named_once():
    model = linear_ensemble([point_mass_matrix(), point_mass_matrix()])

    def nan_for_agent_1(obs, action, next_obs):
        reward = quadratic_reward(obs, action, next_obs)
        return reward.clone().index_fill_(0, torch.tensor([1]), float("nan"))

    planner = TrajectorySamplingCEM(model, nan_for_agent_1, -20.0, 20.0, seed=0, **PLAN)
    obs = torch.tensor([[1.0, 0.5], [-2.0, 1.0]])
    with pytest.warns(RuntimeWarning, match=r"agent\(s\) \[1\]"):
        first = planner.plan(obs)
    counts = planner.nonfinite_rewards.clone()
    assert counts[0] == 0 and counts[1] > 0
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # warned once only
        planner.plan(obs)
    assert planner.nonfinite_rewards[1] > counts[1]
    # agent 0 still plans its optimum; agent 1 gets a finite action within the bounds
    best = lq_optimal_first_action(obs[0], 1.0, PLAN["horizon"])
    assert first[0, 0].item() == pytest.approx(best, abs=0.06 * abs(best) + 0.05)
    assert torch.isfinite(first[1]).all() and first[1].abs().item() <= 20.0
