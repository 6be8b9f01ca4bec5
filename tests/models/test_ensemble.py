"""ProbabilisticEnsemble, EnsembleNLLLoss and train_ensemble."""

import math

import pytest
import torch
from tensordict import TensorDict

from mapets_rl.models import ProbabilisticEnsemble
from mapets_rl.objectives import EnsembleNLLLoss, ensemble_optimizer, train_ensemble

OBS = ("agents", "observation")
ACT = ("agents", "action")
NEXT = ("next", "agents", "observation")


def true_std(x: torch.Tensor) -> torch.Tensor:
    return 0.05 + 0.15 * (x + 2.0)  # 0.05 at x=-2 ... 0.65 at x=2


def sine_data(rows: int, n_agents: int, generator: torch.Generator) -> TensorDict:
    """y = sin x + noise(x) as a 'delta' of a 1-D state; the action is a constant dummy."""
    x = torch.rand(rows, n_agents, 1, generator=generator) * 4 - 2
    y = torch.sin(x) + true_std(x) * torch.randn(rows, n_agents, 1, generator=generator)
    return TensorDict({OBS: x, ACT: torch.zeros_like(x), NEXT: x + y}, [rows])


def rank(values: torch.Tensor) -> torch.Tensor:
    return torch.argsort(torch.argsort(values)).float()


def spearman(a: torch.Tensor, b: torch.Tensor) -> float:
    ra, rb = rank(a), rank(b)
    ra, rb = ra - ra.mean(), rb - rb.mean()
    return (ra @ rb / (ra.norm() * rb.norm())).item()


@pytest.fixture(scope="module")
def trained():
    torch.manual_seed(0)
    gen = torch.Generator().manual_seed(0)
    model = ProbabilisticEnsemble(1, 1, 2, ensemble_size=5, hidden=(32, 32))
    loss = EnsembleNLLLoss(model, generator=gen)
    optim = torch.optim.Adam(loss.parameters(), lr=3e-3)
    data = sine_data(1024, 2, gen)
    history = train_ensemble(loss, optim, data, epochs=40, batch_size=128, generator=gen)
    return model, loss, history, gen


def predict_1d(model: ProbabilisticEnsemble, x: torch.Tensor):
    """x [N] -> member means / variances [I, B, N] of the delta, same x for every agent."""
    obs = x.view(1, 1, -1, 1).expand(model.n_agents, 1, -1, 1)
    with torch.no_grad():
        mean, logvar = model.predict(obs, torch.zeros_like(obs))
    return mean[..., 0], logvar.exp()[..., 0]


def test_training_reduces_per_member_nll(trained):
    _, _, history, _ = trained
    assert history.shape == (40, 2, 5)
    assert bool((history[-1] < history[0] - 1.0).all())


def test_heteroscedastic_fit_beats_homoscedastic(trained):
    model, _, _, gen = trained
    test = sine_data(2000, 2, gen)
    x, y = test[OBS][..., 0], (test[NEXT] - test[OBS])[..., 0]  # [N, I]
    mean, var = predict_1d(model, x[:, 0])
    mix_mean = mean.mean(1)[0]  # agent 0, moment-matched ensemble
    mix_var = (var + mean.pow(2)).mean(1)[0] - mix_mean.pow(2)
    resid = y[:, 0] - mix_mean
    nll_hetero = 0.5 * (torch.log(2 * math.pi * mix_var) + resid.pow(2) / mix_var).mean()
    homo_var = resid.pow(2).mean()  # best constant variance for the same mean
    nll_homo = 0.5 * (torch.log(2 * math.pi * homo_var) + 1.0)
    assert nll_hetero < nll_homo - 0.1


def test_predicted_std_tracks_true_std(trained):
    model, _, _, _ = trained
    grid = torch.linspace(-1.9, 1.9, 50)
    _, var = predict_1d(model, grid)
    for agent in range(model.n_agents):
        aleatoric = var[agent].mean(0).sqrt()
        assert spearman(aleatoric, true_std(grid)) > 0.8


def test_members_disagree_away_from_data(trained):
    model, _, _, _ = trained
    mean_in, _ = predict_1d(model, torch.linspace(-1.5, 1.5, 30))
    mean_out, _ = predict_1d(model, torch.linspace(5.0, 8.0, 30))
    assert mean_out.std(1).mean() > 3 * mean_in.std(1).mean()


def test_tensordict_forward_matches_raw_path_and_agents_are_independent():
    torch.manual_seed(0)
    model = ProbabilisticEnsemble(3, 2, 4, ensemble_size=3, hidden=(8, 8))
    obs, act = torch.randn(5, 6, 4, 3), torch.randn(5, 6, 4, 2)
    td = model(TensorDict({OBS: obs, ACT: act}, [5, 6]))
    mean, logvar = td["agents", "delta_mean"], td["agents", "delta_logvar"]
    assert mean.shape == logvar.shape == (5, 6, 4, 3, 3)
    # The same agent, evaluated alone by a one-agent model holding its weights.
    single = ProbabilisticEnsemble(3, 2, 1, ensemble_size=3, hidden=(8, 8))
    state = {k: v[2:3] for k, v in model.state_dict().items()}
    single.load_state_dict(state)
    alone = single(TensorDict({OBS: obs[:, :, 2:3], ACT: act[:, :, 2:3]}, [5, 6]))
    torch.testing.assert_close(alone["agents", "delta_mean"][:, :, 0], mean[:, :, 2])
    assert bool((logvar <= model.max_logvar.max()).all())


