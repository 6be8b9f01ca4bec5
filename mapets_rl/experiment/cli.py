"""``mapets-rl``: train, resume, evaluate and compare recipes from the command line.

    mapets-rl train RECIPE --env SCENARIO [--seed N] [--config FILE] [--run-dir DIR] [key=value ...]
    mapets-rl train RECIPE --help          (RECIPE's config fields, their types and defaults)
    mapets-rl resume RUN_DIR [key=value ...]
    mapets-rl evaluate RUN_DIR [--episodes N] [--video]
    mapets-rl sweep RECIPE --env SCENARIO --out DIR [--seeds N ...] [--grid KEY=v1,v2 ...]
                    [--backend local|ray] [key=value ...]     (see mapets_rl.experiment.sweep)
    mapets-rl compare RUN_DIR... --out DIR [--metrics a,b,...] [--source eval|train]
                      [--group-by FIELD[,FIELD...]] [--x frames|METRIC] [--allow-mixed-env]
                      [--legacy-as eval|train]

Recipes are found by name among the entry points of the group ``mapets_rl.recipes`` of the
installed packages (see :mod:`mapets_rl.experiment.plugins`); nothing is imported until a
command needs it, so ``--help`` stays fast.

Errors in what the user typed (unknown recipe, scenario or config key, a bad value, an unusable
run directory or checkpoint) print one line ``mapets-rl: error: ...`` and exit with code 2;
warnings of the library (e.g. a checkpoint skipped because it does not verify) print one line
``mapets-rl: warning: ...``.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
from collections.abc import Sequence
from typing import NoReturn

PROG = "mapets-rl"


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


def _show_library_warnings() -> None:
    """Route the ``mapets_rl`` loggers' warnings to stderr as single lines (once)."""
    log = logging.getLogger("mapets_rl")
    if not any(isinstance(h, _StderrLineHandler) for h in log.handlers):
        handler = _StderrLineHandler(logging.WARNING)
        log.addHandler(handler)


def _overrides(items: Sequence[str]) -> list[str]:
    for item in items:
        if "=" not in item:
            _fail(f"expected key=value, got {item!r}")
    return list(items)


