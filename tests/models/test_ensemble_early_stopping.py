"""Early stopping of the ensemble refit on a held-out NLL (fit_ensemble's ``holdout``)."""

from __future__ import annotations

import json

import pytest
import torch
from tensordict import TensorDict

from mapets_rl.experiment import ConfigError
from mapets_rl.models import EnsembleConfig, ProbabilisticEnsemble
from mapets_rl.objectives import (
    EnsembleNLLLoss,
    ensemble_optimizer,
    fit_ensemble,
    holdout_split,
    train_ensemble,
)
from mapets_rl.recipes.mapets import MAPETS, MAPETSConfig

OBS = ("agents", "observation")
ACT = ("agents", "action")
NEXT = ("next", "agents", "observation")
MASK = ("agents", "mask")


def linear_data(rows: int, n_agents: int, seed: int = 0, noise: float = 0.1) -> TensorDict:
    """next = obs + 0.5 * action + noise: a delta the ensemble fits in a few epochs. Agent 1
    holds only 2/3 of the rows (the rest is NaN padding with mask False)."""
    gen = torch.Generator().manual_seed(seed)
    obs = torch.randn(rows, n_agents, 2, generator=gen)
    action = torch.randn(rows, n_agents, 1, generator=gen)
    nxt = obs + 0.5 * action + noise * torch.randn(rows, n_agents, 2, generator=gen)
    mask = torch.ones(rows, n_agents, dtype=torch.bool)
    mask[2 * rows // 3 :, 1] = False
    nxt[~mask] = float("nan")
    return TensorDict({OBS: obs, ACT: action, NEXT: nxt, MASK: mask}, [rows])


def make(share: bool = False, seed: int = 0):
    torch.manual_seed(seed)
    model = ProbabilisticEnsemble(
        2, 1, 3, ensemble_size=4, hidden=(32, 32), share_across_agents=share
    )
    loss = EnsembleNLLLoss(model, generator=torch.Generator().manual_seed(seed + 1))
    return model, loss, ensemble_optimizer(loss, lr=3e-3)


def reference_train(loss, optimizer, data, epochs, batch_size, generator):
    """The training loop as it was before early stopping (fixed epochs, every row)."""
    batch = loss.read_batch(data)
    loss.model.fit_normalizer(*batch)
    x, y, weight = loss.normalized_data(*batch)
    rows, history = data.batch_size[0], []
    for _ in range(epochs):
        order = torch.randperm(rows, generator=generator)
        per_member = []
        for start in range(0, rows, batch_size):
            nll, bounds = loss.member_losses(x, y, weight, order[start : start + batch_size])
            optimizer.zero_grad(set_to_none=True)
            (nll.sum() + bounds).backward()
            optimizer.step()
            per_member.append(nll.detach())
        history.append(torch.stack(per_member).mean(0))
    return torch.stack(history)


@torch.no_grad()
def heldout_nll(model, data, held):
    """Independent per-member NLL [I, B] of the rows ``held`` [I, N] (EnsembleNLLLoss, no
    bootstrap, one agent's rows at a time through the mask)."""
    check = EnsembleNLLLoss(model, bootstrap=False)
    test = data.clone()
    test.set(MASK, held.transpose(0, 1))
    return check(test)["nll_per_member"]


def test_holdout_zero_trains_exactly_as_before():
    data = linear_data(96, 3)
    model, loss, optim = make()
    ref_model, ref_loss, ref_optim = make()
    fit = fit_ensemble(
        loss, optim, data, epochs=3, batch_size=16, generator=torch.Generator().manual_seed(5)
    )
    ref = reference_train(ref_loss, ref_optim, data, 3, 16, torch.Generator().manual_seed(5))
    assert fit.epochs == 3 and fit.holdout_nll is None and fit.best_epoch is None
    assert torch.equal(fit.train_nll, ref)
    for a, b in zip(model.parameters(), ref_model.parameters(), strict=True):
        assert torch.equal(a, b)
    # train_ensemble's defaults are the same fixed-epoch training
    model2, loss2, optim2 = make()
    history = train_ensemble(
        loss2, optim2, data, epochs=3, batch_size=16, generator=torch.Generator().manual_seed(5)
    )
    assert torch.equal(history, ref)


def test_holdout_split_respects_the_mask_and_the_generator():
    mask = torch.zeros(50, 3, dtype=torch.bool)
    mask[:50, 0], mask[:21, 1], mask[:3, 2] = True, True, True
    held = holdout_split(mask, 50, 3, 0.2, torch.Generator().manual_seed(0))
    assert held.shape == (3, 50)
    assert held.sum(1).tolist() == [10, 4, 0]  # floor(0.2 * n_i)
    assert not (held & ~mask.T).any()  # never a padding row
    again = holdout_split(mask, 50, 3, 0.2, torch.Generator().manual_seed(0))
    other = holdout_split(mask, 50, 3, 0.2, torch.Generator().manual_seed(1))
    assert torch.equal(held, again) and not torch.equal(held, other)


def test_stops_early_on_a_quick_fit_and_learns_it():
    data = linear_data(240, 3)
    model, loss, optim = make()
    fit = fit_ensemble(
        loss,
        optim,
        data,
        epochs=300,
        batch_size=32,
        generator=torch.Generator().manual_seed(2),
        holdout=0.25,
        patience=3,
    )
    assert 3 < fit.epochs < 100
    assert fit.train_nll.shape == (fit.epochs, 3, 4)
    assert fit.holdout_nll.shape == (fit.epochs + 1, 3, 4)
    # the known answer: delta = 0.5 * action (noise std 0.1)
    obs = torch.randn(3, 1, 200, 2)
    action = torch.randn(3, 1, 200, 1)
    with torch.no_grad():
        mean, logvar = model.predict(obs, action)
    err = mean - 0.5 * action
    assert err.pow(2).mean().sqrt() < 0.05
    assert logvar.exp().mean().sqrt() == pytest.approx(0.1, rel=0.5)


@pytest.mark.parametrize("share", [False, True])
def test_kept_weights_are_no_worse_on_the_holdout_than_the_last_epoch(share):
    data = linear_data(240, 3, seed=1, noise=0.02)
    model, loss, optim = make(share)
    fit = fit_ensemble(
        loss,
        optim,
        data,
        epochs=40,
        batch_size=32,
        generator=torch.Generator().manual_seed(3),
        holdout=0.25,
        patience=40,  # runs every epoch: the last is rarely every member's best
        min_improvement=0.0,
    )
    assert fit.epochs == 40
    # the split is the generator's first draw: recomputed here, it gives the same rows
    held = holdout_split(data.get(MASK), 240, 3, 0.25, torch.Generator().manual_seed(3))
    final = heldout_nll(model, data, held)  # [I, B]
    torch.testing.assert_close(final, fit.final_holdout_nll)
    last = fit.holdout_nll[-1]
    if share:  # one set of members for all agents: the score pools the agents' rows
        count = held.sum(1, keepdim=True).float()
        final, last = ((v * count).sum(0) / count.sum() for v in (final, last))
    assert bool((final <= last + 1e-6).all())
    assert bool((fit.best_epoch < fit.epochs).any())  # some member went back to its best
    assert float(final.mean()) < float(last.mean())


def test_a_custom_loss_trains_with_a_holdout():
    class MeanLoss(EnsembleNLLLoss):  # redefines forward: trained on TensorDict minibatches
        def forward(self, tensordict):
            x, y, weight = self.normalized_data(*self.read_batch(tensordict))
            nll, bounds = self.member_losses(x, y, weight)
            return TensorDict({"loss_nll": nll.sum(), "loss_b": bounds}, [])

    data = linear_data(120, 3)
    model = ProbabilisticEnsemble(2, 1, 3, ensemble_size=2, hidden=(16,))
    loss = MeanLoss(model)
    fit = fit_ensemble(
        loss, ensemble_optimizer(loss), data, epochs=5, batch_size=32, holdout=0.2, patience=2
    )
    assert 1 <= fit.epochs <= 5 and fit.final_holdout_nll.shape == (3, 2)
    assert int(data.get(MASK).sum()) == 120 + 80 + 120  # the caller's mask is left alone


@pytest.mark.parametrize(
    ("field", "value", "message"),
    [
        ("holdout", 0.5, "holdout must be in [0, 0.5) (0: off), got 0.5"),
        ("holdout", -0.1, "holdout must be in [0, 0.5) (0: off), got -0.1"),
        ("patience", 0, "patience must be >= 1, got 0"),
        ("min_improvement", 1.0, "min_improvement must be in [0, 1), got 1.0"),
        ("min_improvement", -0.01, "min_improvement must be in [0, 1), got -0.01"),
    ],
)
def test_bad_early_stopping_config_is_a_one_line_error(field, value, message):
    with pytest.raises(ConfigError) as err:
        EnsembleConfig(**{field: value})
    assert str(err.value) == message
    with pytest.raises(ConfigError, match=f"model.{field} must be"):
        MAPETSConfig(preset="cpu").with_overrides([f"model.{field}={value}"])


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"holdout": 0.5}, "holdout must be in"),
        ({"holdout": float("nan")}, "holdout"),
        ({"patience": 0}, "patience must be a positive integer"),
        ({"min_improvement": 2.0}, "min_improvement must be in"),
    ],
)
def test_bad_fit_ensemble_arguments(kwargs, match):
    _, loss, optim = make()
    with pytest.raises(ValueError, match=match):
        fit_ensemble(loss, optim, linear_data(30, 3), **kwargs)


