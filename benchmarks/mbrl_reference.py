"""mbrl-lib (facebookresearch/mbrl-lib 0.2.0) as an in-process reference for the benchmarks.

``benchmarks/planner.py --reference mbrl-lib`` times mbrl-lib's PETS agent
(``TrajectoryOptimizerAgent`` + ``CEMOptimizer`` over a ``ModelEnv`` wrapping a
``OneDTransitionRewardModel(GaussianMLP)`` ensemble, TS-inf propagation) next to our
``TrajectorySamplingCEM``; ``benchmarks/ensemble_training.py --reference mbrl-lib`` times
mbrl-lib's ``ModelTrainer`` on the same ``GaussianMLP`` ensemble, same data and epochs, one
trainer per agent. mbrl-lib has no multi-agent batching, so ``I`` agents are ``I`` separate
agents/trainers run one after the other; the headline ratio is per agent.

Nothing here installs anything. mbrl 0.2.0 pins ``hydra-core==1.0.3``, ``omegaconf<2.1`` and
``gymnasium==0.26.3``; hydra-core 1.0.3 does not import on Python 3.11 (a dataclass with a
mutable default), and the project's torch and gymnasium must not change. :data:`INSTALL` is
the recipe: a separate virtual environment layered on the project's one (its own
site-packages first, then the project's), with mbrl installed without its pins.

How mbrl-lib's PETS is configured here (its ``conf/algorithm/pets.yaml``,
``conf/action_optimizer/cem.yaml`` and ``conf/dynamics_model/gaussian_mlp_ensemble.yaml``
defaults, with our sizes):

* ``GaussianMLP(num_layers=len(hidden), hid_size, ensemble_size=B, SiLU,
  propagation_method="fixed_model")``: ``fixed_model`` with propagation indices drawn at
  ``ModelEnv.reset`` is mbrl-lib's TS-inf;
* ``OneDTransitionRewardModel(target_is_delta=True, normalize=True,
  normalize_double_precision=True, learned_rewards=False)``: inputs are normalised in float64
  on every model step (mbrl-lib's PETS default);
* ``CEMOptimizer(num_iterations=Y, elite_ratio=X/Q, population_size=Q, alpha,
  return_mean_elites=True, clipped_normal=False)`` (truncated-normal sampling), always ``Y``
  iterations (no early stop), warm start shifted by one step (``keep_last_solution``);
* ``ModelEnv.evaluate_action_sequences(num_particles=P)`` with the known reward and no
  termination (a function returning ``False``).

What differs from our planner at the same sizes (same GEMM shapes and FLOPs on both sides):
mbrl-lib adds the bias and applies SiLU as separate, allocating ops (we fuse the bias into
``baddbmm`` and apply SiLU in place; a profile at the paper config on an AVX2 CPU: ``bmm`` 59%,
``silu`` 19%, bias ``add`` 19% of mbrl-lib's time), permutes the particles before each forward
and scatters them back (TS-inf by ``fixed_model`` indices; we map particle ``p`` to member
``p mod B``), draws truncated-normal candidates (we clip a normal), draws particle noise per
candidate (ours is common to the candidates of an iteration), runs all ``Y`` iterations (ours
stops once every sigma < epsilon; the benchmark prints how many ran) and normalises inputs in
float64. For training it builds minibatches in numpy, computes a gradient norm with one
``.item()`` per parameter and the loss ``.item()`` every step, and uses torch's default Adam
(ours: fused Adam over the stacked ``I x B`` ensemble).
"""

from __future__ import annotations

import sys
import time
from collections.abc import Callable
from types import ModuleType
from typing import Any

import numpy as np
import torch

#: Values accepted by the benchmarks' ``--reference`` flag.
REFERENCES = ("mbrl-lib",)

#: How to install mbrl-lib beside the project's pinned torch without changing it.
INSTALL = """\
mbrl-lib is not importable from this Python ({reason}).
Install it in a separate virtual environment layered on the project's (nothing in the
project's .venv changes; torch stays {torch}):

  python3 -m venv /work/mbrl-venv
  SHARED=$(/work/main/.venv/bin/python -c 'import site; print(site.getsitepackages()[0])')
  OWN=$(/work/mbrl-venv/bin/python -c 'import site; print(site.getsitepackages()[0])')
  echo "import site; site.addsitedir('$SHARED')" > "$OWN/zz_shared_venv.pth"
  /work/mbrl-venv/bin/pip install --no-deps mbrl==0.2.0 hydra-core==1.3.2 omegaconf==2.3.0 \\
      antlr4-python3-runtime==4.9.3 termcolor
  /work/mbrl-venv/bin/python -c "import torch, mbrl.models, mbrl.planning; print(torch.__version__)"

(--no-deps: mbrl 0.2.0 pins hydra-core==1.0.3, which fails to import on Python 3.11, and
gymnasium==0.26.3; the benchmarks use only mbrl.models, mbrl.planning and mbrl.util, which run
with hydra-core 1.3 and the project's gymnasium.) Then run the benchmark with that Python from
the repository root, e.g.

  PYTHONPATH=. /work/mbrl-venv/bin/python benchmarks/planner.py --reference mbrl-lib ...
"""