def _recipe_names() -> str:
    """The installed recipes for help texts (names only: nothing is imported)."""
    from mapets_rl.experiment.plugins import available_recipes

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
        "recipes that record them), checkpoints/ and logs/.",
        epilog="Any config field can be set as key=value (value parsed as YAML), e.g. "
        "total_frames=30000 lr=3e-4 env_config.n_cavs=8 logger=tensorboard video=true. "
        "`mapets-rl train RECIPE --help` lists RECIPE's fields with their defaults. "
        "Recipes are the installed packages' entry points of the group mapets_rl.recipes.",
    )
    train.add_argument("recipe", metavar="RECIPE", help=f"algorithm: {_recipe_names()}")
    train.add_argument(
        "--env",
        required=True,
        metavar="SCENARIO",
        help="scenario name, e.g. figure-eight, figure-eight-multilane, freeway",
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
        metavar="FILE",
        help="YAML file of config fields, applied before key=value overrides",
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
        epilog="Overrides such as total_frames=60000 extend the budget of a finished run.",
    )
    resume.add_argument("run_dir", metavar="RUN_DIR", help="a directory written by `train`")
    resume.add_argument(
        "overrides",
        nargs="*",
        metavar="key=value",
        help="config overrides applied to the saved config",
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

    compare = sub.add_parser(
        "compare",
        help="learning curves and a final-metrics table over runs",
        description="Group RUN_DIRs by recipe (and --group-by fields), plot mean learning "
        "curves with a 95%% Student-t confidence band over the runs of each group "
        "(learning_curves.png) and write a markdown table of final metrics (final_metrics.md), "
        "summary.json and curves.json into --out. Runs on different scenarios (env or "
        "env_config) are refused unless --allow-mixed-env.",
    )
    compare.add_argument("run_dirs", nargs="+", metavar="RUN_DIR", help="run directories")
    compare.add_argument("--out", required=True, metavar="DIR", help="output directory")
    compare.add_argument(
        "--metrics",
        default=None,
        metavar="a,b,...",
        help="comma-separated metrics to show (default: all common ones)",
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
    from mapets_rl.experiment.sweep import add_sweep_parser

    add_sweep_parser(sub)
    return parser


def _recipe_class(name: str) -> type:
    from mapets_rl.experiment.plugins import load_recipe

    try:
        return load_recipe(name)
    except ValueError as err:
        _fail(str(err))


def _check_env(name: str) -> None:
    from mapets_rl.experiment.runner import available_envs

    known = available_envs()
    if name not in known:
        _fail(f"unknown scenario {name!r} (choose from: {', '.join(known)})")


def _cmd_train(args: argparse.Namespace) -> int:
    cls = _recipe_class(args.recipe)  # an unknown name fails before torch is imported
    _check_env(args.env)
    from mapets_rl.experiment.config import ConfigError
    from mapets_rl.experiment.files import check_writable_dir
    from mapets_rl.experiment.runner import default_run_dir

    overrides = [f"env={args.env}"]
    if args.seed is not None:
        overrides.append(f"seed={args.seed}")
    try:
        config = cls.Config.from_yaml(args.config) if args.config else cls.Config()
        config = config.with_overrides(overrides + _overrides(args.overrides))
    except ConfigError as err:
        _fail(str(err))
    if args.run_dir:
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
    exp.train()
    print(
        json.dumps(
            {"run_dir": str(exp.run_dir), "frames": exp.frames, "metrics": exp.latest_metrics}
        )
    )
    return 0


def _load_run(run_dir: str, overrides: Sequence[str] = ()):
    from mapets_rl.experiment.runner import run_recipe_name

    try:
        cls = _recipe_class(run_recipe_name(run_dir))
        return cls.from_run_dir(run_dir, overrides=list(overrides))
    except ValueError as err:
        _fail(str(err))


def _cmd_resume(args: argparse.Namespace) -> int:
    exp = _load_run(args.run_dir, _overrides(args.overrides))
    exp.train()
    print(
        json.dumps(
            {"run_dir": str(exp.run_dir), "frames": exp.frames, "metrics": exp.latest_metrics}
        )
    )
    return 0


def _cmd_evaluate(args: argparse.Namespace) -> int:
    if args.episodes is not None and args.episodes < 1:
        _fail(f"--episodes must be >= 1, got {args.episodes}")
    exp = _load_run(args.run_dir)
    episodes = args.episodes or exp.config.eval_episodes
    try:
        metrics = exp.evaluate(episodes=episodes, video=args.video)
    except ValueError as err:
        _fail(str(err))
    exp.write_evaluation(metrics, episodes)
    print(
        json.dumps(
            {
                "run_dir": str(exp.run_dir),
                "frames": exp.frames,
                "episodes": episodes,
                "metrics": metrics,
            }
        )
    )
    return 0


def _cmd_compare(args: argparse.Namespace) -> int:
    from mapets_rl.experiment.comparison import compare

    metrics = None
    if args.metrics is not None:
        metrics = [m.strip() for m in args.metrics.split(",") if m.strip()]
        if not metrics:
            _fail(f"--metrics must name at least one metric (a,b,...), got {args.metrics!r}")
    group_by = None
    if args.group_by is not None:
        group_by = [f.strip() for f in args.group_by.split(",") if f.strip()]
        if not group_by:
            _fail(f"--group-by must name at least one config field, got {args.group_by!r}")
    try:
        out = compare(
            args.run_dirs,
            args.out,
            metrics,
            source=args.source,
            group_by=group_by,
            x=args.x,
            allow_mixed_env=args.allow_mixed_env,
            legacy_as=args.legacy_as,
        )
    except ValueError as err:
        _fail(str(err))
    print(out["table"].read_text(), end="")
    print(json.dumps({k: str(v) for k, v in out.items()}))
    return 0


def _cmd_sweep(args: argparse.Namespace) -> int:
    from mapets_rl.experiment.sweep import cmd_sweep

    return cmd_sweep(args)


def _recipe_help(name: str) -> str:
    """Help of ``mapets-rl train RECIPE --help``: RECIPE's config documentation and every
    field with its type and default (imports the recipe)."""
    import dataclasses
    import inspect
    import typing

    config_cls = _recipe_class(name).Config
    hints = typing.get_type_hints(config_cls)
    lines = [
        f"usage: {PROG} train {name} --env SCENARIO [--seed N] [--config FILE] "
        "[--run-dir DIR] [key=value ...]",
        "",
        inspect.getdoc(config_cls) or "",
        "",
        f"fields of {config_cls.__name__} (set as key=value; values parsed as YAML):",
    ]
    for f in dataclasses.fields(config_cls):
        if f.default is not dataclasses.MISSING:
            default = repr(f.default)
        elif f.default_factory is not dataclasses.MISSING:
            default = repr(f.default_factory())
        else:
            default = "(required)"
        tp = hints[f.name]
        type_name = tp.__name__ if isinstance(tp, type) else str(tp).replace("typing.", "")
        lines.append(f"  {f.name}: {type_name} = {default}")
    return "\n".join(lines) + "\n"


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``mapets-rl`` console script."""
    argv = list(sys.argv[1:] if argv is None else argv)
    if (
        len(argv) >= 3
        and argv[0] == "train"
        and not argv[1].startswith("-")
        and {"-h", "--help"} & set(argv[2:])
    ):
        sys.stdout.write(_recipe_help(argv[1]))
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
        "compare": _cmd_compare,
        "sweep": _cmd_sweep,
    }
    return commands[args.command](args)


if __name__ == "__main__":
    sys.exit(main())