def test_share_across_agents():
    model = ProbabilisticEnsemble(2, 1, 3, ensemble_size=2, hidden=(8,), share_across_agents=True)
    assert model.weights[0].shape == (1, 2, 3, 8)
    obs = torch.randn(4, 1, 2).expand(4, 3, 2)
    td = model(TensorDict({OBS: obs, ACT: torch.ones(4, 3, 1)}, [4]))
    mean = td["agents", "delta_mean"]
    torch.testing.assert_close(mean[:, 0], mean[:, 2])
    loss = EnsembleNLLLoss(model)
    data = TensorDict({OBS: obs, ACT: torch.ones(4, 3, 1), NEXT: obs + 1}, [4])
    out = loss(data)
    (out["loss_nll"] + out["loss_logvar_bounds"]).backward()
    assert model.weights[0].grad.abs().sum() > 0


def test_fit_normalizer_per_agent_with_mask():
    model = ProbabilisticEnsemble(1, 1, 2, ensemble_size=2, hidden=(4,))
    obs = torch.stack([torch.randn(200, 1) * 3 + 5, torch.randn(200, 1)], 1)  # [N, I, 1]
    mask = torch.ones(200, 2, dtype=torch.bool)
    mask[100:, 1] = False
    obs[100:, 1] = torch.nan  # padding of the smaller dataset
    model.fit_normalizer(obs, torch.zeros_like(obs), obs + 2.0, mask)
    assert model.input_mean[0, 0, 0, 0].item() == pytest.approx(obs[:, 0].mean().item(), abs=1e-4)
    assert model.input_mean[1, 0, 0, 0].item() == pytest.approx(
        obs[:100, 1].mean().item(), abs=1e-4
    )
    assert model.input_std[0, 0, 0, 1].item() == 1.0  # constant action: std replaced by 1
    assert model.output_mean[:, 0, 0, 0].tolist() == pytest.approx([2.0, 2.0])
    loss = EnsembleNLLLoss(model)
    td = TensorDict({OBS: obs, ACT: torch.zeros_like(obs), NEXT: obs + 2.0}, [200])
    td["agents", "mask"] = mask
    out = loss(td)
    assert torch.isfinite(out["loss_nll"]) and out["nll_per_member"].shape == (2, 2)


def test_bootstrap_is_reproducible_and_per_member():
    model = ProbabilisticEnsemble(1, 1, 1, ensemble_size=4, hidden=(4,))
    with torch.no_grad():  # identical members: differences come from the resamples only
        for p in (*model.weights, *model.biases):
            p.copy_(p[:, :1].expand_as(p))
    data = sine_data(64, 1, torch.Generator().manual_seed(1))
    a = EnsembleNLLLoss(model, generator=torch.Generator().manual_seed(5))(data)
    b = EnsembleNLLLoss(model, generator=torch.Generator().manual_seed(5))(data)
    torch.testing.assert_close(a["nll_per_member"], b["nll_per_member"])
    assert a["nll_per_member"].unique().numel() == 4
    flat = EnsembleNLLLoss(model, bootstrap=False)(data)["nll_per_member"]
    assert flat.unique().numel() == 1


def test_set_keys():
    model = ProbabilisticEnsemble(1, 1, 1, ensemble_size=2, hidden=(4,))
    loss = EnsembleNLLLoss(model)
    loss.set_keys(observation="obs", action="act", next_observation=("next", "obs"))
    td = TensorDict({"obs": torch.zeros(3, 1, 1), "act": torch.zeros(3, 1, 1)}, [3])
    td["next", "obs"] = torch.ones(3, 1, 1)
    assert loss(td)["nll_per_member"].shape == (1, 2)


def test_bad_input():
    with pytest.raises(ValueError, match="ensemble_size"):
        ProbabilisticEnsemble(2, 1, 1, ensemble_size=0)
    with pytest.raises(ValueError, match="n_agents"):
        ProbabilisticEnsemble(2, 1, 0)
    with pytest.raises(ValueError, match="hidden"):
        ProbabilisticEnsemble(2, 1, 1, hidden=(8, 0))
    model = ProbabilisticEnsemble(2, 1, 3, ensemble_size=2, hidden=(4,))
    loss = EnsembleNLLLoss(model)
    obs = torch.randn(10, 3, 2)
    bad = obs.clone()
    bad[4, 1, 0] = torch.nan
    data = TensorDict({OBS: bad, ACT: torch.zeros(10, 3, 1), NEXT: obs}, [10])
    with pytest.raises(ValueError, match=r"'obs'.*agent\(s\) \[1\]"):
        loss(data)
    with pytest.raises(ValueError, match="agent"):
        train_ensemble(loss, torch.optim.Adam(loss.parameters()), data)
    wrong = TensorDict({OBS: torch.randn(10, 2, 2), ACT: torch.zeros(10, 2, 1), NEXT: obs}, [10])
    with pytest.raises(ValueError, match="n_agents"):
        loss(wrong)
    with pytest.raises(ValueError, match="observation"):
        model(TensorDict({OBS: torch.randn(4, 3, 5), ACT: torch.zeros(4, 3, 1)}, [4]))
    good = TensorDict({OBS: obs, ACT: torch.zeros(10, 3, 1), NEXT: obs}, [10])
    with pytest.raises(ValueError, match="epochs"):
        train_ensemble(loss, torch.optim.Adam(loss.parameters()), good, epochs=0)
    with pytest.raises(ValueError, match="batch_size"):
        train_ensemble(loss, torch.optim.Adam(loss.parameters()), good, batch_size=0)


