"""Compare runs: learning curves (mean and bootstrap 95% band over seeds), final-metrics
markdown tables (mean and interquartile mean, each with its bootstrap 95% interval), the
rliable protocol's performance profiles and probabilities of improvement between groups
(:mod:`mapets_rl.app.rliable_report`) and, on request, the marl-eval JSON file, from the
``results.json`` of each run directory.

A comparison says what it compares and refuses what would mislead:

- *what is plotted*: deterministic evaluations (``source="eval"``, the default) or training
  entries (``source="train"``, e.g. MA-PETS's training episodes), never a mix without a word:
  a run without evaluations falls back to its training entries and its group is marked
  ``(train)`` when groups of both kinds are compared; a run whose recipe evaluates during
  training (its config has ``eval_interval``) but has not yet gets a logged warning, a run
  whose recipe evaluates on request only (MA-PETS: its planner acts in training as in
  evaluation) a logged note; the table and the plot title name the source;
- *the final numbers*: the table compares each run's last entry, or its final evaluation
  (``evaluation.json``, written by ``mapets-rl evaluate``) where every run of a group has one
  (``source="eval"``);
- *on what*: runs whose scenario (``env``) or scenario config (``env_config``) differ are
  refused unless ``allow_mixed_env`` (then each group is labelled with its scenario and a
  warning is logged), except the keys that ``group_by`` names;
- *grouped how*: by recipe, plus the values of the config fields in ``group_by`` (e.g. a sweep
  over ``comm.comm_range``), plus the simulator of the batched freeway when the runs' differ
  (``results.json``'s ``simulator``: its C++ kernel or its torch program), each group a mean
  and an interquartile mean (IQM) over its runs (seeds) with bootstrap 95% intervals
  (:mod:`mapets_rl.statistics`: the rliable protocol), clipped to each metric's range; a group
  of one run shows its values, ``n = 1``, and no interval; neither the tables nor the plot
  give an interval for a group of fewer than three runs (the interval of two is their range:
  their values are shown instead, as points in the plot, in braces in the tables);
- *at what point*: the table compares the runs of a group at the last ``x`` all of them
  reached, and its header says so when they end at different ``x``;
- *which metrics*: by default the task metrics (:data:`mapets_rl.metrics.TASK_METRICS`), every
  metric when asked (``metrics="all"``);
- *once*: a run given twice is refused, and so is an ``out_dir`` inside a run directory.
"""

from __future__ import annotations

import json
import logging
import math
import os
import textwrap
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from mapets_rl.app.protocol_report import protocol_summary, protocol_table, read_protocols
from mapets_rl.app.rliable_report import (
    gap_thresholds,
    plot_profiles,
    rliable_summary,
    rliable_table,
)
from mapets_rl.experiment.files import (
    atomic_savefig,
    atomic_write_text,
    check_writable_dir,
    make_writable_dir,
)
from mapets_rl.experiment.results import ENTRY_LISTS, SOURCES, read_evaluation, read_results
from mapets_rl.experiment.runner import refuse_run_dir_as_out
from mapets_rl.metrics import (
    MPH_PER_MPS,
    is_task_metric,
    metric_label,
    metric_range,
    metric_unit,
)
from mapets_rl.plotting import clip_y_axis, draw_band, draw_points
from mapets_rl.statistics import MIN_RUNS_FOR_INTERVAL, bootstrap_curve

log = logging.getLogger(__name__)

SOURCE_NAMES = {
    "eval": "deterministic evaluations",
    "train": "training entries",
    "evaluate": "final evaluations (evaluate)",
}
"""What a group's numbers come from: results.json's evaluations or training entries, or the
runs' ``evaluation.json`` (the table only)."""
STATISTIC_NAMES = {
    "mean": "mean [95% bootstrap CI]",
    "iqm": "interquartile mean (IQM) [95% stratified bootstrap CI]",
}
"""The statistics over a group's runs that ``compare`` reports."""
MARL_EVAL_FILE = "marl_eval.json"
"""The file ``compare(..., marl_eval=True)`` writes (InstaDeep's marl-eval raw-data format)."""


def _fmt(value: Any) -> str:
    """A config value for a label: numbers as ``%g``, strings as they are, others as JSON."""
    if isinstance(value, bool) or value is None:
        return json.dumps(value)
    if isinstance(value, (int, float)):
        return f"{value:g}"
    return value if isinstance(value, str) else json.dumps(value, sort_keys=True)


def _fmt_x(value: float) -> str:
    """An x value for a message: integers in full (``1000000``, not ``1e+06``)."""
    return str(int(value)) if float(value).is_integer() else f"{value:g}"


_MISSING = object()


def _lookup(res: Mapping[str, Any], field: str) -> Any:
    """Value of the dotted config ``field`` (e.g. ``env_config.observation``) of a run,
    ``_MISSING`` when its config has no such field."""
    value: Any = res.get("config", {})
    for part in field.split("."):
        if not isinstance(value, Mapping) or part not in value:
            return _MISSING
        value = value[part]
    return value


