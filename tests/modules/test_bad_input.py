"""Tensors at module boundaries (ensemble, NLL loss, planner, critics, losses, communication
range; the checks of ``mapets_rl.modules.tensor_checks``): a missing key, a wrong shape, a
non-finite value, a bad mask or coefficient is refused with a one-line ValueError naming the
entry (a TypeError for a wrong dtype or a string for a torch.dtype)."""

from __future__ import annotations

import warnings
from collections.abc import Callable
from typing import Any

import pytest
import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModule

from mapets_rl.comm import CommunicationRange, communication_graph
from mapets_rl.models import ProbabilisticEnsemble
from mapets_rl.objectives import COMACritic, COMALoss, EnsembleNLLLoss, ShapleyActorCriticLoss
from mapets_rl.planning import TrajectorySamplingCEM
from mapets_rl.shapley import CoalitionCritic, RandomCoalition, make_coalition_actor
from tests.refusals import INF, NAN, refused

# ---------------------------------------------------------- tensors at module boundaries
OBS, ACT, MASK = ("agents", "observation"), ("agents", "action"), ("agents", "mask")
NEXT_OBS = ("next", "agents", "observation")
COALITION = ("agents", "coalition")
N_AG, OBS_DIM, ACT_DIM, ROWS = 3, 4, 2, 32


def _td(entries: dict, batch: int | tuple[int, ...], **changes: Any) -> TensorDict:
    """``entries`` with ``changes`` (keyed by the entry's name; ``None`` drops the key)."""
    named = {**entries, **changes}
    return TensorDict(dict(item for item in named.values() if item is not None), batch)


def _ensemble(n_agents: int = N_AG) -> ProbabilisticEnsemble:
    torch.manual_seed(0)
    return ProbabilisticEnsemble(OBS_DIM, ACT_DIM, n_agents, ensemble_size=2, hidden=(8,))


def _model_batch(n_agents: int = N_AG, **changes: Any) -> TensorDict:
    g = torch.Generator().manual_seed(0)
    entries = {
        "obs": (OBS, torch.randn(ROWS, n_agents, OBS_DIM, generator=g)),
        "action": (ACT, torch.randn(ROWS, n_agents, ACT_DIM, generator=g)),
        "next_obs": (NEXT_OBS, torch.randn(ROWS, n_agents, OBS_DIM, generator=g)),
    }
    changes = {
        k: None if v is None else (entries.get(k, (MASK,))[0], v) for k, v in changes.items()
    }
    return _td(entries, [ROWS], **changes)


def _planner(**kwargs: Any) -> TrajectorySamplingCEM:
    settings = dict(horizon=3, population=8, elites=2, iterations=2, particles=2, dtype="fp32")
    low, high = kwargs.pop("action_low", -1.0), kwargs.pop("action_high", 1.0)

    def reward(obs: torch.Tensor, action: torch.Tensor, next_obs: torch.Tensor) -> torch.Tensor:
        return -next_obs.pow(2).sum(-1)

    return TrajectorySamplingCEM(_ensemble(), reward, low, high, seed=0, **{**settings, **kwargs})


def _warm_planner() -> TrajectorySamplingCEM:
    """A planner that has planned for 4 envs (so that ``is_init`` is read)."""
    planner = _planner()
    planner.plan(torch.zeros(4, N_AG, OBS_DIM))
    return planner


def _critic() -> CoalitionCritic:
    torch.manual_seed(0)
    return CoalitionCritic(N_AG, OBS_DIM, ACT_DIM, num_cells=(8, 8))


def _critic_batch(**changes: Any) -> TensorDict:
    keys = {"obs": OBS, "action": ACT, "coalition": COALITION}
    g = torch.Generator().manual_seed(0)
    entries = {
        "obs": (OBS, torch.randn(5, N_AG, OBS_DIM, generator=g)),
        "action": (ACT, torch.randn(5, N_AG, ACT_DIM, generator=g)),
        "coalition": (COALITION, torch.ones(5, N_AG, dtype=torch.bool)),
    }
    return _td(entries, [5], **{k: None if v is None else (keys[k], v) for k, v in changes.items()})