TINY = dict(
    env_config={"n_cavs": 3, "n_hvs": 2, "horizon": 20},
    preset="cpu",
    planner={"horizon": 3, "population": 8, "elites": 2, "iterations": 2, "particles": 5},
    model={
        "hidden": [16],
        "buffer_size": 64,
        "batch_size": 16,
        "epochs": 6,
        "holdout": 0.25,
        "patience": 1,
        "min_improvement": 0.03,
    },
    num_threads=1,
    progress=False,
    seed=3,
)


def test_mapets_with_early_stopping_trains_and_resumes_like_an_uninterrupted_run(tmp_path):
    run_dir = tmp_path / "run"
    MAPETS(MAPETSConfig(**TINY, episodes=2), run_dir).train()
    resumed = MAPETS.from_run_dir(run_dir, overrides=["episodes=3"])
    assert resumed.config.model.holdout == 0.25 and resumed.episode == 2
    resumed.train()
    entries = json.loads((run_dir / "results.json").read_text())["train"]
    straight = MAPETS(MAPETSConfig(**TINY, episodes=3), tmp_path / "straight")
    straight.train()
    for got, ref in zip(entries, straight.results.train, strict=True):
        m = got["metrics"]
        assert 1 <= m["model_epochs"] <= 6 and m["model_epochs"] == ref["metrics"]["model_epochs"]
        for key in ("model_nll", "model_holdout_nll", "safety", "reward"):
            assert m[key] == pytest.approx(ref["metrics"][key], rel=1e-5)
    assert any(e["metrics"]["model_epochs"] < 6 for e in entries)  # it did stop early
    for a, b in zip(resumed.model.parameters(), straight.model.parameters(), strict=True):
        torch.testing.assert_close(a, b)