def _group_values(
    runs: Sequence[str], results: Sequence[Mapping[str, Any]], fields: Sequence[str]
) -> list[dict[str, Any]]:
    """Per run, ``{field: value}`` of the ``group_by`` fields its recipe has.

    A field that no run of a recipe has is left out of that recipe's groups (``comm.comm_range``
    splits MA-PETS runs and leaves the baselines beside them whole); a field that some runs of
    one recipe have and others lack, or that no run has, is a ValueError naming a run."""
    values = [{f: _lookup(res, f) for f in fields} for res in results]
    for field in fields:
        if all(v[field] is _MISSING for v in values):
            raise ValueError(
                f"group_by field {field!r} is not in the config of run_dir {runs[0]!r}"
            )
        for recipe in {res["recipe"] for res in results}:
            mine = [i for i, res in enumerate(results) if res["recipe"] == recipe]
            missing = [i for i in mine if values[i][field] is _MISSING]
            if missing and len(missing) < len(mine):
                raise ValueError(
                    f"group_by field {field!r} is not in the config of run_dir "
                    f"{runs[missing[0]]!r} (other {recipe} runs have it)"
                )
    return [{f: v for f, v in vals.items() if v is not _MISSING} for vals in values]


def _scenario(res: Mapping[str, Any]) -> dict[str, str]:
    """``{"env": name, "env_config.<key>": value as JSON}`` of a run: the keys its
    ``env_config`` sets, and every other key of a built-in scenario at its default (so that a
    key set to its default value and a key left unset compare equal)."""
    from mapets_rl.envs.registry import scenario_defaults

    env_config = {
        **scenario_defaults(res["env"]),
        **(res.get("config", {}).get("env_config") or {}),
    }
    out = {"env": json.dumps(res["env"])}
    out.update({f"env_config.{k}": json.dumps(v, sort_keys=True) for k, v in env_config.items()})
    return out


def _scenario_differences(
    runs: Sequence[str], results: Sequence[Mapping[str, Any]], group_by: Sequence[str]
) -> dict[str, dict[str, list[str]]]:
    """Scenario keys whose values differ between runs -> {value: [runs]}; the keys that
    ``group_by`` names (``env``, ``env_config`` or ``env_config.<key>``) are exempt."""
    scenarios = [_scenario(res) for res in results]
    keys = sorted(set().union(*scenarios))
    exempt = [k for k in keys if any(k == f or k.startswith(f + ".") for f in group_by)]
    diffs: dict[str, dict[str, list[str]]] = {}
    for key in keys:
        if key in exempt:
            continue
        by_value: dict[str, list[str]] = {}
        for run, scenario in zip(runs, scenarios, strict=True):
            by_value.setdefault(scenario.get(key, "unset"), []).append(run)
        if len(by_value) > 1:
            diffs[key] = by_value
    return diffs


def _scenario_labels(
    results: Sequence[Mapping[str, Any]],
    diffs: Mapping[str, Mapping[str, list[str]]],
    name_env: bool = False,
) -> list[str]:
    """Per run, its scenario in a few words: the scenario's name when the runs' ``env`` differ
    (or ``name_env``), and ``key=value`` of the ``env_config`` keys that differ between runs of
    the same ``env`` (``"figure-eight, n_cavs=8"``; two scenarios differ in most of their keys,
    which would say nothing)."""
    scenarios = [_scenario(res) for res in results]
    by_env = _by_env(scenarios)
    labels = []
    for scenario in scenarios:
        same_env = by_env[scenario["env"]]
        parts = [_fmt(json.loads(scenario["env"]))] if "env" in diffs or name_env else []
        for key in diffs:
            if key != "env" and len({s.get(key) for s in same_env}) > 1:
                value = _fmt(json.loads(scenario[key])) if key in scenario else "unset"
                parts.append(f"{key.removeprefix('env_config.')}={value}")
        labels.append(", ".join(parts) or _fmt(json.loads(scenario["env"])))
    return labels


def _by_env(scenarios: Sequence[Mapping[str, str]]) -> dict[str, list[Mapping[str, str]]]:
    """The runs' :func:`_scenario` dicts by their ``env``."""
    by_env: dict[str, list[Mapping[str, str]]] = {}
    for scenario in scenarios:
        by_env.setdefault(scenario["env"], []).append(scenario)
    return by_env


def _keys_to_group_by(
    results: Sequence[Mapping[str, Any]], diffs: Mapping[str, Mapping[str, list[str]]]
) -> list[str]:
    """The scenario keys that split the runs: ``env`` when it differs, and the ``env_config``
    keys that differ between runs of the same ``env``."""
    by_env = _by_env([_scenario(res) for res in results])
    return [
        key
        for key in diffs
        if key == "env" or any(len({s.get(key) for s in same}) > 1 for same in by_env.values())
    ]


def _describe_scenarios(runs: Sequence[str], labels: Sequence[str]) -> str:
    """``"figure-eight, n_cavs=4 (run a), freeway (run b and 2 more)"``: each scenario and a
    run on it."""
    by_label: dict[str, list[str]] = {}
    for run, label in zip(runs, labels, strict=True):
        by_label.setdefault(label, []).append(run)
    return ", ".join(
        f"{label} (run {mine[0]}" + (f" and {len(mine) - 1} more)" if len(mine) > 1 else ")")
        for label, mine in by_label.items()
    )