def _shapley_loss(**kwargs: Any) -> ShapleyActorCriticLoss:
    torch.manual_seed(0)
    actor = make_coalition_actor(N_AG, OBS_DIM, ACT_DIM, discrete=True, num_cells=(8,))
    return ShapleyActorCriticLoss(actor, _critic(), **kwargs)


SHAPLEY_KEYS = {
    "obs": OBS,
    "action": ACT,
    "coalition": COALITION,
    "next_obs": NEXT_OBS,
    "reward": ("next", "agents", "reward"),
    "terminated": ("next", "agents", "terminated"),
}


def _shapley_batch(**changes: Any) -> TensorDict:
    g = torch.Generator().manual_seed(0)
    action = torch.nn.functional.one_hot(torch.randint(ACT_DIM, (6, N_AG), generator=g), ACT_DIM)
    values = {
        "obs": torch.randn(6, N_AG, OBS_DIM, generator=g),
        "action": action.float(),
        "coalition": torch.ones(6, N_AG, dtype=torch.bool),
        "next_obs": torch.randn(6, N_AG, OBS_DIM, generator=g),
        "reward": torch.rand(6, N_AG, 1, generator=g),
        "terminated": torch.zeros(6, N_AG, 1, dtype=torch.bool),
        **changes,
    }
    return TensorDict({SHAPLEY_KEYS[k]: v for k, v in values.items() if v is not None}, [6])


def _coma_loss(**kwargs: Any) -> COMALoss:
    torch.manual_seed(0)
    actor = TensorDictModule(
        torch.nn.Linear(OBS_DIM, ACT_DIM), in_keys=[OBS], out_keys=[("agents", "logits")]
    )
    critic = TensorDictModule(
        COMACritic(N_AG, OBS_DIM, ACT_DIM, num_cells=[8]),
        in_keys=[OBS, ACT],
        out_keys=[("agents", "action_value")],
    )
    return COMALoss(actor, critic, **kwargs)


COMA_KEYS = {
    "obs": OBS,
    "action": ACT,
    "next_obs": NEXT_OBS,
    "reward": ("next", "agents", "reward"),
    "done": ("next", "done"),
    "terminated": ("next", "terminated"),
}


def _coma_batch(**changes: Any) -> TensorDict:
    g = torch.Generator().manual_seed(0)
    action = torch.nn.functional.one_hot(torch.randint(ACT_DIM, (5, N_AG), generator=g), ACT_DIM)
    values = {
        "obs": torch.randn(5, N_AG, OBS_DIM, generator=g),
        "action": action.float(),
        "next_obs": torch.randn(5, N_AG, OBS_DIM, generator=g),
        "reward": torch.randn(5, N_AG, 1, generator=g),
        "done": torch.zeros(5, 1, dtype=torch.bool),
        "terminated": torch.zeros(5, 1, dtype=torch.bool),
        **changes,
    }
    return TensorDict({COMA_KEYS[k]: v for k, v in values.items() if v is not None}, [5])


HAND = torch.tensor([[0.0, 0.0], [30.0, 40.0], [100.0, 0.0]])


def _positions(position: torch.Tensor, mask: torch.Tensor | None = None) -> TensorDict:
    agents = {"position": position} if mask is None else {"position": position, "mask": mask}
    return TensorDict({"agents": TensorDict(agents, position.shape[:-1])}, position.shape[:-2])


def _half(shape: tuple[int, ...]) -> torch.Tensor:
    return torch.full(shape, 0.5)


def _nan_at(shape: tuple[int, ...], agent: int, value: float = NAN) -> torch.Tensor:
    x = torch.randn(shape)
    x[..., agent, 0] = value
    return x


