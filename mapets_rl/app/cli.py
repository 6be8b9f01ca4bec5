"""``mapets-rl``: train, resume, evaluate and compare recipes from the command line.

    mapets-rl train RECIPE --env SCENARIO [--seed N] [--config FILE] [--run-dir DIR] [key=value ...]
    mapets-rl train --config NAME [--seed N] [key=value ...]   (a published configuration)
    mapets-rl configs                      (the published configurations, one line each)
    mapets-rl train RECIPE [key=value ...] --help
                                           (RECIPE's scenarios, and its config fields with type,
                                            value, unit and description; see mapets_rl.app.help)
    mapets-rl resume RUN_DIR [key=value ...]
    mapets-rl evaluate RUN_DIR [--episodes N] [--video]
    mapets-rl evaluate RUN_DIR --roads B [--references NAME ...]   (the evaluation protocol)
    mapets-rl sweep RECIPE --env SCENARIO --out DIR [--seeds N ...] [--grid KEY=v1,v2 ...]
                    [--backend local|ray|submitit] [key=value ...]  (see mapets_rl.app.sweep)
    mapets-rl compare RUN_DIR... --out DIR [--metrics a,b,...] [--source eval|train]
                      [--group-by FIELD[,FIELD...]] [--x frames|METRIC] [--allow-mixed-env]
                      [--legacy-as eval|train]

Recipes are found by name among the entry points of the group ``mapets_rl.recipes`` of the
installed packages (see :mod:`mapets_rl.app.plugins`). The library, the recipes, sweeps and
``compare`` are imported inside the commands that need them, so ``--help`` imports no torch.

Errors in what the user typed (unknown recipe, scenario or config key, a bad value, an unusable
run directory or checkpoint) print one line ``mapets-rl: error: ...`` and exit with code 2;
warnings of the library (e.g. a checkpoint skipped because it does not verify) print one line
``mapets-rl: warning: ...``.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import sys
import warnings
from collections.abc import Mapping, Sequence
from typing import Any, NoReturn

from mapets_rl import quiet_dependencies
from mapets_rl._compile_cache import prepare_compile_cache
from mapets_rl.app.prog import PROG
from mapets_rl.threads import prepare_process


class _Parser(argparse.ArgumentParser):
    """ArgumentParser whose errors are a single line and exit code 2."""

    def error(self, message: str) -> NoReturn:
        self.exit(2, f"{PROG}: error: {message}\n")


def _fail(message: str) -> NoReturn:
    lines = [line.strip() for line in str(message).splitlines() if line.strip()]
    sys.stderr.write(f"{PROG}: error: {lines[0] if lines else 'failed'}\n")
    raise SystemExit(2)


class _StderrLineHandler(logging.Handler):
    """Writes ``mapets-rl: <level>: <message>`` lines to the current ``sys.stderr``."""

    def emit(self, record: logging.LogRecord) -> None:
        message = " ".join(self.format(record).split())
        sys.stderr.write(f"{PROG}: {record.levelname.lower()}: {message}\n")


DEPRECATED_KEY = "config key "
"""How the library's warning about a deprecated config key begins (``mapets_rl.config``)."""


def _show_library_warnings() -> None:
    """Route the ``mapets_rl`` loggers' warnings to stderr as single lines (once), and the
    library's DeprecationWarning about a renamed config key too (Python hides
    DeprecationWarnings by default)."""
    log = logging.getLogger("mapets_rl")
    if not any(isinstance(h, _StderrLineHandler) for h in log.handlers):
        handler = _StderrLineHandler(logging.WARNING)
        log.addHandler(handler)
    if getattr(warnings.showwarning, "one_line", False):
        return
    shown = warnings.showwarning

    def show(message, category, filename, lineno, file=None, line=None) -> None:  # noqa: ANN001
        if issubclass(category, DeprecationWarning) and str(message).startswith(DEPRECATED_KEY):
            sys.stderr.write(f"{PROG}: warning: {message}\n")
        else:
            shown(message, category, filename, lineno, file, line)

    show.one_line = True  # type: ignore[attr-defined]
    warnings.showwarning = show
    warnings.filterwarnings("default", message=DEPRECATED_KEY, category=DeprecationWarning)