def compare(
    run_dirs: Sequence[str | os.PathLike],
    out_dir: str | os.PathLike,
    metrics: Sequence[str] | str | None = None,
    *,
    source: str = "eval",
    group_by: Sequence[str] | str | None = None,
    x: str = "frames",
    x_grid: float | None = None,
    allow_mixed_env: bool = False,
    legacy_as: str = "eval",
    title: str | None = None,
    marl_eval: bool = False,
    optimality_thresholds: Mapping[str, float] | None = None,
) -> dict[str, Path]:
    """Group runs by recipe (and the values of ``group_by`` fields), and write to ``out_dir``:

    - ``learning_curves.png``: one panel per metric against ``x``, the mean over the group's
      runs with a shaded bootstrap 95% band clipped to the metric's range
      (:func:`mapets_rl.plotting.draw_band`; for a group of at least three runs: a group of
      two shows each run's values as points, one run its line), at the ``x`` values every run
      of the group reached; the y axis inside the metric's range, speeds also in mph on a
      second axis; the title names the source;
    - ``final_metrics.md``: two markdown tables of each run's final numbers, ``mean [low,
      high] (n=runs)`` and the interquartile mean ``iqm [low, high] (n=runs)``, with the source
      of every group and its ``frames`` (the fewest of its runs' compared entries); a group of
      two runs has no interval but each run's value, ``mean {run, run} (n=2)`` (the bootstrap
      interval of two runs is their range; a note under the header says so), one run its
      value, ``value (n=1)``;
    - ``summary.json``: those numbers, ``{group: {metric: {"mean", "mean_ci95", "iqm",
      "iqm_ci95", "std", "values", "n", "frames", "source"}}}`` (each ``*_ci95`` ``[low,
      high]``, null below three runs; ``std`` null for ``n = 1``; ``values`` each run's);
    - ``curves.json``: ``{"source": the requested source, "x": x, "groups": {group: ...}}``,
      per group its recipe, ``group_by`` values, scenario, source, runs and, at every ``x``
      value any of its runs reached (``x``, ``n`` runs), ``mean`` / ``std`` / ``mean_ci95``
      / ``iqm`` / ``iqm_ci95`` of every metric (``std`` null where ``n = 1``, the intervals
      where ``n < 3``);
    - ``rliable.md``, ``rliable.json`` and ``performance_profiles.png``: the rliable
      protocol over the same final numbers (:mod:`mapets_rl.app.rliable_report`): per metric
      each group's performance profile (fraction of its runs above ``tau``, with a
      stratified-bootstrap 95% band), its optimality gap below ``gamma``
      (``optimality_thresholds``) and the probability of improvement P(X > Y) of every
      ordered pair of groups (with a bootstrap 95% interval), intervals only where the groups
      have at least three runs;
    - with ``marl_eval``, ``marl_eval.json``: every run's entries in InstaDeep's marl-eval
      raw-data format, ``{env: {task: {algorithm: {"run_<i>": {"step_<k>": {"step_count":
      frames, metric: [value]}, ..., "absolute_metrics": {metric: [value]}}}}}}``: the
      scenario's name, its ``env_config`` keys that differ from the scenario's defaults
      (``"n_cavs=8"``; ``"default"`` when none), the group (recipe and ``group_by`` values),
      the runs of the group in order, the run's compared entries in ``x`` order (``step_count``
      their environment frames) and its final evaluation (``evaluation.json``) or, without
      one, its last entry.

    The intervals are percentile-bootstrap intervals over the group's runs (the mean's) and
    stratified-bootstrap intervals of the interquartile mean (Agarwal et al. 2021; see
    :mod:`mapets_rl.statistics`), clipped to the values the metric can take
    (:data:`mapets_rl.metrics.METRIC_RANGES`: safety in [0, 1], speeds and counts >= 0). Frames
    and other integer ``x`` get integer ticks.

    The table compares each run's final evaluation (``evaluation.json``, written by
    ``mapets-rl evaluate``, at or after the run's last entry and holding every compared metric)
    where every run of a group has one and ``source`` is ``"eval"``. Otherwise runs of one
    group that end at different ``x`` (a run still training, a resumed one, seeds whose
    episodes end at different frames) are compared, in the table and ``summary.json``, at the
    last ``x`` all of them reached: each run's last entry at or before it, and the table's
    header line names the group, that ``x`` and where its runs end. Aligning, rather than
    refusing, keeps the comparison of a run in progress (or of runs that log at slightly
    different frames) possible while never averaging entries of different training progress
    without a word; a group whose runs share no such ``x`` (one run ends before another's first
    entry) is refused, pointing at ``x_grid``. Different groups are not aligned with each
    other: each row names its own ``frames``.

    Args:
        run_dirs: run directories, each holding ``results.json``.
        out_dir: output directory (created).
        metrics: metric names to show, at least one; ``"all"``: every metric present in all
            compared entries; ``None`` (default): those of them that are task metrics
            (:data:`mapets_rl.metrics.TASK_METRICS`: agility, safety, velocity, comfort,
            collisions, length, reward, return), not the bookkeeping (timings, counters,
            losses), or all of them when none is a task metric.
        source: ``"eval"``: deterministic evaluations; a run without any falls back to its
            training entries (a note when its recipe evaluates on request only, as MA-PETS,
            a warning when it evaluates during training but has not yet), and its group is
            marked ``(train)`` beside groups of evaluations. ``"train"``: training entries,
            every run must have some.
        group_by: config fields (dotted for nested ones, e.g. ``"comm.comm_range"``,
            ``"env_config.observation"``) whose values split each recipe's runs into groups;
            a recipe none of whose runs has a field is not split by it (MA-PETS by range
            beside the baselines).
        x: the x axis: ``"frames"`` (environment frames) or a metric of every entry that
            numbers the entries, e.g. ``"episode"`` (runs whose episodes differ in length
            share episodes, not frames).
        x_grid: put every run on the x values ``x_grid, 2 x_grid, ...``: at each, the run's
            last entry at or before it (up to the first grid value at or past its last
            entry). Runs that log at different x then share a curve, e.g. MA-PETS's
            episodes, which end early when every CAV crashed, beside baselines evaluated
            every 200 frames (``x_grid=200``). ``None`` (default): the x values as logged.
        allow_mixed_env: compare runs whose ``env`` or ``env_config`` differ (beyond the
            ``group_by`` fields): a warning is logged and each group is labelled with its
            scenario. Without it such runs are refused.
        legacy_as: where the entries of a results file from before training and evaluation
            entries were kept apart go (``"eval"`` or ``"train"``; see :func:`read_results`);
            such runs are named in a logged note.
        title: prefix of the plot title (e.g. the experiment's name).
        marl_eval: also write ``marl_eval.json`` (the input of InstaDeep's marl-eval tools).
        optimality_thresholds: metric -> ``gamma`` of its optimality gap in the rliable report;
            a compared metric left out takes the top of its range where it has one (safety
            1), else has no gap; a metric not compared, or a value that is not a finite
            number, is refused.
    Returns:
        ``{"plot": Path, "table": Path, "summary": Path, "curves": Path, "rliable": Path,
        "rliable_table": Path, "profiles_plot": Path}``, and ``"marl_eval": Path`` with
        ``marl_eval``; when every run was scored by the evaluation
        protocol (``mapets-rl evaluate RUN --roads B``), ``"protocol"`` (``protocol.md``: the
        gains over each reference per seed, their mean and IQM with bootstrap intervals, the
        training return, the behaviour metrics; :mod:`mapets_rl.app.protocol_report`) and
        ``"protocol_summary"`` (``protocol.json``).
    Raises:
        ValueError: one line, before anything is written, when a run has no usable results
            (or a malformed ``evaluation.json``), a run is given twice (paths resolved),
            ``out_dir`` is inside a run directory, runs of different scenarios are mixed
            without ``allow_mixed_env`` (the message names the scenarios), a ``group_by``
            field or the ``x`` metric is missing, the runs of a group share no ``x``, a metric
            is unknown, ``metrics`` is empty, an option is not one of its choices or
            ``out_dir`` cannot be written.
    """
    if not run_dirs:
        raise ValueError("run_dirs must name at least one run directory")
    every_metric = metrics == "all"
    if isinstance(metrics, str):
        metrics = None if every_metric else [metrics]
    if x_grid is not None and not (math.isfinite(x_grid) and x_grid > 0):
        raise ValueError(f"x_grid must be a finite number > 0 (or None), got {x_grid!r}")
    if metrics is not None and not list(metrics):
        raise ValueError("metrics must name at least one metric (or None for all common ones)")
    if source not in SOURCES:
        raise ValueError(f"source must be one of {list(SOURCES)}, got {source!r}")
    fields = [group_by] if isinstance(group_by, str) else list(group_by or [])
    if any(not f or not isinstance(f, str) for f in fields):
        raise ValueError(f"group_by must name config fields, got {group_by!r}")
    _check_distinct(run_dirs, out_dir)
    refuse_run_dir_as_out(out_dir, "out_dir")
    check_writable_dir(out_dir, "out_dir")
    runs = [str(d) for d in run_dirs]
    results = [read_results(d, legacy_as=legacy_as) for d in run_dirs]
    evaluations = [read_evaluation(d) for d in run_dirs]
    protocols = read_protocols(runs)

    # what each run contributes
    sources: list[str] = []
    fallback, on_request = [], []
    for run, res in zip(runs, results, strict=True):
        if res[ENTRY_LISTS[source]]:
            sources.append(source)
        elif source == "train":
            raise ValueError(
                f"run_dir {run!r} has no training entries (its recipe records "
                "only evaluations); compare its evaluations (source 'eval')"
            )
        elif res["train"]:
            sources.append("train")
            evaluates = "eval_interval" in res.get("config", {})
            (fallback if evaluates else on_request).append(run)
        else:
            raise ValueError(f"run_dir {run!r} has no evaluations yet")
    legacy = [run for run, res in zip(runs, results, strict=True) if res["legacy"]]

    # on what: one scenario unless told otherwise
    diffs = _scenario_differences(runs, results, fields)
    scenario_labels = _scenario_labels(results, diffs)
    if diffs and not allow_mixed_env:
        raise ValueError(
            "the runs are on different scenarios: "
            f"{_describe_scenarios(runs, _scenario_labels(results, diffs, name_env=True))}; "
            "pass allow_mixed_env=True (--allow-mixed-env) to compare them anyway, or group_by "
            f"the keys that differ ({', '.join(_keys_to_group_by(results, diffs))})"
        )

    # groups: recipe + group_by values (+ scenario, source, simulator when mixed)
    mixed_sources = len(set(sources)) > 1
    mixed_simulators = len({res.get("simulator") for res in results}) > 1
    groups: dict[str, dict[str, Any]] = {}
    for run, res, src, values, scenario, evaluation in zip(
        runs,
        results,
        sources,
        _group_values(runs, results, fields),
        scenario_labels,
        evaluations,
        strict=True,
    ):
        algorithm = " ".join([res["recipe"], *(f"{f}={_fmt(v)}" for f, v in values.items())])
        label = f"{algorithm} [{scenario}]" if diffs else algorithm
        if mixed_sources:
            algorithm += f" ({src})"
            label += f" ({src})"
        if mixed_simulators:  # the batched freeway's kernel and torch program part ways
            simulator = f" ({res.get('simulator') or 'unrecorded'} simulator)"
            algorithm += simulator
            label += simulator
        group = groups.setdefault(
            label,
            {
                "recipe": res["recipe"],
                "algorithm": algorithm,
                "group": values,
                "env": res["env"],
                "task": _task_name(res),
                "source": src,
                "runs": [],
                "entries": [],
                "evaluations": [],
            },
        )
        group["runs"].append(run)
        group["entries"].append(res[ENTRY_LISTS[src]])
        group["evaluations"].append(evaluation)

    all_entries = [e for g in groups.values() for entries in g["entries"] for e in entries]
    common = set.intersection(*(set(e["metrics"]) for e in all_entries))
    if x != "frames":
        if x not in common:
            raise ValueError(
                f"x {x!r} is not a metric of every compared entry (common "
                f"metrics: {sorted(common)}); use 'frames' or one of those"
            )
        common.discard(x)
    if metrics is None:
        metrics = sorted(common)
        if not metrics:
            raise ValueError("the runs have no metric in common to compare")
        task = [m for m in metrics if is_task_metric(m)]
        if task and not every_metric:
            if len(task) < len(metrics):
                log.info(
                    "showing the task metrics %s; metrics='all' (--metrics all) shows the "
                    "others too (%s)",
                    task,
                    ", ".join(m for m in metrics if m not in task),
                )
            metrics = task
    unknown = [m for m in metrics if m not in common]
    if unknown:
        raise ValueError(f"metrics {unknown} are not in every run (available: {sorted(common)})")
    _check_numbers(groups, [*metrics, *([x] if x != "frames" else [])])
    gammas = gap_thresholds(metrics, optimality_thresholds)

    # per group, each run's entries by x, and the entries the table compares
    for label, group in groups.items():
        group["by_entry"] = [{_x_value(e, x): e for e in entries} for entries in group["entries"]]
        if x_grid is not None:
            group["by_entry"] = [_on_grid(be, x_grid) for be in group["by_entry"]]
        group["final"] = _final_evaluations(group, metrics) if source == "eval" else None
        if group["final"] is None:
            group["last"], group["ends"] = _aligned_last(label, group["runs"], group["by_entry"], x)
        else:
            group["last"], group["ends"] = group["final"], []

    out_dir = make_writable_dir(out_dir, "out_dir")
    if legacy:
        log.warning(
            "%s: results.json predates the split of training and evaluation entries; "
            "its entries are read as %s (legacy_as=%r)",
            ", ".join(legacy),
            SOURCE_NAMES[legacy_as],
            legacy_as,
        )
    if fallback:
        log.warning(
            "%s: no evaluations; comparing their training entries instead%s",
            ", ".join(fallback),
            " (groups marked (train))" if mixed_sources else "",
        )
    if on_request:
        log.info(
            "%s: training entries (the recipe evaluates on request only, "
            "with mapets-rl evaluate)%s",
            ", ".join(on_request),
            " (groups marked (train))" if mixed_sources else "",
        )
    if diffs:
        log.warning(
            "comparing runs on different scenarios (%s); each group is labelled with its scenario",
            _describe_scenarios(runs, _scenario_labels(results, diffs, name_env=True)),
        )
    summary: dict[str, dict[str, dict[str, Any]]] = {}
    curves: dict[str, Any] = {"source": source, "x": x, "groups": {}}
    finals: dict[str, dict[str, list[float]]] = {}
    run_values: dict[str, list[dict[float, Any]]] = {}
    cut: list[str] = []
    for label, group in groups.items():
        by_entry, last, ends = group["by_entry"], group["last"], group["ends"]
        if len(set(ends)) > 1:
            cut.append(
                f"{label} at {x} {_fmt_x(min(ends))} (its runs end at {x} "
                f"{_fmt_x(min(ends))} to {_fmt_x(max(ends))})"
            )
        summary[label] = {}
        finals[label] = {m: [e["metrics"][m] for e in last] for m in metrics}
        for m in metrics:
            final = _interval_stats(m, [finals[label][m]])
            summary[label][m] = {
                **{key: values[0] for key, values in final.items()},
                "values": finals[label][m],
                "n": len(last),
                "frames": min(e["frames"] for e in last),
                "source": "evaluate" if group["final"] is not None else group["source"],
            }
        by_x = [{v: e["metrics"] for v, e in be.items()} for be in by_entry]
        run_values[label] = by_x
        xs = sorted(set().union(*by_x))
        counts = [sum(v in bx for bx in by_x) for v in xs]
        stats: dict[str, dict[str, list[Any]]] = {}
        for m in metrics:
            stats[m] = _interval_stats(m, [[bx[v][m] for bx in by_x if v in bx] for v in xs])
        curves["groups"][label] = {
            "recipe": group["recipe"],
            "group": group["group"],
            "env": group["env"],
            "source": group["source"],
            "runs": group["runs"],
            "x": xs,
            "n": counts,
            "metrics": stats,
        }

    described = (
        SOURCE_NAMES[sources[0]]
        if not mixed_sources
        else f"{SOURCE_NAMES['eval']}, training entries for the groups marked (train)"
    )
    plot = out_dir / "learning_curves.png"
    _plot(
        curves["groups"],
        run_values,
        metrics,
        x,
        plot,
        f"{title}: {described}" if title else described,
    )
    table = out_dir / "final_metrics.md"
    aligned = (
        f" Runs of a group that end at different {x} are compared at the last {x} all of "
        f"them reached: {'; '.join(cut)}."
        if cut
        else ""
    )
    evaluated = (
        ", or its final evaluation (evaluation.json, written by mapets-rl evaluate) for the "
        f"groups of source {SOURCE_NAMES['evaluate']!r}"
        if any(group["final"] is not None for group in groups.values())
        else ""
    )
    few = (
        f" Groups of fewer than {MIN_RUNS_FOR_INTERVAL} runs have no interval (the bootstrap "
        "interval of two runs is their range): each run's value in braces, {run, run}."
        if any(1 < len(group["runs"]) < MIN_RUNS_FOR_INTERVAL for group in groups.values())
        else ""
    )
    lines = [
        f"Last entry of each run: {described}{evaluated}; over runs, intervals clipped to "
        f"each metric's range (n = runs).{few}{aligned}",
    ]
    for statistic, name in STATISTIC_NAMES.items():
        lines += [
            "",
            f"{name[0].upper()}{name[1:]}:",
            "",
            "| group | source | frames | " + " | ".join(map(metric_label, metrics)) + " |",
            "|" + "---|" * (len(metrics) + 3),
        ]
        for label, row in summary.items():
            cells = [_cell(m, row[m], statistic) for m in metrics]
            first = row[metrics[0]]
            lines.append(
                f"| {label} | {SOURCE_NAMES[first['source']]} | {first['frames']} | "
                + " | ".join(cells)
                + " |"
            )
    atomic_write_text(table, "\n".join(lines) + "\n")
    summary_path = out_dir / "summary.json"
    atomic_write_text(summary_path, json.dumps(summary, indent=1))
    curves_path = out_dir / "curves.json"
    atomic_write_text(curves_path, json.dumps(curves, indent=1))
    written = {"plot": plot, "table": table, "summary": summary_path, "curves": curves_path}
    rliable = rliable_summary(finals, metrics, gammas)
    written["rliable"] = out_dir / "rliable.json"
    atomic_write_text(written["rliable"], json.dumps(rliable, indent=1))
    written["rliable_table"] = out_dir / "rliable.md"
    atomic_write_text(written["rliable_table"], rliable_table(rliable))
    written["profiles_plot"] = out_dir / "performance_profiles.png"
    plot_profiles(rliable, written["profiles_plot"], title)
    if marl_eval:
        written["marl_eval"] = out_dir / MARL_EVAL_FILE
        atomic_write_text(written["marl_eval"], json.dumps(_marl_eval(groups, metrics), indent=1))
    if protocols is not None:
        members = {label: group["runs"] for label, group in groups.items()}
        report = protocol_summary(members, dict(zip(runs, protocols, strict=True)))
        written["protocol"] = out_dir / "protocol.md"
        atomic_write_text(written["protocol"], protocol_table(report, protocols[0]["roads"]))
        written["protocol_summary"] = out_dir / "protocol.json"
        atomic_write_text(written["protocol_summary"], json.dumps(report, indent=1))
    return written