MISSING_KEY_CASES = [
    (
        "ensemble forward without the action",
        lambda: _ensemble()(_model_batch(action=None)),
        r"ProbabilisticEnsemble needs \('agents', 'action'\) \[\*, 3, 2\] .* missing",
    ),
    (
        "NLL loss without the next observation",
        lambda: EnsembleNLLLoss(_ensemble())(_model_batch(next_obs=None)),
        r"EnsembleNLLLoss needs \('next', 'agents', 'observation'\) \[\*, 3, 4\] .* missing",
    ),
    (
        "planner forward without the observation",
        lambda: _planner()(TensorDict({}, [])),
        r"TrajectorySamplingCEM needs \('agents', 'observation'\) \[\*, n_agents=3, obs_dim=4\]",
    ),
    (
        "critic without the coalition",
        lambda: _critic()(_critic_batch(coalition=None)),
        r"CoalitionCritic needs \('agents', 'coalition'\) \[\*, n_agents=3\] bool .* missing",
    ),
    (
        "Shapley loss without terminated",
        lambda: _shapley_loss()(_shapley_batch(terminated=None)),
        r"ShapleyActorCriticLoss needs \('next', 'agents', 'terminated'\) .* missing",
    ),
    (
        "Shapley actor loss without the action",
        lambda: _shapley_loss().loss_actor(_shapley_batch(action=None)),
        r"ShapleyActorCriticLoss needs \('agents', 'action'\) .* missing",
    ),
    (
        "COMA loss without terminated",
        lambda: _coma_loss()(_coma_batch(terminated=None)),
        r"COMALoss needs \('next', 'terminated'\) \[\*, T, 1\] .* missing",
    ),
    (
        "COMA loss without the reward",
        lambda: _coma_loss()(_coma_batch(reward=None)),
        r"COMALoss needs \('next', 'agents', 'reward'\) \[\*, T, n, 1\] .* missing",
    ),
    (
        "COMA loss without the action",
        lambda: _coma_loss()(_coma_batch(action=None)),
        r"COMALoss needs \('agents', 'action'\) .* missing",
    ),
    (
        "CommunicationRange episode graph without positions",
        lambda: CommunicationRange(10.0).episode_graph(
            TensorDict({("next", "agents", "speed"): torch.zeros(4, N_AG)}, [4])
        ),
        r"episode_graph needs \('next', 'agents', 'position'\) \[\*B, T, I, 2\] .* missing",
    ),
]

SHAPE_AND_DTYPE_CASES = [
    (
        "NLL mask [32, 3] for 2 agents",
        lambda: EnsembleNLLLoss(_ensemble(2))(
            _model_batch(2, mask=torch.ones(ROWS, 3, dtype=torch.bool))
        ),
        r"\('agents', 'mask'\) must have shape \[32, 2\] \(or \[32, 2, 1\]\), got \[32, 3\]",
        ValueError,
    ),
    (
        "NLL bool observations",
        lambda: EnsembleNLLLoss(_ensemble())(
            _model_batch(obs=torch.ones(ROWS, N_AG, OBS_DIM, dtype=torch.bool))
        ),
        r"obs must be a float \(or int\) tensor \[N, n_agents=3, 4\], got dtype torch.bool",
        TypeError,
    ),
    (
        "ensemble forward bool observations",
        lambda: _ensemble()(_model_batch(obs=torch.ones(ROWS, N_AG, OBS_DIM, dtype=torch.bool))),
        r"\('agents', 'observation'\) must be a float \(or int\) tensor .* got dtype torch.bool",
        TypeError,
    ),
    (
        "planner bool observations",
        lambda: _planner().plan(torch.ones(N_AG, OBS_DIM, dtype=torch.bool)),
        r"observation must be a float \(or int\) tensor .* got dtype torch.bool",
        TypeError,
    ),
    (
        "planner is_init of the wrong size",
        lambda: _warm_planner().plan(
            torch.zeros(4, N_AG, OBS_DIM), is_init=torch.zeros(3, 1, dtype=torch.bool)
        ),
        r"is_init must have shape \[4\] or \[4, 1\] .* got \[3, 1\]",
        ValueError,
    ),
    (
        "predict dtype 'fp16'",
        lambda: _ensemble().predict(
            torch.zeros(N_AG, 2, 5, OBS_DIM), torch.zeros(N_AG, 2, 5, ACT_DIM), "fp16"
        ),
        r"dtype must be a torch.dtype \(e.g. torch.bfloat16\) or None, got 'fp16'",
        TypeError,
    ),
]

