"""The run library every recipe stands on: configs, the run loop, checkpoints, results and
loggers. The application that drives it (the ``mapets-rl`` command, sweeps, ``compare``) is
:mod:`mapets_rl.app`, the floor above the recipes.

How a recipe plugs in
---------------------
1. A config dataclass subclassing :class:`ExperimentConfig` (seed, env, env_config, frame
   budget, evaluation / checkpoint intervals, logger, ... are inherited; a recipe without a
   frame budget subclasses :class:`RunConfig`, the fields every recipe shares). Add fields with type
   hints and defaults; validate in ``__post_init__`` after ``super().__post_init__()`` with
   ``check(cond, "field", "allowed range", value)`` (raises :class:`ConfigError`, a ValueError
   naming the field). YAML loading and ``key=value`` overrides then work for free.
2. A class subclassing :class:`Experiment` with class attributes ``name = "myalgo"`` and
   ``Config = MyConfig``, whose ``__init__(self, config, run_dir=None)`` calls
   ``super().__init__(config, run_dir)`` (which seeds, creates the run dir, writes
   ``config.yaml`` and builds ``self.env``), then builds, in this order:
   modules -> ``self.collector = self.make_collector(exploration_policy)`` -> replay buffer ->
   loss -> optimisers, and sets ``self.eval_policy`` (run under
   ``ExplorationType.DETERMINISTIC`` for evaluation).
3. Two methods:

   - ``train_step(batch) -> dict[str, float]``: consume one collected batch ([frames_per_batch]
     TensorDict with the ``"agents"`` layout): extend buffers, optimise, update targets;
     return scalar losses to log.
   - ``stateful_components() -> dict[str, obj]``: everything with ``state_dict`` /
     ``load_state_dict`` a checkpoint must hold (modules, losses with target params,
     optimisers, replay buffers, annealing modules).

   Everything else is inherited: ``train()`` (the loop: collect, ``train_step``, log, evaluate
   every ``eval_interval`` frames, checkpoint every ``checkpoint_interval`` frames),
   ``evaluate(episodes, video)``, ``state_dict()`` / ``load_state_dict()`` (components +
   counters + results entries + python/numpy/torch RNG states), ``from_run_dir(run_dir)``
   (resume / evaluate a saved run). Override ``episode_metrics`` / ``batch_metrics`` only to
   add metrics.
   A recipe whose unit of training is not a collected batch (MA-PETS: one episode of its
   Algorithm 1) writes its own ``train()`` as one loop on ``self.training_loop(...)`` (and
   overrides ``progress()``), the bookkeeping every loop shares: one call after each
   iteration, ``loop.end_iteration(metrics)``, logs the metrics, keeps them in
   ``results.json``, evaluates and checkpoints when due, calls the ``on_iteration_end``
   callback and advances the progress bar (see ``recipes/mapets.py``). Training entries
   (``add_train``) and deterministic evaluations (``add_evaluation``) are kept apart;
   ``compare`` never mixes the two.
4. Register it for the CLI with an entry point in the ``pyproject.toml`` of the package that
   holds it (then reinstall it, ``pip install -e .``)::

       [project.entry-points."mapets_rl.recipes"]
       myalgo = "mypackage.myalgo:MyAlgo"

   ``mapets-rl train myalgo``, ``resume`` and ``evaluate`` (which find the recipe by the name
   in ``run.json``) then load it; :func:`mapets_rl.app.plugins.load_recipe` does the same in
   Python.

A recipe whose data flow does not fit a collector (none of ours) can still satisfy the CLI's
protocol directly: ``Config``, ``__init__(config, run_dir)``, ``train()``,
``evaluate(episodes, video)``, ``state_dict()`` / ``load_state_dict()`` and ``from_run_dir``.

Run directory layout: ``config.yaml`` (resolved config), ``run.json`` (recipe, scenario, seed),
``results.json`` (frames and metrics of every deterministic evaluation under
``evaluations`` and of training entries, e.g. MA-PETS's episodes, under ``train``; read by
:func:`read_results` and :func:`mapets_rl.app.comparison.compare`),
``checkpoints/ckpt_<frames>.pt`` (atomic, the newest ``keep_last`` that verify, each with its
SHA-256 digest ``ckpt_<frames>.pt.sha256``; replay storages save only their filled rows),
``train_episodes.jsonl`` (the model-free loop's training episodes, one line each: the frame
count, the system return, the length and the scenario's episode metrics; read by
:func:`read_train_episodes`, averaged per window of episodes by :func:`window_means`),
``logs/`` (torchrl logger), ``videos/`` (GIFs when ``video=true``), and ``.lock`` (the pid of the
process writing the run while it runs). Every file is written atomically with the same
permissions.

Reliability: a config is validated when it is built (finite numbers, a device this machine has,
a registered scenario, installed logger packages), an env config when the env is built, and both
before anything is written to the run directory. Resuming verifies checkpoints and falls back to
the newest one that verifies; a resume that fails (bad override, no usable checkpoint) leaves
the run directory as it was. One process writes a run directory at a time: a run holds an OS
lock on it (``.lock``, released with the process, kill -9 included), and a second writer is
refused with one line naming the holder's pid.

Scenarios (``register_env`` here, or the entry-point group ``mapets_rl.scenarios``) and the
building blocks recipes share (:mod:`mapets_rl.modules`): see "Where new code goes" in
``docs/ARCHITECTURE.md``.
"""