def _interval_stats(metric: str, points: Sequence[Sequence[float]]) -> dict[str, list[Any]]:
    """At every point (one value per run, a run missing from a point left out): the mean and
    the IQM with their bootstrap 95% intervals clipped to the metric's range (``[low, high]``,
    ``None`` below :data:`~mapets_rl.statistics.MIN_RUNS_FOR_INTERVAL` values: the interval of
    two is their range) and the sample standard deviation (``None`` for one value); each key a
    list over the points. Points with as many values are bootstrapped together
    (:func:`~mapets_rl.statistics.bootstrap_curve`: the same intervals as one at a time)."""
    out: dict[str, list[Any]] = {
        key: [None] * len(points) for key in ("mean", "mean_ci95", "iqm", "iqm_ci95", "std")
    }
    by_count: dict[int, list[int]] = {}
    for i, values in enumerate(points):
        by_count.setdefault(len(values), []).append(i)
    for count, where in by_count.items():
        runs = np.array([points[i] for i in where], dtype=float).T  # [runs, points]
        for statistic in ("mean", "iqm"):
            estimate, low, high = bootstrap_curve(runs, statistic, bounds=metric_range(metric))
            for j, i in enumerate(where):
                out[statistic][i] = float(estimate[j])
                if count >= MIN_RUNS_FOR_INTERVAL:
                    out[f"{statistic}_ci95"][i] = [float(low[j]), float(high[j])]
        if count > 1:
            for j, std in zip(where, runs.std(axis=0, ddof=1), strict=True):
                out["std"][j] = float(std)
    return out