NON_FINITE_CASES = [
    (
        "ensemble forward NaN observation",
        lambda: _ensemble()(_model_batch(obs=_nan_at((ROWS, N_AG, OBS_DIM), 1))),
        r"\('agents', 'observation'\) contains NaN or inf values for agent\(s\) \[1\]",
    ),
    (
        "critic NaN observation",
        lambda: _critic()(_critic_batch(obs=_nan_at((5, N_AG, OBS_DIM), 2))),
        r"\('agents', 'observation'\) contains NaN or inf values for agent\(s\) \[2\]",
    ),
    (
        "Shapley loss NaN reward",
        lambda: _shapley_loss()(_shapley_batch(reward=torch.full((6, N_AG, 1), NAN))),
        r"\('next', 'agents', 'reward'\) must be finite, got 18 NaN or infinite entries of 18",
    ),
    (
        "COMA loss NaN reward",
        lambda: _coma_loss()(_coma_batch(reward=_nan_at((5, N_AG, 1), 1))),
        r"\('next', 'agents', 'reward'\) contains NaN or inf values for agent\(s\) \[1\]",
    ),
    (
        "CommunicationRange NaN position",
        lambda: CommunicationRange(1000.0)(_positions(_nan_at((N_AG, 2), 1))),
        r"position must be finite for every unmasked agent, got NaN or inf for agent\(s\) \[1\]",
    ),
    (
        "planner NaN observation",
        lambda: _planner().plan(_nan_at((N_AG, OBS_DIM), 0)),
        r"observation contains NaN or inf values for agent\(s\) \[0\]",
    ),
    (
        "planner inf observation",
        lambda: _planner().plan(_nan_at((2, N_AG, OBS_DIM), 2, INF)),
        r"observation contains NaN or inf values for agent\(s\) \[2\]",
    ),
    (
        "planner action_low=-inf, action_high=inf",
        lambda: _planner(action_low=-INF, action_high=INF),
        r"action_low must be finite in every dimension .* got -inf",
    ),
    (
        "planner action_high=[1, inf]",
        lambda: _planner(action_high=[1.0, INF]),
        r"action_high must be finite in every dimension .* got \[1.0, inf\]",
    ),
]

