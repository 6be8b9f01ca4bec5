"""How many training epochs the MA-PETS world model needs: NLL and gap error against epochs.

Takes the datasets ``D(i)+`` of a finished MA-PETS run (its latest checkpoint), holds out 20% of
every agent's transitions, and trains a fresh ensemble of the run's size on the rest one epoch at
a time (the recipe's loss, optimiser and batch size). After each epoch it reports, on the
held-out transitions:

* the Gaussian NLL (normalised delta space, eq. 9, members averaged, no bootstrap);
* the error of the predicted change of the gap ahead in metres per step, over all rows and over
  rows where the CAV drives faster than 8 m/s: bias (mean predicted - true) and RMSE of the
  members' mean, and the predicted noise (mean predicted std of that delta).

The transitions in which the CAV's neighbours changed identity are not in ``D(i)+`` (the recipe
filters them), so the gap changes here are dynamics.

    python benchmarks/model_epochs.py RUN_DIR [--epochs 60] [--seed 0]

``--compare`` instead weighs early stopping (``model.holdout``, ``model.patience``,
``model.min_improvement``) against fixed epochs. On the same 80% of the transitions, each
setting trains the same ensemble (a fresh one: ``cold``; or, as MA-PETS refits after every
episode, one first trained ``--epochs`` epochs on half of those rows: ``warm``) and reports the
training seconds, the epochs run, and on the 20% that no setting trains or stops on: the NLL
and the gap-ahead RMSE over all rows and over rows faster than 8 m/s. Then it times
``MAPETS.train_models`` itself on the run's datasets (warm, from the checkpoint's model and
optimiser, which already fitted these very datasets: a lower bound on the epochs) for each
setting:

    python benchmarks/model_epochs.py RUN_DIR --compare [--epochs 30] [--holdout 0.2]
        [--patience 2 3 5] [--min-improvement 0.01] [--seeds 0 1]

``RUN_DIR`` e.g. ``outputs/mapets_figure_eight/crossing/d100_seed0`` (from
``examples/mapets_figure_eight.py``). The run directory is only read.
"""

from __future__ import annotations

import argparse
import dataclasses
import shutil
import tempfile
import time
from pathlib import Path

import torch
from tensordict import TensorDict

from mapets_rl.machine import machine_line
from mapets_rl.models import ProbabilisticEnsemble
from mapets_rl.objectives.ensemble_nll import EnsembleNLLLoss, fit_ensemble, train_ensemble
from mapets_rl.recipes.mapets import MAPETS

GAP_AHEAD = 5
#: The loss keys of the flat ``[N, I, *]`` dataset :func:`load_data` builds.
FLAT_KEYS = {
    "observation": "observation",
    "action": "action",
    "next_observation": "next_observation",
    "mask": "mask",
}
SPEED = 0


def load_data(run_dir: Path) -> tuple[MAPETS, TensorDict]:
    """The run (restored from a private copy) and its ``D(i)+`` as a padded batch ``[N, I]``."""
    with tempfile.TemporaryDirectory() as tmp:
        copy = Path(tmp) / "run"
        shutil.copytree(run_dir, copy)
        exp = MAPETS.from_run_dir(copy)
    datasets = exp.datasets
    sets = [datasets.dataset(i) for i in range(exp.n_agents)]
    rows = max(len(d) for d in sets)
    keys = ("observation", "action", "next_observation")
    padded = {key: [] for key in keys}
    for d in sets:
        pad = rows - len(d)
        for key in keys:
            value = d.get(key)
            padded[key].append(torch.cat([value, value[:1].expand(pad, *value.shape[1:])]))
    data = TensorDict({k: torch.stack(v, 1) for k, v in padded.items()}, batch_size=[rows])
    sizes = torch.tensor([len(d) for d in sets])
    data.set("mask", torch.arange(rows)[:, None] < sizes[None, :])
    return exp, data


@torch.no_grad()
def gap_errors(model: ProbabilisticEnsemble, data: TensorDict) -> dict[str, float]:
    """Bias, RMSE and predicted std [m/step] of the gap-ahead delta, all rows and v > 8 m/s."""
    obs, action, nxt, mask = (
        data.get(k) for k in ("observation", "action", "next_observation", "mask")
    )
    obs_t, act_t = obs.transpose(0, 1).unsqueeze(1), action.transpose(0, 1).unsqueeze(1)
    mean, logvar = model.predict(obs_t, act_t)  # [I, B, N, S] (every member on every row)
    pred = mean[..., GAP_AHEAD].mean(1)  # [I, N]
    std = logvar[..., GAP_AHEAD].mul(0.5).exp().mean(1)
    true = (nxt - obs)[..., GAP_AHEAD].transpose(0, 1)
    valid = mask.transpose(0, 1)
    fast = valid & (obs[..., SPEED].transpose(0, 1) > 8.0)
    out = {}
    for name, rows in (("all", valid), ("fast", fast)):
        err = (pred - true)[rows]
        out[f"bias_{name}"] = err.mean().item()
        out[f"rmse_{name}"] = err.pow(2).mean().sqrt().item()
        out[f"std_{name}"] = std[rows].mean().item()
    return out