def _final_evaluations(
    group: Mapping[str, Any], metrics: Sequence[str]
) -> list[dict[str, Any]] | None:
    """The group's runs' final evaluations (``evaluation.json``) as entries, when every run
    has one at or after its last entry holding every metric; else ``None`` (with a note
    when some runs have a usable one)."""
    usable = [
        evaluation is not None
        and evaluation["frames"] >= max(e["frames"] for e in entries)
        and all(m in evaluation["metrics"] for m in metrics)
        for evaluation, entries in zip(group["evaluations"], group["entries"], strict=True)
    ]
    if all(usable):
        return [{"frames": e["frames"], "metrics": e["metrics"]} for e in group["evaluations"]]
    if any(usable):
        log.info(
            "%s: not every run has a final evaluation (evaluation.json at or after its last "
            "entry, with every compared metric); the table compares their last entries",
            ", ".join(run for run, ok in zip(group["runs"], usable, strict=True) if not ok),
        )
    return None


def _task_name(res: Mapping[str, Any]) -> str:
    """marl-eval's task of a run: its ``env_config`` keys that differ from the scenario's
    defaults, ``"key=value"`` comma-joined, lower case (``"default"`` when none)."""
    from mapets_rl.envs.registry import scenario_defaults

    defaults = scenario_defaults(res["env"])
    env_config = res.get("config", {}).get("env_config") or {}
    changed = [
        f"{key}={_fmt(value)}"
        for key, value in sorted(env_config.items())
        if key not in defaults or defaults[key] != value
    ]
    return ",".join(changed).lower() or "default"