def import_mbrl() -> ModuleType:
    """Import the parts of mbrl-lib the references use; any failure propagates."""
    import mbrl
    import mbrl.models
    import mbrl.planning
    import mbrl.types
    import mbrl.util.replay_buffer  # noqa: F401

    return mbrl


def require_mbrl(reference: str) -> ModuleType:
    """Return the ``mbrl`` package, or print :data:`INSTALL` and exit with status 2.

    Called right after argument parsing, before any benchmark work.
    """
    if reference not in REFERENCES:
        raise ValueError(f"reference must be one of {list(REFERENCES)}, got {reference!r}.")
    try:
        return import_mbrl()
    except Exception as exc:  # ImportError, or hydra-core 1.0.3's ValueError on Python 3.11
        reason = f"{type(exc).__name__}: {exc}"
        print(INSTALL.format(reason=reason, torch=torch.__version__), file=sys.stderr)
        raise SystemExit(2) from None


def _gaussian_dynamics(
    mbrl: ModuleType,
    in_size: int,
    out_size: int,
    members: int,
    hidden: tuple[int, ...],
    propagation: str | None,
    learn_logvar_bounds: bool,
    device: str = "cpu",
) -> Any:
    """mbrl-lib's ``GaussianMLP`` ensemble (SiLU, equal hidden sizes) inside a
    ``OneDTransitionRewardModel`` predicting normalised state deltas (no learned reward)."""
    if len(set(hidden)) != 1:
        raise ValueError(
            f"mbrl-lib's GaussianMLP has equal hidden sizes, got hidden={list(hidden)}."
        )
    net = mbrl.models.GaussianMLP(
        in_size,
        out_size,
        device,
        num_layers=len(hidden),
        ensemble_size=members,
        hid_size=hidden[0],
        deterministic=False,
        propagation_method=propagation,
        learn_logvar_bounds=learn_logvar_bounds,
        activation_fn_cfg={"_target_": "torch.nn.SiLU"},
    )
    return mbrl.models.OneDTransitionRewardModel(
        net,
        target_is_delta=True,
        normalize=True,
        normalize_double_precision=True,
        learned_rewards=False,
    )


def _copy_member_weights(net: torch.nn.Module, model: torch.nn.Module, agent: int) -> None:
    """Copy agent ``agent``'s layers of our ``ProbabilisticEnsemble`` into a ``GaussianMLP``.

    Both store ``[B, in, out]`` weights and ``[B, 1, out]`` biases per layer. Our model also
    de-normalises its outputs (``output_mean/std``); mbrl-lib's does not, so the predictions
    differ by that affine map (the shapes and FLOPs are the same).
    """
    layers = [seq[0] for seq in net.hidden_layers] + [net.mean_and_logvar]
    with torch.no_grad():
        for layer, weight, bias in zip(layers, model.weights, model.biases, strict=True):
            layer.weight.copy_(weight[agent])
            layer.bias.copy_(bias[agent])