def split(data: TensorDict, gen: torch.Generator) -> tuple[TensorDict, TensorDict]:
    """(train, test): 20% of the rows (the same for every agent, one draw from ``gen``) masked
    out of ``train`` and only those in ``test``."""
    holdout = torch.rand(data.batch_size, generator=gen) < 0.2
    train = data.clone()
    train.set("mask", data.get("mask") & ~holdout[:, None])
    test = data.clone()
    test.set("mask", data.get("mask") & holdout[:, None])
    return train, test


def new_loss(exp: MAPETS, seed: int, bootstrap: bool = True) -> EnsembleNLLLoss:
    """A fresh ensemble of the run's size (initialised from ``seed``) in the recipe's loss,
    reading the flat dataset keys."""
    cfg = exp.config.model
    torch.manual_seed(seed)
    model = ProbabilisticEnsemble(
        exp.model.obs_dim,
        exp.model.action_dim,
        exp.n_agents,
        ensemble_size=cfg.ensemble_size,
        hidden=tuple(cfg.hidden),
    )
    loss = EnsembleNLLLoss(
        model,
        bootstrap=bootstrap,
        logvar_bound_coef=cfg.logvar_bound_coef,
        generator=torch.Generator().manual_seed(seed + 1),
    )
    loss.set_keys(**FLAT_KEYS)
    return loss


def compare(args: argparse.Namespace) -> None:
    """``--compare``: fixed epochs against early stopping (see the module docstring)."""
    exp, data = load_data(args.run_dir)
    cfg = exp.config.model
    settings = [("fixed", 0.0, 1)] + [(f"p={p}", args.holdout, p) for p in args.patience]
    print(
        f"run {args.run_dir}: {exp.n_agents} agents, |D(i)+| = "
        f"{data.get('mask').sum(0).tolist()}, hidden {cfg.hidden}, B = {cfg.ensemble_size}, "
        f"batch {cfg.batch_size}, lr {cfg.lr}; at most {args.epochs} epochs, early stopping "
        f"holdout {args.holdout}, min_improvement {args.min_improvement}; {machine_line()}"
    )
    print(
        "\n| start | seed | setting | epochs run | train s | CPU s | test NLL | gap RMSE all "
        "| gap RMSE v>8 |"
    )
    print("|---|---|---|---|---|---|---|---|---|")
    for seed in args.seeds:
        train, test = split(data, torch.Generator().manual_seed(seed))
        for start in ("cold", "warm"):
            init = new_loss(exp, seed)
            if start == "warm":  # the previous episode's model: trained on half of the rows
                half = train.clone()
                keep = torch.rand(data.batch_size, generator=torch.Generator().manual_seed(seed))
                half.set("mask", train.get("mask") & (keep < 0.5)[:, None])
                optim = torch.optim.Adam(init.parameters(), lr=cfg.lr)
                train_ensemble(
                    init,
                    optim,
                    half,
                    epochs=args.epochs,
                    batch_size=cfg.batch_size,
                    generator=torch.Generator().manual_seed(seed + 2),
                )
                optim_state = optim.state_dict()
            state = {k: v.clone() for k, v in init.model.state_dict().items()}
            for name, holdout, patience in settings:
                loss = new_loss(exp, seed)
                loss.model.load_state_dict(state)
                optim = torch.optim.Adam(loss.parameters(), lr=cfg.lr)
                if start == "warm":
                    optim.load_state_dict(optim_state)
                begin, cpu = time.perf_counter(), time.process_time()
                fit = fit_ensemble(
                    loss,
                    optim,
                    train,
                    epochs=args.epochs,
                    batch_size=cfg.batch_size,
                    generator=torch.Generator().manual_seed(seed + 3),
                    holdout=holdout,
                    patience=patience,
                    min_improvement=args.min_improvement,
                )
                seconds, cpu = time.perf_counter() - begin, time.process_time() - cpu
                with torch.no_grad():
                    check = new_loss(exp, seed, bootstrap=False)
                    check.model.load_state_dict(loss.model.state_dict())
                    test_nll = check(test)["nll_per_member"].mean().item()
                e = gap_errors(loss.model, test)
                print(
                    f"| {start} | {seed} | {name} | {fit.epochs} | {seconds:.2f} | {cpu:.2f} | "
                    f"{test_nll:.2f} | {e['rmse_all']:.4f} | {e['rmse_fast']:.4f} |",
                    flush=True,
                )
    time_train_models(args, settings)