def _marl_eval(groups: Mapping[str, Mapping[str, Any]], metrics: Sequence[str]) -> dict[str, Any]:
    """The groups' runs in marl-eval's raw-data format (see :func:`compare`)."""
    data: dict[str, Any] = {}
    for group in groups.values():
        algorithms = data.setdefault(group["env"].lower(), {}).setdefault(group["task"], {})
        runs = algorithms.setdefault(group["algorithm"], {})
        for by_entry, evaluation in zip(group["by_entry"], group["evaluations"], strict=True):
            steps = [by_entry[v] for v in sorted(by_entry)]
            run = {
                f"step_{k}": {
                    "step_count": entry["frames"],
                    **{m: [entry["metrics"][m]] for m in metrics},
                }
                for k, entry in enumerate(steps)
            }
            final = evaluation if evaluation is not None else steps[-1]
            run["absolute_metrics"] = {
                m: [final["metrics"][m]] for m in metrics if m in final["metrics"]
            }
            runs[f"run_{len(runs)}"] = run
    return data


def _cell(metric: str, stats: Mapping[str, Any], statistic: str) -> str:
    """A table cell: the ``statistic`` (``"mean"`` or ``"iqm"``) with its 95% interval
    ``[low, high]`` (n), speeds in m/s also in mph; below
    :data:`~mapets_rl.statistics.MIN_RUNS_FOR_INTERVAL` runs no interval but each run's value,
    ``value {run, run} (n=2)``, and the value alone for one run (``n=1``)."""
    value, interval = stats[statistic], stats[f"{statistic}_ci95"]
    runs = stats["values"] if stats["n"] > 1 else []

    def text(scale: float) -> str:
        if interval is None:
            points = ", ".join(f"{scale * v:.4g}" for v in runs)
            return f"{scale * value:.4g} {{{points}}}" if points else f"{scale * value:.4g}"
        return f"{scale * value:.4g} [{scale * interval[0]:.4g}, {scale * interval[1]:.4g}]"

    out = text(1.0)
    if metric_unit(metric) == "m/s":
        out += f" ({text(MPH_PER_MPS)} mph)"
    return f"{out} (n={stats['n']})"