def pets_agents(
    model: torch.nn.Module,
    cfg: object,
    low: float,
    high: float,
    reward_fn: Callable[[torch.Tensor, torch.Tensor, torch.Tensor], torch.Tensor],
    seed: int = 0,
    device: str = "cpu",
) -> list:
    """One mbrl-lib PETS agent per agent of ``model`` (a ``ProbabilisticEnsemble``).

    Args:
        model: our ensemble ``[I agents x B members]``; each mbrl-lib agent gets a
            ``GaussianMLP`` with agent ``i``'s weights and input normalisation.
        cfg: a :class:`~mapets_rl.planning.Preset` (planner and model sizes).
        low, high: scalar action bounds.
        reward_fn: our known reward ``(obs, action, next_obs) -> [...]``; mbrl-lib's reward
            sees only ``(action, next_obs)`` and is given ``next_obs`` as ``obs`` (the
            figure-eight's reads ``obs`` only in its headway test of a closing gap, which
            then never fires: give it ``headway=0`` for the same scores on both sides).
        seed: seeds each agent's ``ModelEnv`` generator.
        device: where mbrl-lib's models, particles and CEM run (``"cpu"``, ``"cuda"``).

    Returns:
        ``I`` ``TrajectoryOptimizerAgent`` s; ``agent.act(obs)`` takes a ``[obs]`` float32
        numpy array and returns a ``[act]`` array.
    """
    import gymnasium
    from omegaconf import OmegaConf

    mbrl = import_mbrl()
    planner, sizes = cfg.planner, cfg.model
    obs_dim, act_dim = model.obs_dim, model.action_dim
    if planner.propagation != "ts_inf":
        raise ValueError(f"the mbrl-lib reference uses TS-inf, got {planner.propagation!r}.")

    class _Spaces:  # ModelEnv reads only the spaces of the env it models
        observation_space = gymnasium.spaces.Box(-np.inf, np.inf, (obs_dim,), np.float32)
        action_space = gymnasium.spaces.Box(low, high, (act_dim,), np.float32)

    def reward(action: torch.Tensor, next_obs: torch.Tensor) -> torch.Tensor:
        return reward_fn(next_obs, action, next_obs).unsqueeze(-1)

    def no_termination(action: torch.Tensor, next_obs: torch.Tensor) -> torch.Tensor:
        return torch.zeros(next_obs.shape[0], 1, dtype=torch.bool, device=next_obs.device)

    agents = []
    for i in range(model.n_agents):
        dynamics = _gaussian_dynamics(
            mbrl,
            obs_dim + act_dim,
            obs_dim,
            sizes.ensemble_size,
            tuple(sizes.hidden),
            "fixed_model",
            learn_logvar_bounds=False,
            device=device,
        )
        _copy_member_weights(dynamics.model, model, i)
        dynamics.input_normalizer.mean = model.input_mean[i, 0].double().to(device)
        dynamics.input_normalizer.std = model.input_std[i, 0].double().to(device)
        model_env = mbrl.models.ModelEnv(
            _Spaces(),
            dynamics,
            no_termination,
            reward,
            generator=torch.Generator(device=device).manual_seed(seed + i),
        )
        agent_cfg = OmegaConf.create(
            {
                "_target_": "mbrl.planning.TrajectoryOptimizerAgent",
                # hydra >= 1.1 instantiates nested configs by default; mbrl 0.2.0 was written
                # for hydra 1.0 and instantiates the optimizer itself from this config.
                "_recursive_": False,
                "action_lb": [float(low)] * act_dim,
                "action_ub": [float(high)] * act_dim,
                "planning_horizon": planner.horizon,
                "replan_freq": 1,
                "verbose": False,
                "optimizer_cfg": {
                    "_target_": "mbrl.planning.CEMOptimizer",
                    "num_iterations": planner.iterations,
                    "elite_ratio": planner.elites / planner.population,
                    "population_size": planner.population,
                    "alpha": planner.alpha,
                    "lower_bound": "???",
                    "upper_bound": "???",
                    "return_mean_elites": True,
                    "device": device,
                    "clipped_normal": False,
                },
            }
        )
        agent = mbrl.planning.create_trajectory_optim_agent_for_model(
            model_env, agent_cfg, num_particles=planner.particles
        )
        elite_num = int(agent.optimizer.optimizer.elite_num)
        if elite_num != planner.elites:
            raise RuntimeError(f"mbrl-lib CEM keeps {elite_num} elites, expected {planner.elites}")
        agents.append(agent)
    return agents


def train_ensembles(
    obs: torch.Tensor,
    action: torch.Tensor,
    next_obs: torch.Tensor,
    members: int,
    hidden: tuple[int, ...],
    epochs: int,
    batch_size: int,
    lr: float = 1e-3,
    seed: int = 0,
) -> tuple[float, list[float]]:
    """Train one mbrl-lib ``GaussianMLP`` ensemble per agent with its ``ModelTrainer``.

    Same workload as our ``train_ensemble``: per agent ``B`` members, ``epochs`` passes over
    the agent's ``N`` transitions in minibatches of ``batch_size``, a bootstrap resample per
    member (mbrl-lib's ``BootstrapIterator`` with replacement, its PETS default), Gaussian NLL
    with learned log-variance bounds and their 0.01 penalty, Adam ``lr`` without weight decay,
    targets ``next_obs - obs``, inputs normalised (float64 normaliser, fitted on the data).

    Args:
        obs, next_obs: ``[N, I, obs]``; action: ``[N, I, act]``.
        members, hidden, epochs, batch_size, lr: ensemble size, hidden widths, training sizes.
        seed: seeds the iterators and the weight initialisation.

    Returns:
        Seconds for all ``I`` agents (model construction excluded; normaliser fit, iterator
        construction and training included) and each agent's last-epoch mean training loss.
    """
    mbrl = import_mbrl()
    from mbrl.util.replay_buffer import BootstrapIterator

    rows, n_agents, obs_dim = obs.shape
    act_dim = action.shape[-1]
    total, losses = 0.0, []
    for i in range(n_agents):
        torch.manual_seed(seed + i)
        dynamics = _gaussian_dynamics(
            mbrl,
            obs_dim + act_dim,
            obs_dim,
            members,
            tuple(hidden),
            None,
            learn_logvar_bounds=True,
        )
        trainer = mbrl.models.ModelTrainer(dynamics, optim_lr=lr, weight_decay=0.0)
        batch = mbrl.types.TransitionBatch(
            obs[:, i].numpy(),
            action[:, i].numpy(),
            next_obs[:, i].numpy(),
            np.zeros(rows, np.float32),
            np.zeros(rows, bool),
            np.zeros(rows, bool),
        )
        start = time.perf_counter()
        dynamics.update_normalizer(batch)
        iterator = BootstrapIterator(
            batch,
            batch_size,
            members,
            shuffle_each_epoch=True,
            permute_indices=False,
            rng=np.random.default_rng(seed + i),
        )
        train_losses, _ = trainer.train(iterator, num_epochs=epochs, evaluate=False, silent=True)
        total += time.perf_counter() - start
        losses.append(train_losses[-1])
    return total, losses