def _overrides(items: Sequence[str]) -> list[str]:
    """The ``key=value`` arguments, refused (exit 2, one line) when one is not of that form or
    two set the same key (which would otherwise leave the last one winning silently)."""
    seen: dict[str, str] = {}
    for item in items:
        key, sep, _ = item.partition("=")
        if not sep or not key.strip():
            _fail(f"expected key=value, got {item!r}")
        key = key.strip()
        if key in seen:
            _fail(f"{key} is set twice ({seen[key]!r} and {item!r}): give it once")
        seen[key] = item
    return list(items)


def _check_flag_conflicts(args: argparse.Namespace, overrides: Sequence[str]) -> None:
    """``--env``/``--seed``/``--run-dir`` against ``key=value`` overrides of the same field."""
    keys = {item.partition("=")[0].strip(): item for item in overrides}
    if "env" in keys:
        _fail(f"the scenario is chosen by --env ({args.env}), not by {keys['env']!r}")
    if args.seed is not None and "seed" in keys:
        _fail(f"--seed {args.seed} and {keys['seed']!r} both set the seed: give one")
    if args.run_dir == "":
        _fail("--run-dir must be a non-empty path, got ''")


def _check_action_kind(cls: type, env_name: str, env_config: Mapping[str, Any]) -> None:
    """Refuse (exit 2, one line) a recipe on a scenario whose actions it cannot take, before
    its config is read (a recipe's default ``env_config`` is written for the scenarios it
    supports); the scenario is built with ``env_config``, a published file's (which may choose
    the actions, e.g. highway-env's continuous ones)."""
    from mapets_rl.app.help import recipe_action_kinds, scenario_group

    kinds = recipe_action_kinds(cls)
    if {"continuous", "discrete"} <= set(kinds):
        return
    _, kind = scenario_group(env_name, dict(env_config))
    if kind not in kinds:
        _fail(
            f"{cls.name} needs {' or '.join(kinds)} actions; scenario {env_name!r} has {kind} "
            f"actions (`mapets-rl train {cls.name} --help` lists the scenarios it supports)"
        )