def _check_distinct(run_dirs: Sequence[str | os.PathLike], out_dir: str | os.PathLike) -> None:
    """One-line ValueError when a run directory is given twice (paths resolved: symlinks,
    ``..``) or ``out_dir`` is, or is inside, one of them (the comparison would be written into
    a run)."""
    seen: dict[Path, str] = {}
    for run in run_dirs:
        real = Path(run).resolve()
        if real in seen:
            raise ValueError(
                f"run_dir {str(run)!r} is {seen[real]!r} again: a run counted twice would "
                "weigh double in its group's mean; name each run once"
            )
        seen[real] = str(run)
    out = Path(out_dir).resolve()
    for real, run in seen.items():
        if out == real or real in out.parents:
            raise ValueError(
                f"out_dir {str(out_dir)!r} is inside run_dir {run!r}: the comparison would be "
                "written into a run; choose an --out outside every compared run"
            )


def _check_numbers(groups: Mapping[str, Mapping[str, Any]], names: Sequence[str]) -> None:
    """ValueError naming the run, the metric and the entry's frames when a compared metric
    (``names``) of an entry is not a finite number (NaN, a string: an edited or damaged
    ``results.json``, or a run that trained on NaN)."""
    for group in groups.values():
        for run, entries in zip(group["runs"], group["entries"], strict=True):
            for entry in entries:
                for name in names:
                    value = entry["metrics"][name]
                    number = isinstance(value, (int, float)) and not isinstance(value, bool)
                    if not (number and math.isfinite(value)):
                        raise ValueError(
                            f"run_dir {run!r}: metric {name!r} at frames {entry['frames']} is "
                            f"{value!r}, not a finite number; it cannot be compared"
                        )