BOOL_AND_MASK_CASES = [
    ("ensemble obs_dim=True", lambda: ProbabilisticEnsemble(True, 1, 1), "obs_dim must be a"),
    ("planner horizon=True", lambda: _planner(horizon=True), "horizon must be an integer"),
    (
        "CommunicationRange(True)",
        lambda: CommunicationRange(True),
        r"comm_range must be a number in \[0, inf\], got True",
    ),
    (
        "NLL mask 0.5",
        lambda: EnsembleNLLLoss(_ensemble())(_model_batch(mask=_half((ROWS, N_AG)))),
        r"\('agents', 'mask'\) must be a bool tensor \[32, 3\] \(or hold only 0 and 1\), got "
        r"dtype torch.float32 with values such as \[0.5, 0.5, 0.5\]",
    ),
    (
        "NLL mask 2",
        lambda: EnsembleNLLLoss(_ensemble())(_model_batch(mask=torch.full((ROWS, N_AG), 2.0))),
        r"\('agents', 'mask'\) must be a bool tensor .* values such as \[2.0, 2.0, 2.0\]",
    ),
    (
        "critic coalition 0.5",
        lambda: _critic()(_critic_batch(coalition=_half((5, N_AG)))),
        r"\('agents', 'coalition'\) must be a bool tensor \[\*, 3\] .* such as \[0.5",
    ),
    (
        "Shapley loss coalition 2",
        lambda: _shapley_loss()(_shapley_batch(coalition=torch.full((6, N_AG), 2))),
        r"\('agents', 'coalition'\) must be a bool tensor .* dtype torch.int64 .* \[2, 2, 2\]",
    ),
    (
        "Shapley actor loss mask 0.5",
        lambda: _shapley_loss().loss_actor(_shapley_batch().set(MASK, _half((6, N_AG)))),
        r"\('agents', 'mask'\) must be a bool tensor \[6, 3\]",
    ),
    (
        "COMA loss mask 0.5",
        lambda: _coma_loss()(_coma_batch().set(MASK, _half((5, N_AG)))),
        r"\('agents', 'mask'\) must be a bool tensor \[\*, n\]",
    ),
    (
        "random coalition mask 0.5",
        lambda: RandomCoalition(N_AG)(_critic_batch().set(MASK, _half((5, N_AG)))),
        r"\('agents', 'mask'\) must be a bool tensor \[5, 3\]",
    ),
    (
        "CommunicationRange mask 0.5",
        lambda: CommunicationRange(1000.0)(_positions(HAND.clone(), _half((N_AG,)))),
        r"mask must be a bool tensor \(3,\) \(or hold only 0 and 1\)",
    ),
    (
        "planner is_init 0.5",
        lambda: _warm_planner().plan(torch.zeros(4, N_AG, OBS_DIM), is_init=_half((4, 1))),
        r"is_init must be a bool tensor \[4, 1\]",
    ),
]

COEFFICIENT_CASES = [
    (
        "logvar_bound_coef=inf",
        lambda: EnsembleNLLLoss(_ensemble(), logvar_bound_coef=INF),
        "logvar_bound_coef must be a finite number >= 0, got inf",
    ),
    (
        "logvar_bound_coef=nan",
        lambda: EnsembleNLLLoss(_ensemble(), logvar_bound_coef=NAN),
        "logvar_bound_coef must be a finite number >= 0, got nan",
    ),
    (
        "Shapley reward_scale=inf",
        lambda: _shapley_loss(reward_scale=INF),
        "reward_scale must be a finite number > 0, got inf",
    ),
    (
        "Shapley logits_reg=inf",
        lambda: _shapley_loss(logits_reg=INF),
        "logits_reg must be a finite number >= 0, got inf",
    ),
    (
        "Shapley gumbel_temperature=inf",
        lambda: _shapley_loss(gumbel_temperature=INF),
        "gumbel_temperature must be a finite number > 0, got inf",
    ),
    (
        "COMA entropy_coeff=inf",
        lambda: _coma_loss(entropy_coeff=INF),
        "entropy_coeff must be a finite number >= 0, got inf",
    ),
    (
        "COMA reward_scale=inf",
        lambda: _coma_loss(reward_scale=INF),
        "reward_scale must be a finite number > 0, got inf",
    ),
    (
        "CommunicationRange seed='abc'",
        lambda: CommunicationRange(10.0, seed="abc"),
        "seed must be None or an int >= 0, got 'abc'",
    ),
]

VALUE_ERROR_CASES = MISSING_KEY_CASES + NON_FINITE_CASES + BOOL_AND_MASK_CASES + COEFFICIENT_CASES


@pytest.mark.parametrize(
    "call, match", [c[1:] for c in VALUE_ERROR_CASES], ids=[c[0] for c in VALUE_ERROR_CASES]
)
def test_module_refuses_bad_tensors_and_arguments(call: Callable[[], Any], match: str) -> None:
    refused(call, match)