def _recipe_names() -> str:
    """The installed recipes for help texts (names only: nothing is imported)."""
    from mapets_rl.app.plugins import available_recipes

    try:
        names = available_recipes()
    except ValueError as err:  # a name declared twice: `train` reports it
        return f"(the installed recipes clash: {err})"
    return f"one of {', '.join(names)}" if names else "(none installed: pip install -e .)"


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(
        prog=PROG,
        description="Multi-agent RL for connected autonomous vehicles: "
        "train, resume, evaluate and compare recipes.",
    )
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    train = sub.add_parser(
        "train",
        help="train a recipe on a scenario",
        description="Train RECIPE on SCENARIO. The run directory receives config.yaml (the "
        "resolved config), results.json (metrics of every evaluation, and of training episodes for "
        "recipes that record them; their measured durations go to timings.json), checkpoints/ "
        "and logs/. A --run-dir that holds files but is not a run directory is refused.",
        epilog="Any config field can be set as key=value (value parsed as YAML), e.g. "
        "total_frames=30000 lr=3e-4 env_config.n_cavs=8 logger=tensorboard video=true. "
        "`mapets-rl train RECIPE --help` lists the scenarios RECIPE supports and its fields "
        "(nested sections too) with defaults, units and descriptions. "
        "Recipes are the installed packages' entry points of the group mapets_rl.recipes.",
    )
    train.add_argument(
        "recipe",
        nargs="?",
        default=None,
        metavar="RECIPE",
        help=f"algorithm: {_recipe_names()} (default: the one --config names)",
    )
    train.add_argument(
        "--env",
        default=None,
        metavar="SCENARIO",
        help="scenario name, e.g. figure-eight, figure-eight-multilane, freeway, or one an "
        "installed package declares (entry-point group mapets_rl.scenarios); "
        "`mapets-rl train RECIPE --help` lists those RECIPE supports (default: the "
        "--config's env)",
    )
    train.add_argument(
        "--seed",
        type=int,
        default=None,
        metavar="N",
        help="seed of all RNGs and environments (default: the config's, 0)",
    )
    train.add_argument(
        "--config",
        default=None,
        metavar="NAME|FILE",
        help="a published configuration (`mapets-rl configs` lists them, e.g. "
        "freeway-merge/maddpg-individual) or a YAML file of config fields, applied before "
        "key=value overrides",
    )
    train.add_argument(
        "--run-dir",
        default=None,
        metavar="DIR",
        help="run directory (default: RUNS_ROOT/<recipe>_<env>_seed<N>_<time>)",
    )
    train.add_argument(
        "--runs-root",
        default="runs",
        metavar="RUNS_ROOT",
        help="parent of the default run directory (default: runs)",
    )
    train.add_argument(
        "overrides",
        nargs="*",
        metavar="key=value",
        help="config overrides, e.g. total_frames=30000 lr=3e-4",
    )

    resume = sub.add_parser(
        "resume",
        help="continue a run from its latest checkpoint",
        description="Continue RUN_DIR from its latest checkpoint with the same config and seed; "
        "the result is identical to an uninterrupted run.",
        epilog="Overrides such as total_frames=60000 extend the budget of a finished run. A "
        "resume changes only the budget (total_frames; MA-PETS: episodes), the intervals "
        "(eval_interval, checkpoint_interval) and keep_last, device, logger, progress, video; "
        "any other change is refused (start a new run). A run sent SIGTERM stops with a "
        "checkpoint (exit 143) and resumes from it.",
    )
    resume.add_argument("run_dir", metavar="RUN_DIR", help="a directory written by `train`")
    resume.add_argument(
        "overrides",
        nargs="*",
        metavar="key=value",
        help="config overrides applied to the saved config (the budget and the intervals)",
    )

    evaluate = sub.add_parser(
        "evaluate",
        help="evaluate a run's latest checkpoint",
        description="Run deterministic evaluation episodes with RUN_DIR's latest checkpoint; "
        "prints the mean metrics as JSON and writes RUN_DIR/evaluation.json.",
    )
    evaluate.add_argument("run_dir", metavar="RUN_DIR", help="a directory written by `train`")
    evaluate.add_argument(
        "--episodes",
        type=int,
        default=None,
        metavar="N",
        help="evaluation episodes (default: the run's eval_episodes)",
    )
    evaluate.add_argument(
        "--video",
        action="store_true",
        help="save the first episode as RUN_DIR/videos/eval_<frames>.gif",
    )
    evaluate.add_argument(
        "--roads",
        type=int,
        default=None,
        metavar="B",
        help="the evaluation protocol: one greedy episode on each of B evaluation roads of a "
        "batched env (B episodes on a scenario without one), beside the --references on the "
        "same roads; writes RUN_DIR/evaluation_protocol.json",
    )
    evaluate.add_argument(
        "--references",
        nargs="+",
        default=None,
        metavar="NAME",
        help="reference policies scored on the same roads (with --roads; default: every one "
        "registered for the scenario, e.g. keep-lane cooperative-merge on freeway-merge)",
    )

    sub.add_parser(
        "configs",
        help="list the published configurations",
        description="The configurations behind the published tables, shipped with the "
        "package: train one with `mapets-rl train --config NAME`, sweep its seeds with "
        "`mapets-rl sweep --config NAME --seeds 0 1 2 3 4 --out DIR`.",
    )

    compare = sub.add_parser(
        "compare",
        help="learning curves and a final-metrics table over runs",
        description="Group RUN_DIRs by recipe (and --group-by fields), plot mean learning "
        "curves with a bootstrap 95% band over the runs of each group, clipped to each "
        "metric's range (learning_curves.png), and write markdown tables of final metrics "
        "(mean and interquartile mean with bootstrap intervals, final_metrics.md), "
        "summary.json and curves.json into --out (with --marl-eval also marl_eval.json). "
        "Runs on different scenarios (env or env_config) are refused unless "
        "--allow-mixed-env; a run named twice, or an --out inside a run, is refused. The runs "
        "of a group that end at different x are compared at the last x all of them reached "
        "(the table's header says so).",
    )
    compare.add_argument("run_dirs", nargs="+", metavar="RUN_DIR", help="run directories")
    compare.add_argument("--out", required=True, metavar="DIR", help="output directory")
    compare.add_argument(
        "--metrics",
        default=None,
        metavar="a,b,...",
        help="comma-separated metrics to show, or all (every metric common to the runs); "
        "default: the task metrics among them (agility, safety, velocity, comfort, "
        "collisions, length, reward, return), not timings, counters or losses",
    )
    compare.add_argument(
        "--source",
        choices=["eval", "train"],
        default="eval",
        help="eval (default): deterministic evaluations; a run without any "
        "(e.g. mapets) falls back to its training entries, with a note. "
        "train: training entries (e.g. mapets's episodes)",
    )
    compare.add_argument(
        "--group-by",
        default=None,
        metavar="FIELD[,FIELD...]",
        help="config fields (dotted for nested ones, e.g. comm.comm_range or "
        "env_config.observation) whose values split each recipe's runs into "
        "groups, e.g. one curve per communication range",
    )
    compare.add_argument(
        "--x",
        default="frames",
        metavar="NAME",
        help="x axis: frames (default) or a metric numbering the entries, "
        "e.g. episode (mapets's episodes differ in length)",
    )
    compare.add_argument(
        "--x-grid",
        type=float,
        default=None,
        metavar="STEP",
        help="put every run on the x values STEP, 2 STEP, ... (each run's last entry at or "
        "before each), so runs that log at different x share a curve, e.g. 200 for mapets "
        "episodes beside baselines evaluated every 200 frames",
    )
    compare.add_argument(
        "--allow-mixed-env",
        action="store_true",
        help="compare runs on different scenarios (env or env_config), each "
        "group labelled with its scenario, instead of refusing them",
    )
    compare.add_argument(
        "--legacy-as",
        choices=["eval", "train"],
        default="eval",
        help="what the entries of a results.json from before training and "
        "evaluation entries were kept apart are (old mapets runs: train)",
    )
    compare.add_argument(
        "--marl-eval",
        action="store_true",
        help="also write marl_eval.json, every run's entries in InstaDeep's marl-eval format",
    )
    compare.add_argument(
        "--optimality-gap",
        default=None,
        metavar="METRIC=GAMMA[,...]",
        help="gamma of the rliable report's optimality gap (mean over runs of max(gamma - "
        "value, 0)) per compared metric, e.g. return=10; default: the top of the metric's "
        "range where it has one (safety=1), else no gap",
    )
    _add_sweep_parser(sub)
    return parser