def _aligned_last(
    label: str, runs: Sequence[str], by_entry: Sequence[Mapping[float, Any]], x: str
) -> tuple[list[Mapping[str, Any]], list[float]]:
    """Each run's entry at the last ``x`` all runs of the group reached (its last entry at or
    before the smallest last ``x``), and the last ``x`` of each run. A one-line ValueError
    naming the runs when one has no entry that early."""
    ends = [max(be) for be in by_entry]
    common = min(ends)
    first = ends.index(common)
    last = []
    for run, be in zip(runs, by_entry, strict=True):
        before = [v for v in be if v <= common]
        if not before:
            raise ValueError(
                f"group {label!r}: run_dir {run!r} has no entry at {x} <= {_fmt_x(common)}, "
                f"where run_dir {runs[first]!r} ends, so the runs share no {x} to compare at; "
                "put them on common x values with x_grid (--x-grid)"
            )
        last.append(be[max(before)])
    return last, ends


def _on_grid(by_x: Mapping[float, Any], step: float) -> dict[float, Any]:
    """``{k * step: the value of the largest x <= k * step}`` for ``k = 1 .. ceil(max x /
    step)`` (grid values before the first x are left out)."""
    xs = sorted(by_x)
    out: dict[float, Any] = {}
    j = -1
    for k in range(1, math.ceil(xs[-1] / step) + 1):
        g = k * step
        while j + 1 < len(xs) and xs[j + 1] <= g:
            j += 1
        if j >= 0:
            out[int(g) if float(g).is_integer() else g] = by_x[xs[j]]
    return out


def _x_value(entry: Mapping[str, Any], x: str) -> float:
    """The x of an entry: its frames, or its metric ``x``."""
    return entry["frames"] if x == "frames" else entry["metrics"][x]


def _plot(
    groups: Mapping[str, Mapping[str, Any]],
    run_values: Mapping[str, Sequence[Mapping[float, Mapping[str, float]]]],
    metrics: Sequence[str],
    x: str,
    path: Path,
    title: str,
) -> None:
    """One panel per metric: every group's mean at the x values all its runs reached (a group
    whose runs share none is left out, with a logged note) and, for a group of at least
    :data:`~mapets_rl.statistics.MIN_RUNS_FOR_INTERVAL` runs, its bootstrap 95% band
    (:func:`mapets_rl.plotting.draw_band`, clipped to the metric's range); a group of two runs
    shows each run's values as points instead (``run_values``: per group, each run's metrics
    by x), one run its line alone. The y axis stays inside the metric's range (no count below
    zero); speeds get a second axis in mph; integer ticks when every x is an integer (frames,
    episodes)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.ticker import MaxNLocator

    integer_x = all(float(v).is_integer() for group in groups.values() for v in group["x"])
    n = max(len(metrics), 1)
    cols = min(n, 3)
    rows = math.ceil(n / cols)
    fig, axes = plt.subplots(
        rows, cols, figsize=(5 * cols, 3.6 * rows + 0.5), squeeze=False, layout="constrained"
    )
    for label, group in groups.items():
        full = [i for i, count in enumerate(group["n"]) if count == len(group["runs"])]
        if not full:
            log.warning(
                "group %r: its runs share no %s value, so its curve is not drawn (runs "
                "whose episodes differ in length share episodes, not frames: plot "
                "against a metric that numbers them, e.g. x='episode')",
                label,
                x,
            )
    for ax, m in zip(list(axes.flat)[:n], metrics, strict=False):
        for label, group in groups.items():
            full = [i for i, count in enumerate(group["n"]) if count == len(group["runs"])]
            if not full:
                continue
            xs = [group["x"][i] for i in full]
            stats = group["metrics"][m]
            count = len(group["runs"])
            banded = count >= MIN_RUNS_FOR_INTERVAL  # two runs' interval is their range
            line = draw_band(
                ax,
                xs,
                [stats["mean"][i] for i in full],
                [stats["mean_ci95"][i][0] for i in full] if banded else None,
                [stats["mean_ci95"][i][1] for i in full] if banded else None,
                metric=m,
                marker="o",
                ms=3,
                label=f"{label} (n={count})",
            )
            if 1 < count < MIN_RUNS_FOR_INTERVAL:
                runs = [[by_x[v][m] for v in xs] for by_x in run_values[label]]
                draw_points(ax, xs, runs, color=line.get_color())
        clip_y_axis(ax, m)
        if metric_unit(m) == "m/s":
            mph = ax.secondary_yaxis(
                "right", functions=(lambda v: v * MPH_PER_MPS, lambda v: v / MPH_PER_MPS)
            )
            mph.set_ylabel("mph", fontsize=8)
        ax.set_title(metric_label(m), fontsize=9)
        ax.set_xlabel("environment frames [env steps]" if x == "frames" else metric_label(x))
        if integer_x:
            ax.xaxis.set_major_locator(MaxNLocator(integer=True))
        ax.grid(alpha=0.3)
    for ax in list(axes.flat)[n:]:
        ax.set_visible(False)
    axes.flat[0].legend(fontsize=8)
    fig.suptitle(
        textwrap.fill(
            f"{title}: mean over runs, bootstrap 95% CI for groups of >= "
            f"{MIN_RUNS_FOR_INTERVAL} runs, each run's values (points) for groups of 2",
            55 * cols,
        ),
        fontsize=10,
    )
    atomic_savefig(fig, path, dpi=110)
    plt.close(fig)