def _masked_data(rows: int = 40, n_agents: int = 2) -> TensorDict:
    gen = torch.Generator().manual_seed(3)
    obs = torch.randn(rows, n_agents, 3, generator=gen)
    act = torch.rand(rows, n_agents, 1, generator=gen)
    mask = torch.rand(rows, n_agents, generator=gen) > 0.2
    nxt = obs + 0.1 * torch.tanh(obs) + act
    nxt[~mask] = float("nan")  # masked rows may hold anything
    return TensorDict(
        {
            ("agents", "observation"): obs,
            ("agents", "action"): act,
            ("next", "agents", "observation"): nxt,
            ("agents", "mask"): mask,
        },
        [rows],
    )


@pytest.mark.parametrize("bootstrap", [True, False])
def test_train_ensemble_equals_steps_of_the_tensordict_loss(bootstrap):
    """The fast path (dataset normalised once, one gather per step) takes exactly the steps of
    the documented loop: shuffle, TensorDict minibatch, loss forward, Adam step."""
    data = _masked_data()
    results = []
    for fast in (True, False):
        torch.manual_seed(0)
        model = ProbabilisticEnsemble(3, 1, 2, ensemble_size=3, hidden=(16, 16))
        loss = EnsembleNLLLoss(
            model, bootstrap=bootstrap, generator=torch.Generator().manual_seed(1)
        )
        optim = ensemble_optimizer(loss, lr=1e-2)
        shuffle = torch.Generator().manual_seed(2)
        if fast:
            history = train_ensemble(loss, optim, data, epochs=3, batch_size=16, generator=shuffle)
        else:
            loss.fit_normalizer(data)
            history = []
            for _ in range(3):
                order = torch.randperm(40, generator=shuffle)
                per_member = []
                for start in range(0, 40, 16):
                    out = loss(data[order[start : start + 16]])
                    optim.zero_grad(set_to_none=True)
                    (out["loss_nll"] + out["loss_logvar_bounds"]).backward()
                    optim.step()
                    per_member.append(out["nll_per_member"])
                history.append(torch.stack(per_member).mean(0))
            history = torch.stack(history)
        results.append((history, [p.detach().clone() for p in model.parameters()]))
    (fast_hist, fast_params), (ref_hist, ref_params) = results
    assert fast_hist.shape == (3, 2, 3) and fast_hist.isfinite().all()
    torch.testing.assert_close(fast_hist, ref_hist)
    for a, b in zip(fast_params, ref_params, strict=True):
        torch.testing.assert_close(a, b)
    assert fast_hist[-1].mean() < fast_hist[0].mean()


def test_ensemble_optimizer_is_fused_adam_on_cpu():
    loss = EnsembleNLLLoss(ProbabilisticEnsemble(3, 1, 2, ensemble_size=2, hidden=(8,)))
    optim = ensemble_optimizer(loss, lr=3e-3)
    assert isinstance(optim, torch.optim.Adam)
    group = optim.param_groups[0]
    assert group["lr"] == 3e-3 and group["fused"] is True
    assert len(group["params"]) == len(list(loss.parameters()))


def test_bf16_predictions_follow_fused_adam_updates():
    """A fused Adam step changes the parameters without bumping their version counters; a
    prediction in another dtype after the step must still see the new weights (a cache keyed
    on versions planned every later episode with stale weights)."""
    torch.manual_seed(0)
    model = ProbabilisticEnsemble(3, 1, 2, ensemble_size=2, hidden=(8,))
    optim = ensemble_optimizer(EnsembleNLLLoss(model), lr=1e-1)
    obs, act = torch.randn(2, 2, 5, 3), torch.randn(2, 2, 5, 1)

    def predict_bf16() -> torch.Tensor:
        with torch.no_grad(), model.frozen_parameters(torch.bfloat16):
            first = model.predict(obs, act, dtype=torch.bfloat16)[0]
            torch.testing.assert_close(model.predict(obs, act, dtype=torch.bfloat16)[0], first)
            return first

    before = predict_bf16()
    model.predict(obs, act)[0].square().sum().backward()
    optim.step()
    after = predict_bf16()
    assert not torch.equal(before, after)
    torch.testing.assert_close(after, model.predict(obs, act, dtype=torch.bfloat16)[0])
    assert model._param_cache is None  # nothing outlives the block