def _add_sweep_parser(sub: argparse._SubParsersAction) -> None:
    """Register ``mapets-rl sweep`` on the CLI's subparsers (its work is
    :func:`mapets_rl.app.sweep.cmd_sweep`)."""
    parser = sub.add_parser(
        "sweep",
        help="run a recipe over config grids x seeds, on this machine or on Ray",
        description="Run RECIPE on SCENARIO for every combination of the --grid values and "
        "--seeds, each trial a normal run directory under OUT/trials/, then compare them "
        "grouped by the swept fields (OUT/summary: learning_curves.png with 95% bands, "
        "final_metrics.md). OUT/sweep.json lists the trials and their state. Running the same "
        "command again skips finished trials and resumes unfinished ones; failed trials are "
        "listed (their traceback in error.txt) and make the command exit with 1.",
        epilog="Example: mapets-rl sweep mapets --env figure-eight --seeds 0 1 2 "
        "--grid comm.comm_range=0,50,100 --grid comm.p_fail=0,0.25 preset=cpu episodes=5 "
        "--out runs/d_sweep",
    )
    parser.add_argument(
        "recipe",
        nargs="?",
        default=None,
        metavar="RECIPE",
        help="an installed recipe, e.g. mapets (default: the one --config names)",
    )
    parser.add_argument(
        "--env", default=None, metavar="SCENARIO", help="scenario name (default: --config's env)"
    )
    parser.add_argument(
        "--seeds",
        nargs="+",
        default=["0"],
        metavar="N",
        help="seeds of the trials (default: 0)",
    )
    parser.add_argument(
        "--grid",
        action="append",
        default=[],
        metavar="KEY=v1,v2,...",
        help="a config field and its values (dotted for nested fields, e.g. "
        "comm.comm_range=0,50,100 or env_config.n_cavs=4,8; a YAML list for list values: "
        "'model.hidden=[[32,32],[64,64]]'); repeat for a cartesian product",
    )
    parser.add_argument("--out", required=True, metavar="DIR", help="the sweep directory")
    parser.add_argument(
        "--config",
        default=None,
        metavar="NAME|FILE",
        help="a published configuration (`mapets-rl configs`) or a YAML file of config fields",
    )
    parser.add_argument(
        "--backend",
        default="local",
        metavar="local|ray|submitit",
        help="local (default): a process pool on this machine; ray: Ray tasks on a local Ray "
        "instance, or on the cluster of --address / RAY_ADDRESS; submitit: Slurm jobs "
        "(see --executor-param)",
    )
    parser.add_argument(
        "--executor-param",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="a parameter of the submitit backend's executor, e.g. timeout_min=120, "
        "slurm_partition=gpu, cluster=local (jobs on this machine); repeat for more",
    )
    parser.add_argument(
        "--address", default=None, metavar="HOST:PORT", help="Ray cluster to join (ray backend)"
    )
    parser.add_argument(
        "--cpus-per-trial",
        type=float,
        default=1.0,
        metavar="N",
        help="CPUs per trial, also its torch threads (default 1; the local backend runs "
        "cpu_count // N trials at once)",
    )
    parser.add_argument(
        "--gpus-per-trial",
        type=float,
        default=0.0,
        metavar="N",
        help="GPUs per trial (ray backend; pass device=cuda too)",
    )
    parser.add_argument("--metrics", default=None, metavar="a,b,...", help="metrics of the summary")
    parser.add_argument(
        "--source",
        choices=["eval", "train"],
        default="eval",
        help="what the summary compares (see compare --source)",
    )
    parser.add_argument(
        "--x",
        default="auto",
        metavar="NAME",
        help="x axis of the summary: frames, a metric numbering the entries, or auto "
        "(default: episode when every entry has one, e.g. mapets, else frames)",
    )
    parser.add_argument(
        "overrides", nargs="*", metavar="key=value", help="config overrides of every trial"
    )