@pytest.mark.parametrize(
    "call, match, error",
    [c[1:] for c in SHAPE_AND_DTYPE_CASES],
    ids=[c[0] for c in SHAPE_AND_DTYPE_CASES],
)
def test_module_refuses_wrong_shapes_and_dtypes(
    call: Callable[[], Any], match: str, error: type[Exception]
) -> None:
    refused(call, match, error)


def test_planner_refuses_a_nan_observation_before_any_rollout() -> None:
    """Refused at plan entry: no rollout ran, so no reward_fn warning and no counted reward."""
    planner = _planner()
    with warnings.catch_warnings(record=True) as record:
        warnings.simplefilter("always")
        refused(lambda: planner.plan(_nan_at((N_AG, OBS_DIM), 1)), r"agent\(s\) \[1\]")
    assert [str(w.message) for w in record] == []
    assert int(planner.nonfinite_rewards.sum()) == 0


def test_communication_range_accepts_int_positions() -> None:
    """int64 metres are a legitimate input: cast, the same graph as in float."""
    ints = torch.tensor([[0, 0], [30, 40], [100, 0]])
    for comm_range in (50.0, 100.0, INF):
        expected = communication_graph(ints.float(), comm_range)
        out = CommunicationRange(comm_range)(_positions(ints))["agents", "neighbors"]
        assert torch.equal(out, expected) and out.dtype == torch.bool
    assert int(communication_graph(ints, 50.0).sum()) == 2  # 0-1 at exactly 50 m, both ways


def test_masked_agents_may_hold_non_finite_positions() -> None:
    """Only the unmasked agents' positions must be finite (a removed agent may be anywhere)."""
    position = HAND.clone()
    position[1] = NAN
    mask = torch.tensor([True, False, True])
    out = CommunicationRange(1000.0)(_positions(position, mask))["agents", "neighbors"]
    assert out.tolist() == [[False, False, True], [False, False, False], [True, False, False]]


def test_zero_one_masks_of_any_dtype_act_as_bool_masks() -> None:
    """Float and int masks holding only 0 and 1 stay accepted, with the bool mask's result."""
    mask = torch.rand(ROWS, N_AG, generator=torch.Generator().manual_seed(1)) > 0.3
    loss = EnsembleNLLLoss(_ensemble(), bootstrap=False)
    expected = loss(_model_batch(mask=mask))["nll_per_member"]
    for dtype in (torch.float32, torch.int64, torch.uint8):
        out = loss(_model_batch(mask=mask.to(dtype)))["nll_per_member"]
        torch.testing.assert_close(out, expected)
    critic = _critic()
    coalition = torch.tensor([[1.0, 0.0, 1.0]]).expand(5, N_AG)
    values = critic(_critic_batch(coalition=coalition))["coalition_value"]
    bool_values = critic(_critic_batch(coalition=coalition.bool()))["coalition_value"]
    torch.testing.assert_close(values, bool_values)


def test_predict_still_takes_torch_dtypes_inside_and_outside_frozen_parameters() -> None:
    """The dtype check (behind the cache hit of the planner's ``frozen_parameters`` path)
    leaves valid calls unchanged: None, float32 and bfloat16, inside and outside the block."""
    model = _ensemble()
    obs, action = torch.randn(N_AG, 2, 5, OBS_DIM), torch.randn(N_AG, 2, 5, ACT_DIM)
    with torch.no_grad():
        outside = model.predict(obs, action)
        torch.testing.assert_close(model.predict(obs, action, torch.float32), outside)
        with model.frozen_parameters():
            torch.testing.assert_close(model.predict(obs, action), outside)
        bf16 = model.predict(obs, action, torch.bfloat16)
        with model.frozen_parameters(torch.bfloat16):
            torch.testing.assert_close(model.predict(obs, action, torch.bfloat16), bf16)
    torch.testing.assert_close(bf16, outside, atol=0.1, rtol=0.05)