from mapets_rl.config import ConfigError, ConfigSection, check
from mapets_rl.envs.registry import available_envs, build_env, register_env
from mapets_rl.experiment.checkpoint import (
    CheckpointError,
    atomic_torch_save,
    checkpoint_frames,
    checkpoint_problem,
    digest_path,
    file_sha256,
    latest_checkpoint,
    list_checkpoints,
    load_checkpoint,
    load_latest_checkpoint,
    remove_stale_files,
    rng_state,
    save_checkpoint,
    seed_everything,
    set_rng_state,
    verified_checkpoints,
    verify_checkpoint,
)
from mapets_rl.experiment.config import ExperimentConfig, RunConfig
from mapets_rl.experiment.episodes import TRAIN_EPISODES_FILE, read_train_episodes, window_means
from mapets_rl.experiment.files import atomic_savefig, atomic_write, atomic_write_text
from mapets_rl.experiment.reference import evaluate_scripted
from mapets_rl.experiment.results import (
    ResultsWriter,
    log_scalars,
    make_logger,
    mean_metrics,
    read_results,
)
from mapets_rl.experiment.runner import (
    Experiment,
    SystemRewardMetrics,
    default_run_dir,
    run_recipe_name,
)
from mapets_rl.experiment.training import (
    DiscreteExplorationConfig,
    ModelFreeConfig,
    OffPolicyConfig,
    OnPolicyConfig,
)

__all__ = [
    "CheckpointError",
    "ConfigError",
    "ConfigSection",
    "DiscreteExplorationConfig",
    "Experiment",
    "ExperimentConfig",
    "ModelFreeConfig",
    "OffPolicyConfig",
    "OnPolicyConfig",
    "ResultsWriter",
    "RunConfig",
    "SystemRewardMetrics",
    "TRAIN_EPISODES_FILE",
    "atomic_torch_save",
    "atomic_savefig",
    "atomic_write",
    "atomic_write_text",
    "available_envs",
    "build_env",
    "check",
    "checkpoint_frames",
    "checkpoint_problem",
    "default_run_dir",
    "digest_path",
    "evaluate_scripted",
    "file_sha256",
    "latest_checkpoint",
    "list_checkpoints",
    "load_checkpoint",
    "load_latest_checkpoint",
    "log_scalars",
    "make_logger",
    "mean_metrics",
    "read_results",
    "read_train_episodes",
    "register_env",
    "remove_stale_files",
    "rng_state",
    "run_recipe_name",
    "save_checkpoint",
    "seed_everything",
    "set_rng_state",
    "verified_checkpoints",
    "verify_checkpoint",
    "window_means",
]