def _recipe_class(name: str) -> type:
    from mapets_rl.app.plugins import load_recipe

    try:
        return load_recipe(name)
    except ValueError as err:
        _fail(str(err))


def _check_env(name: str) -> None:
    from mapets_rl.envs.registry import available_envs

    known = available_envs()
    if name not in known:
        _fail(f"unknown scenario {name!r} (choose from: {', '.join(known)})")


def _published(name_or_path: str) -> Any:
    """The published configuration or config file ``--config`` names (exit 2, one line, when
    it is neither)."""
    from mapets_rl.config import ConfigError
    from mapets_rl.experiment.published import load_published

    try:
        return load_published(name_or_path)
    except ConfigError as err:
        _fail(str(err))


def _cmd_train(args: argparse.Namespace) -> int:
    if args.recipe is not None and "=" in args.recipe:  # `train --config NAME key=value`
        args.overrides = [args.recipe, *args.overrides]
        args.recipe = None
    published = _published(args.config) if args.config else None
    from mapets_rl.config import ConfigError
    from mapets_rl.experiment.published import recipe_and_env

    try:
        recipe, env = recipe_and_env("train", args.recipe, args.env, published)
    except ConfigError as err:
        _fail(str(err))
    cls = _recipe_class(recipe)  # an unknown name fails before torch is imported
    _check_env(env)
    user_overrides = _overrides(args.overrides)
    args.env = env
    _check_flag_conflicts(args, user_overrides)
    _check_action_kind(cls, env, published.fields.get("env_config", {}) if published else {})
    from mapets_rl.experiment.files import check_writable_dir
    from mapets_rl.experiment.runner import default_run_dir

    overrides = [f"env={env}"]
    if args.seed is not None:
        overrides.append(f"seed={args.seed}")
    try:
        if published is not None:  # validated once, with the overrides applied to its fields
            source = f"config {published.name!r}"
            if published.path.as_posix() == published.name:
                source = f"config file {published.name!r}"
            config = cls.Config.from_fields(published.fields, overrides + user_overrides, source)
        else:
            config = cls.Config().with_overrides(overrides + user_overrides)
    except ConfigError as err:
        _fail(str(err))
    if args.run_dir is not None:
        run_dir = args.run_dir
    else:
        try:
            check_writable_dir(args.runs_root, "--runs-root")
        except ValueError as err:
            _fail(str(err))
        run_dir = default_run_dir(cls.name, config.env, config.seed, args.runs_root)
    try:
        exp = cls(config, run_dir)
    except ValueError as err:
        _fail(str(err))
    except OSError as err:
        _fail_setup(err)
    _train(exp)
    _print_run_summary(exp)
    return 0


def _print_run_summary(exp: Any) -> None:
    """The JSON line ``train`` and ``resume`` end with: run directory, frames, the latest
    metrics and their units."""
    summary = {
        "run_dir": str(exp.run_dir),
        "frames": exp.frames,
        "metrics": exp.latest_metrics,
        "units": _metric_units(["frames", *exp.latest_metrics]),
    }
    print(json.dumps(summary))