def time_train_models(args: argparse.Namespace, settings: list) -> None:
    """``MAPETS.train_models`` on the run's datasets, from its checkpoint, per setting."""
    print(
        "\n| MAPETS.train_models | epochs run | seconds | CPU s | model_nll | model_holdout_nll |"
    )
    print("|---|---|---|---|---|---|")
    with tempfile.TemporaryDirectory() as tmp:
        copy = Path(tmp) / "run"
        shutil.copytree(args.run_dir, copy)
        exp = MAPETS.from_run_dir(copy)
        model_state = {k: v.clone() for k, v in exp.model.state_dict().items()}
        optim_state = exp.optimizer.state_dict()
        optim_state = {
            "state": {
                k: {n: t.clone() for n, t in v.items()} for k, v in optim_state["state"].items()
            },
            "param_groups": optim_state["param_groups"],
        }
        base = exp.config.model
        for name, holdout, patience in settings:
            exp.model.load_state_dict(model_state)
            exp.optimizer.load_state_dict(optim_state)
            exp.config.model = dataclasses.replace(
                base,
                epochs=args.epochs,
                holdout=holdout,
                patience=patience,
                min_improvement=args.min_improvement,
            )
            torch.manual_seed(0)
            exp.shuffle_generator.manual_seed(1)
            exp.bootstrap_generator.manual_seed(2)
            begin, cpu = time.perf_counter(), time.process_time()
            m = exp.train_models()
            seconds, cpu = time.perf_counter() - begin, time.process_time() - cpu
            print(
                f"| {name} | {m['model_epochs']:.0f} | {seconds:.2f} | {cpu:.2f} | "
                f"{m['model_nll']:.2f} | "
                f"{m.get('model_holdout_nll', float('nan')):.2f} |",
                flush=True,
            )
        exp.close()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("run_dir", type=Path)
    parser.add_argument("--epochs", type=int, default=None, help="default 60, 30 with --compare")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--report", type=int, nargs="+", default=[1, 2, 5, 10, 15, 20, 30, 40, 60])
    parser.add_argument("--compare", action="store_true", help="fixed epochs vs early stopping")
    parser.add_argument("--holdout", type=float, default=0.2)
    parser.add_argument("--patience", type=int, nargs="+", default=[2, 3, 5])
    parser.add_argument("--min-improvement", type=float, default=0.01)
    parser.add_argument("--seeds", type=int, nargs="+", default=[0])
    args = parser.parse_args()
    if args.epochs is None:
        args.epochs = 30 if args.compare else 60
    if args.epochs < 1:
        parser.error(f"--epochs must be >= 1, got {args.epochs}")
    if args.compare:
        compare(args)
        return
    torch.manual_seed(args.seed)
    exp, data = load_data(args.run_dir)
    cfg = exp.config.model
    gen = torch.Generator().manual_seed(args.seed)
    train, test = split(data, gen)  # gen then drives the training's bootstrap and shuffles
    model = ProbabilisticEnsemble(
        exp.model.obs_dim,
        exp.model.action_dim,
        exp.n_agents,
        ensemble_size=cfg.ensemble_size,
        hidden=tuple(cfg.hidden),
    )
    loss = EnsembleNLLLoss(model, logvar_bound_coef=cfg.logvar_bound_coef, generator=gen)
    loss.set_keys(**FLAT_KEYS)
    holdout_loss = EnsembleNLLLoss(model, bootstrap=False)
    holdout_loss.set_keys(**FLAT_KEYS)
    optimizer = torch.optim.Adam(loss.parameters(), lr=cfg.lr)
    print(
        f"run {args.run_dir}: {exp.n_agents} agents, |D(i)+| = "
        f"{data.get('mask').sum(0).tolist()}, hidden {cfg.hidden}, B = {cfg.ensemble_size}, "
        f"batch {cfg.batch_size}, lr {cfg.lr}; holdout 20%; {machine_line()}"
    )
    print(
        "| epochs | train NLL | holdout NLL | gap bias [m/step] | gap RMSE | gap pred. std "
        "| bias v>8 | RMSE v>8 | pred. std v>8 |"
    )
    print("|---|---|---|---|---|---|---|---|---|")
    for epoch in range(1, args.epochs + 1):
        history = train_ensemble(
            loss,
            optimizer,
            train,
            epochs=1,
            batch_size=cfg.batch_size,
            fit_normalizer=epoch == 1,
            generator=gen,
        )
        if epoch in args.report or epoch == args.epochs:
            with torch.no_grad():
                test_nll = holdout_loss(test)["nll_per_member"].mean().item()
            e = gap_errors(model, test)
            print(
                f"| {epoch} | {history.mean().item():.2f} | {test_nll:.2f} | "
                f"{e['bias_all']:+.3f} | {e['rmse_all']:.3f} | {e['std_all']:.3f} | "
                f"{e['bias_fast']:+.3f} | {e['rmse_fast']:.3f} | {e['std_fast']:.3f} |",
                flush=True,
            )


if __name__ == "__main__":
    from mapets_rl import quiet_dependencies

    quiet_dependencies()
    main()