def _metric_units(names: Sequence[str]) -> dict[str, str]:
    """Name -> unit of the metrics among ``names`` that have one (printed with them)."""
    from mapets_rl.experiment.results import metric_units as units

    return units(names)


def _train(exp: Any) -> None:
    """``exp.train()``; a file that cannot be written (disk full, file size limit) is one line
    naming it (exit 2), and so is a collected batch with NaN or infinite observations or
    rewards (the checkpoints written before either stay valid). A run stopped by SIGTERM (after
    its checkpoint) says so in one line and exits with 128 + the signal's number, as a process
    killed by it would."""
    from mapets_rl.experiment.files import WriteFailed
    from mapets_rl.experiment.runner import NonFiniteData, RunStopped
    from mapets_rl.ray_runtime import RayUnreachable

    try:
        exp.train()
    except WriteFailed as err:
        from mapets_rl.experiment.checkpoint import list_checkpoints

        if list_checkpoints(exp.run_dir):
            _fail(f"{err}; the run stopped, its earlier checkpoints are kept (resume it later)")
        _fail(f"{err}; the run stopped before its first checkpoint (start it again)")
    except (RayUnreachable, NonFiniteData) as err:
        _fail(str(err))
    except RunStopped as err:
        sys.stderr.write(f"{PROG}: {err}\n")
        raise SystemExit(128 + err.signum) from None


def _load_run(run_dir: str, overrides: Sequence[str] = ()):
    from mapets_rl.experiment.runner import run_recipe_name

    try:
        cls = _recipe_class(run_recipe_name(run_dir))
        return cls.from_run_dir(run_dir, overrides=list(overrides))
    except ValueError as err:
        _fail(str(err))
    except OSError as err:
        _fail_setup(err)


def _fail_setup(err: OSError) -> NoReturn:
    """One line for an OSError while a run is set up, e.g. the shared memory of a replay
    buffer under a file-size limit (``ulimit -f``) or on a full ``/dev/shm``."""
    import errno

    reason = err.strerror or str(err) or type(err).__name__
    if err.errno == errno.EFBIG:
        reason += " (the file size limit, ulimit -f, was reached)"
    _fail(f"the run cannot be set up: {reason}")


def _cmd_resume(args: argparse.Namespace) -> int:
    exp = _load_run(args.run_dir, _overrides(args.overrides))
    _train(exp)
    _print_run_summary(exp)
    return 0


def _cmd_configs(args: argparse.Namespace) -> int:
    from mapets_rl.config import ConfigError
    from mapets_rl.experiment.published import available_configs

    try:
        configs = available_configs()
    except ConfigError as err:
        _fail(str(err))
    width = max(len(c.name) for c in configs)
    for config in configs:
        print(f"{config.name:<{width}}  {config.recipe:<10}  {config.summary}")
    return 0


def _cmd_evaluate_protocol(args: argparse.Namespace) -> int:
    """``evaluate --roads B``: the evaluation protocol (mapets_rl.experiment.protocol)."""
    from mapets_rl.experiment.protocol import check_roads

    try:
        check_roads(args.roads)
    except ValueError as err:
        _fail(f"--{err}")
    if args.episodes is not None or args.video:
        _fail("--roads scores the protocol's roads: give it without --episodes and --video")
    exp = _load_run(args.run_dir)
    from mapets_rl.experiment.protocol import evaluate_protocol

    try:
        result = evaluate_protocol(exp, args.roads, args.references or ())
    except ValueError as err:
        _fail(f"--{err}" if str(err).startswith("references") else str(err))
    policy = result["policy"]
    print(
        json.dumps(
            {
                "run_dir": str(exp.run_dir),
                "frames": result["frames"],
                "roads": result["roads"],
                "eval_seed": result["eval_seed"],
                "system_reward": policy["system_reward_mean"],
                "gain_percent": result["gain_percent"],
                "metrics": policy["metrics"],
                "references": {
                    name: {"system_reward": ref["system_reward_mean"], "metrics": ref["metrics"]}
                    for name, ref in result["references"].items()
                },
            }
        )
    )
    return 0


def _cmd_evaluate(args: argparse.Namespace) -> int:
    if args.roads is not None:
        return _cmd_evaluate_protocol(args)
    if args.references is not None:
        _fail("--references needs --roads B (the protocol's evaluation roads)")
    if args.episodes is not None and args.episodes < 1:
        _fail(f"--episodes must be >= 1, got {args.episodes}")
    exp = _load_run(args.run_dir)
    episodes = args.episodes or exp.config.eval_episodes
    try:
        metrics = exp.evaluate(episodes=episodes, video=args.video)
    except ValueError as err:
        _fail(str(err))
    try:
        exp.write_evaluation(metrics, episodes)
    except ValueError as err:  # WriteFailed: the disk is full
        _fail(str(err))
    print(
        json.dumps(
            {
                "run_dir": str(exp.run_dir),
                "frames": exp.frames,
                "episodes": episodes,
                "metrics": metrics,
                "units": _metric_units(["frames", *metrics]),
            }
        )
    )
    return 0


def _cmd_compare(args: argparse.Namespace) -> int:
    from mapets_rl.app.comparison import compare

    metrics: list[str] | str | None = None
    if args.metrics is not None:
        metrics = [m.strip() for m in args.metrics.split(",") if m.strip()]
        if not metrics:
            _fail(f"--metrics must name at least one metric (a,b,...), got {args.metrics!r}")
        if metrics == ["all"]:
            metrics = "all"
    group_by = None
    if args.group_by is not None:
        group_by = [f.strip() for f in args.group_by.split(",") if f.strip()]
        if not group_by:
            _fail(f"--group-by must name at least one config field, got {args.group_by!r}")
    thresholds: dict[str, float] = {}
    for item in filter(None, (i.strip() for i in (args.optimality_gap or "").split(","))):
        name, _, value = item.partition("=")
        try:
            thresholds[name.strip()] = float(value)
        except ValueError:
            _fail(f"--optimality-gap must be METRIC=GAMMA[,...] (GAMMA a number), got {item!r}")
    try:
        out = compare(
            args.run_dirs,
            args.out,
            metrics,
            source=args.source,
            group_by=group_by,
            x=args.x,
            x_grid=args.x_grid,
            allow_mixed_env=args.allow_mixed_env,
            legacy_as=args.legacy_as,
            marl_eval=args.marl_eval,
            optimality_thresholds=thresholds,
        )
    except ValueError as err:
        _fail(str(err))
    print(out["table"].read_text(), end="")
    if "protocol" in out:
        print(out["protocol"].read_text(), end="")
    print(json.dumps({k: str(v) for k, v in out.items()}))
    return 0


def _cmd_sweep(args: argparse.Namespace) -> int:
    from mapets_rl.app.sweep import cmd_sweep

    return cmd_sweep(args)


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``mapets-rl`` console script."""
    prepare_process()  # the OpenMP wait policy must be set before anything imports torch
    try:  # so must torch.compile's cache: importing torch creates it
        prepare_compile_cache()
    except ValueError as err:
        _fail(str(err))
    quiet_dependencies()
    argv = list(sys.argv[1:] if argv is None else argv)
    if (
        len(argv) >= 3
        and argv[0] == "train"
        and not argv[1].startswith("-")
        and {"-h", "--help"} & set(argv[2:])
    ):
        from mapets_rl.app.help import recipe_help

        try:
            sys.stdout.write(recipe_help(argv[1], argv[2:]))
        except ValueError as err:  # an unknown recipe, a bad key=value
            _fail(str(err))
        return 0
    parser = build_parser()
    # key=value overrides may follow options (argparse does not intermix positionals)
    args, extra = parser.parse_known_args(argv)
    stray = [
        x
        for x in extra
        if x.startswith("-") or "=" not in x or args.command not in ("train", "resume", "sweep")
    ]
    if stray:
        parser.error(f"unrecognized arguments: {' '.join(stray)}")
    if extra:
        args.overrides = [*args.overrides, *extra]
    _show_library_warnings()
    commands = {
        "train": _cmd_train,
        "resume": _cmd_resume,
        "evaluate": _cmd_evaluate,
        "configs": _cmd_configs,
        "compare": _cmd_compare,
        "sweep": _cmd_sweep,
    }
    return commands[args.command](args)


if __name__ == "__main__":
    # `python -m mapets_rl.app.cli` puts the working directory first on sys.path: run
    # inside a run directory from elsewhere, a module or *.dist-info entry point planted there
    # would be imported as a recipe or scenario (the mapets-rl command has no such entry)
    if sys.path and sys.path[0] in ("", os.getcwd()):
        del sys.path[0]
    sys.exit(main())
