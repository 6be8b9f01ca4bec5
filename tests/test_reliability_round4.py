"""Issue 51 (reliability, round four): each case a test that failed before its fix.

No write through a link (the logs a run appends to are never opened through a symbolic or hard
link); no ``--out`` in a run directory; a resume that cannot relabel a run (only the budget and
the intervals change); sweeps that take ``progress=false``, keep every trial they ran and check
their summary options first; no training on NaN and no run without an update; SIGTERM stops a
run with a checkpoint; the memory bound of the process's own cgroup; which simulator ran; and
the smaller cases (a bad metric in ``compare``, a full disk before the first checkpoint, two
sweeps into one ``--out``, a run that fails to start); the inputs of the batched freeway, its
simulator, ``make_env`` and ``wrap_pettingzoo`` (and the wrapped env's API), each refused in
one line naming it; the memory estimate of the batched freeway's roads; collector workers that
leave a SIGTERM to the run.
"""

from __future__ import annotations

import errno
import json
import os
import signal
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch
from gymnasium import spaces
from tensordict import TensorDict
from toy_recipe import ToyConfig, ToyLearner
from toy_scenario import ToyAgentsEnv

from mapets_rl.app import sweep
from mapets_rl.app.sweep import SweepResult, SweepSpec, run_sweep, run_trial
from mapets_rl.envs import registry
from mapets_rl.experiment import register_env, runner
from mapets_rl.experiment.checkpoint import list_checkpoints, load_checkpoint
from mapets_rl.experiment.episodes import TRAIN_EPISODES_FILE
from mapets_rl.experiment.files import RunDirLock, WriteFailed, open_append
from mapets_rl.experiment.runner import RunStopped
from tests.cli_run import run_cli
from tests.experiment.test_checkpoint_determinism import _assert_equal


# ------------------------------------------------------------- no append through a link
@pytest.fixture
def csv_toy_run(tmp_path, toy_scenario) -> Path:
    """A finished 20-frame toy run logging CSV scalars."""
    run_dir = tmp_path / "run"
    ToyLearner(ToyConfig(total_frames=20, logger="csv"), run_dir).train()
    return run_dir


def _reward_csv(run_dir: Path) -> Path:
    return run_dir / "logs" / "toy_toy" / "scalars" / "eval" / "reward.csv"


@pytest.mark.parametrize("target", ["victim", "empty victim", "dangling"])
def test_a_resume_never_appends_through_a_symlinked_csv_log(tmp_path, csv_toy_run, target):
    victim = tmp_path / "victim.csv"
    if target != "dangling":
        victim.write_text("" if target == "empty victim" else "0,1.0\n")
    log = _reward_csv(csv_toy_run)
    log.unlink()
    log.symlink_to(victim)
    resumed = ToyLearner.from_run_dir(csv_toy_run, ["total_frames=40"])
    resumed.train()
    assert resumed.frames == 40
    if target == "dangling":
        assert not victim.exists()
    else:
        assert victim.read_text() == ("" if target == "empty victim" else "0,1.0\n")
    assert not log.is_symlink() and log.read_text().splitlines()[-1].startswith("40,")


def test_a_resume_never_appends_through_a_hard_linked_csv_log(tmp_path, csv_toy_run):
    log = _reward_csv(csv_toy_run)
    victim = tmp_path / "victim.csv"
    victim.write_text(log.read_text())
    log.unlink()
    os.link(victim, log)
    before = victim.read_text()
    ToyLearner.from_run_dir(csv_toy_run, ["total_frames=40"]).train()
    assert victim.read_text() == before
    assert os.stat(log).st_nlink == 1 and log.read_text().startswith(before)


@pytest.mark.parametrize("dangling", [False, True])
def test_a_resume_never_appends_through_a_symlinked_episode_log(tmp_path, csv_toy_run, dangling):
    victim = tmp_path / "victim.jsonl"
    if not dangling:
        victim.write_text('{"frames": 0}\n')
    episodes = csv_toy_run / TRAIN_EPISODES_FILE
    episodes.unlink()
    episodes.symlink_to(victim)
    ToyLearner.from_run_dir(csv_toy_run, ["total_frames=40"]).train()
    assert not victim.exists() if dangling else victim.read_text() == '{"frames": 0}\n'
    assert not episodes.is_symlink() and episodes.is_file()


@pytest.mark.parametrize("kind", ["symlink", "hard link", "fifo"])
def test_open_append_refuses_a_file_that_is_not_a_plain_one_of_ours(tmp_path, kind):
    victim = tmp_path / "victim"
    victim.write_text("precious\n")
    path = tmp_path / "log.csv"
    {"symlink": path.symlink_to, "hard link": lambda v: os.link(v, path)}.get(
        kind, lambda _: os.mkfifo(path)
    )(victim)
    with pytest.raises(WriteFailed, match="cannot append to .*log.csv.* it ") as err:
        open_append(path)
    assert "\n" not in str(err.value)
    assert victim.read_text() == "precious\n"


def test_a_log_that_cannot_be_appended_to_is_one_line_from_the_cli(csv_toy_run, toy_recipe, capsys):
    log = _reward_csv(csv_toy_run)
    log.unlink()
    os.mkfifo(log)  # not a link: left in place, and refused when the run appends to it
    code, _, err = run_cli(["resume", str(csv_toy_run), "total_frames=40"], capsys)
    assert code == 2 and err.count("\n") == 1, err
    assert "cannot append to" in err and "reward.csv" in err and "not a regular file" in err


# ------------------------------------------------- --out of compare and sweep is no run dir
def _files(folder: Path) -> dict[Path, bytes]:
    return {p: p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


@pytest.mark.parametrize("inside", [False, True])
def test_compare_refuses_an_out_in_a_run_directory(tmp_path, csv_toy_run, capsys, inside):
    other = tmp_path / "other"
    ToyLearner(ToyConfig(total_frames=20), other).train()
    before = _files(other)
    out = other / "figures" if inside else other
    code, _, err = run_cli(["compare", str(csv_toy_run), "--out", str(out)], capsys)
    assert code == 2 and err.count("\n") == 1, err
    assert "is a run directory (it holds run.json)" in err
    assert _files(other) == before


def test_sweep_refuses_an_out_that_is_a_run_directory(tmp_path, csv_toy_run, toy_recipe, capsys):
    before = _files(csv_toy_run)
    argv = ["sweep", "toy", "--env", "toy", "--seeds", "0", "--out", str(csv_toy_run)]
    code, _, err = run_cli([*argv, "total_frames=20"], capsys)
    assert code == 2 and err.count("\n") == 1, err
    assert "out" in err and "is a run directory (it holds run.json)" in err
    assert _files(csv_toy_run) == before


# ------------------------------------------------- a resume cannot relabel a finished run
def _run_files(run_dir: Path) -> dict[Path, bytes]:
    """Every file of a run but its lock (whose pid record a resume rewrites in place)."""
    return {p: b for p, b in _files(run_dir).items() if p.name != ".lock"}


@pytest.mark.parametrize("override", ["lr=0.5", "eval_episodes=3", "sigma=0.1"])
def test_a_resume_that_changes_a_setting_is_refused_and_changes_no_file(
    csv_toy_run, toy_recipe, capsys, override
):
    before = _run_files(csv_toy_run)
    code, _, err = run_cli(["resume", str(csv_toy_run), override], capsys)
    assert code == 2 and err.count("\n") == 1, err
    key = override.partition("=")[0]
    assert f"cannot resume with {key} changed" in err and "start a new run" in err
    assert _run_files(csv_toy_run) == before
    with pytest.raises(ValueError, match=f"cannot resume with {key} changed"):
        ToyLearner.from_run_dir(csv_toy_run, ["total_frames=40", override])
    assert _run_files(csv_toy_run) == before


def test_a_resume_may_change_the_budget_intervals_and_bookkeeping(csv_toy_run):
    overrides = [
        "total_frames=40",
        "eval_interval=10",
        "checkpoint_interval=10",
        "keep_last=3",
        "logger=none",
        "progress=false",
        "video=false",
        "device=cpu",
    ]
    resumed = ToyLearner.from_run_dir(csv_toy_run, overrides)
    resumed.train()
    assert resumed.frames == 40 and resumed.config.eval_interval == 10
    assert [e["frames"] for e in resumed.results.evaluations] == [20, 30, 40]
    assert ToyLearner.check_resume(csv_toy_run, ["total_frames=80", "lr=0.05"]) is None


def test_a_mapets_resume_may_extend_its_episodes_only(tmp_path):
    from mapets_rl.recipes.mapets import MAPETS, MAPETSConfig
    from tests.recipes.test_recipe_mapets import TINY

    run_dir = tmp_path / "run"
    MAPETS(MAPETSConfig(**{**TINY, "episodes": 1}), run_dir).close()  # config.yaml only
    MAPETS.check_resume(run_dir, ["episodes=3", "num_threads=2", "keep_last=4"])
    with pytest.raises(ValueError, match=r"planner.horizon changed \(planner.horizon: 3 -> 4\)"):
        MAPETS.check_resume(run_dir, ["episodes=3", "planner.horizon=4"])


# ----------------------------------------------------------------------------- sweeps
SWEEP_TINY = [
    "total_frames=20",
    "frames_per_batch=10",
    "eval_interval=10",
    "checkpoint_interval=10",
]


@pytest.fixture
def sweep_here(toy_recipe, monkeypatch) -> Callable[..., SweepResult]:
    """``sweep_here(out, **spec fields)``: a toy sweep (seed 0, :data:`SWEEP_TINY` unless its
    ``overrides`` set the key) whose trials run in this process, one after the other (the
    local backend's pool spawns a process per worker)."""
    monkeypatch.setattr(
        sweep, "run_local", lambda payloads, _: ((i, run_trial(p)) for i, p in enumerate(payloads))
    )

    def run(out: Path, **fields: Any) -> SweepResult:
        spec = {"recipe": "toy", "env": "toy", "seeds": [0], "out": out, **fields}
        given = {o.partition("=")[0] for o in spec.get("overrides", [])}
        tiny = [o for o in SWEEP_TINY if o.partition("=")[0] not in given]
        spec["overrides"] = [*tiny, *spec.get("overrides", [])]
        return run_sweep(SweepSpec(**spec), echo=lambda _: None)

    return run


def test_a_sweep_rerun_with_an_added_override_is_refused_before_any_trial(tmp_path, sweep_here):
    out = tmp_path / "sweep"
    assert not sweep_here(out, grid={"lr": [0.05]}).failed
    trial = out / "trials" / "lr=0.05__seed=0"
    before = {**_run_files(trial), **_files(out / "summary")}
    manifest = (out / "sweep.json").read_bytes()
    with pytest.raises(ValueError, match="trial lr=0.05__seed=0: cannot resume with sigma changed"):
        sweep_here(out, grid={"lr": [0.05]}, overrides=["sigma=0.1"])
    assert {**_run_files(trial), **_files(out / "summary")} == before
    assert (out / "sweep.json").read_bytes() == manifest
    # a longer budget resumes the finished trial
    result = sweep_here(out, grid={"lr": [0.05]}, overrides=["total_frames=30"])
    assert result.records["lr=0.05__seed=0"]["resumed"] and not result.failed


@pytest.mark.parametrize("where", ["override", "config file"])
def test_a_sweep_takes_progress_false_and_a_config_file_with_progress(tmp_path, sweep_here, where):
    fields: dict[str, Any] = {"overrides": ["progress=false"]}
    if where == "config file":
        config = tmp_path / "config.yaml"
        config.write_text("progress: true\nlr: 0.1\n")
        fields = {"config_file": str(config)}
    result = sweep_here(tmp_path / "sweep", **fields)
    assert not result.failed and result.records["seed=0"]["state"] == "done"


def test_a_sweep_refuses_progress_true_naming_it(tmp_path, toy_recipe):
    with pytest.raises(ValueError, match="progress must be false or unset in a sweep"):
        SweepSpec(recipe="toy", env="toy", seeds=[0], out=tmp_path, overrides=["progress=true"])


def test_a_sweep_rerun_with_another_grid_keeps_the_earlier_trials(tmp_path, sweep_here):
    out = tmp_path / "sweep"
    assert not sweep_here(out, grid={"lr": [0.05, 0.2]}).failed
    result = sweep_here(out, grid={"sigma": [0.1]})
    assert not result.failed and [t.id for t in result.trials] == ["sigma=0.1__seed=0"]
    manifest = json.loads((out / "sweep.json").read_text())
    states = {t["id"]: (t["state"], t["ran"]) for t in manifest["trials"]}
    assert states == {
        "sigma=0.1__seed=0": ("done", True),
        "lr=0.05__seed=0": ("done", False),
        "lr=0.2__seed=0": ("done", False),
    }
    summary = json.loads((out / "summary" / "summary.json").read_text())
    assert sorted(summary) == [
        "toy sigma=0.1 lr=0.05",
        "toy sigma=0.3 lr=0.05",
        "toy sigma=0.3 lr=0.2",
    ]


def test_a_bogus_x_is_refused_before_any_trial(tmp_path, sweep_here):
    out = tmp_path / "sweep"
    with pytest.raises(ValueError, match="x must be one of .*'frames'.*got 'bogus'"):
        sweep_here(out, x="bogus")
    assert not out.exists()


@pytest.mark.parametrize(
    "fields, match",
    [
        ({"x": "bogus"}, "x must be 'auto', 'frames' or a metric of every finished trial"),
        ({"metrics": ["return", "nosuch"]}, r"metrics must be metrics of every finished trial"),
    ],
)
def test_bad_summary_options_are_refused_before_a_rerun_runs_a_trial(
    tmp_path, sweep_here, fields, match
):
    out = tmp_path / "sweep"
    assert not sweep_here(out, grid={"lr": [0.05]}).failed
    manifest = (out / "sweep.json").read_bytes()
    with pytest.raises(ValueError, match=match):
        sweep_here(out, grid={"lr": [0.05, 0.2]}, **fields)
    assert not (out / "trials" / "lr=0.2__seed=0").exists()
    assert (out / "sweep.json").read_bytes() == manifest


# ------------------------------------------------ no silent training on NaN, no empty run
class NaNToyEnv(ToyAgentsEnv):
    """The toy scenario whose ``entry`` (``"observation"``, ``"reward"`` or ``"position"``)
    turns NaN for one agent from its ``after``-th step on (counted over every episode)."""

    def __init__(self, entry: str = "reward", after: int = 15, **kwargs: Any) -> None:
        super().__init__(**kwargs)
        self.entry, self.after, self.steps = entry, after, 0

    def _step(self, td: TensorDict) -> TensorDict:
        out = super()._step(td)
        self.steps += 1
        if self.steps > self.after:
            out["agents", self.entry][0] = float("nan")
        return out


@pytest.mark.parametrize("entry", ["observation", "reward", "position"])
def test_a_model_free_run_refuses_non_finite_data(tmp_path, toy_scenario, monkeypatch, entry):
    monkeypatch.setattr(registry, "_SCENARIOS", dict(registry._SCENARIOS))
    register_env("nantoy", NaNToyEnv)
    config = ToyConfig(
        env="nantoy",
        env_config={"entry": entry},
        total_frames=40,
        eval_interval=10,
        checkpoint_interval=10,
    )
    exp = ToyLearner(config, tmp_path / "run")
    with pytest.raises(ValueError) as err:
        exp.train()
    message = str(err.value)
    assert "\n" not in message and "must be finite" in message
    assert f"agents/{entry} of the batch toy collected after frame 10" in message
    results = (tmp_path / "run" / "results.json").read_text()
    assert exp.frames == 10 and '"frames": 10' in results and "NaN" not in results
    assert [p.name for p in (tmp_path / "run" / "checkpoints").glob("*.pt")] == [
        "ckpt_000000000010.pt"
    ]


def test_an_update_interval_beyond_the_budget_is_refused_naming_it():
    from mapets_rl.recipes.maddpg import MADDPGConfig

    fields = dict(total_frames=400, frames_per_batch=100, batch_size=100)
    with pytest.raises(ValueError, match="update_interval must be a number of frames with a"):
        MADDPGConfig(**fields, update_interval=10**9)
    # rounds at frames 150 and 300 come before the buffer holds 350 transitions (at 400)
    with pytest.raises(ValueError, match="between frame 301 and frame 400"):
        MADDPGConfig(**{**fields, "batch_size": 350}, update_interval=150)
    assert MADDPGConfig(**fields, update_interval=400).update_interval == 400
    assert MADDPGConfig(**{**fields, "batch_size": 350}, update_interval=200).batch_size == 350


# ----------------------------------------------------- SIGTERM: checkpoint, stop, resume
def _toy_config(checkpoint_interval: int) -> ToyConfig:
    return ToyConfig(
        total_frames=40, eval_interval=30, checkpoint_interval=checkpoint_interval, logger="csv"
    )


class UnhandledSigterm(Exception):
    """A SIGTERM that no training loop handled (the test's own handler caught it)."""


@pytest.fixture
def sigterm_handler() -> Any:
    """A SIGTERM handler raising :class:`UnhandledSigterm` for the test (instead of the
    default, which would end the test process), put back after it."""

    def handle(signum: int, frame: Any) -> None:
        raise UnhandledSigterm(signum)

    previous = signal.signal(signal.SIGTERM, handle)
    yield handle
    signal.signal(signal.SIGTERM, previous)


class SigtermToy(ToyLearner):
    """The toy learner, sending this process SIGTERM in its training step once it has
    ``sigterm_at`` frames (as ``timeout`` or Slurm would, while a batch trains)."""

    sigterm_at: int | None = None

    def train_step(self, batch: TensorDict) -> dict[str, float]:
        if self.frames == self.sigterm_at:
            os.kill(os.getpid(), signal.SIGTERM)
        return super().train_step(batch)


def test_a_sigterm_stops_a_run_with_a_checkpoint_and_it_resumes_identically(
    tmp_path, toy_scenario, sigterm_handler
):
    full = ToyLearner(_toy_config(10), tmp_path / "full")
    full.train()
    run = tmp_path / "run"
    exp = SigtermToy(_toy_config(10), run)
    exp.sigterm_at = 20
    with pytest.raises(RunStopped, match=r"stopped by SIGTERM at frame 20: .* resume "):
        exp.train()
    assert signal.getsignal(signal.SIGTERM) is sigterm_handler  # put back
    assert list_checkpoints(run)[-1].name == "ckpt_000000000020.pt" and exp.frames == 20
    assert exp.results.evaluations == []  # no evaluation the uninterrupted run does not make
    resumed = ToyLearner.from_run_dir(run)
    assert resumed.train() == full.results.evaluations
    assert [e["frames"] for e in full.results.evaluations] == [30, 40]
    for part in ("actor", "optim"):  # (the buffer's storage past its 40 entries is not set)
        _assert_equal(
            load_checkpoint(list_checkpoints(run)[-1])["components"][part],
            load_checkpoint(list_checkpoints(tmp_path / "full")[-1])["components"][part],
        )


def test_a_sigterm_between_checkpoints_writes_one_more(tmp_path, toy_scenario, sigterm_handler):
    run = tmp_path / "run"
    exp = SigtermToy(_toy_config(20), run)
    exp.sigterm_at = 10
    with pytest.raises(RunStopped, match="at frame 10"):
        exp.train()
    assert [p.name for p in list_checkpoints(run)] == ["ckpt_000000000010.pt"]
    resumed = ToyLearner.from_run_dir(run)
    assert [e["frames"] for e in resumed.train()] == [30, 40]


def test_the_cli_says_a_sigterm_stop_in_one_line(
    tmp_path, toy_recipe, capsys, monkeypatch, sigterm_handler
):
    train_step = ToyLearner.train_step

    def train_step_then_sigterm(self: ToyLearner, batch: Any) -> dict[str, float]:
        if self.frames == 20:
            os.kill(os.getpid(), signal.SIGTERM)
        return train_step(self, batch)

    monkeypatch.setattr(ToyLearner, "train_step", train_step_then_sigterm)
    run = tmp_path / "run"
    argv = ["train", "toy", "--env", "toy", "--run-dir", str(run), "total_frames=40"]
    code, _, err = run_cli([*argv, "checkpoint_interval=10"], capsys)
    assert code == 128 + signal.SIGTERM and err.count("\n") == 1, err
    assert "stopped by SIGTERM at frame 20" in err and f"mapets-rl resume {run}" in err
    monkeypatch.setattr(ToyLearner, "train_step", train_step)
    code, out, err = run_cli(["resume", str(run)], capsys)
    assert code == 0 and '"frames": 40' in out, err


# ------------------------------------------------------- memory: the process's own cgroup
GIB = 2**30


@pytest.mark.parametrize("version", ["v2", "v1"])
def test_the_memory_bound_reads_the_process_own_cgroup(tmp_path, version):
    from mapets_rl.memory import _cgroup_left

    proc = tmp_path / "proc_cgroup"
    root = tmp_path / "sys"
    if version == "v2":
        proc.write_text("0::/slurm/job7\n")
        own, parent = root / "slurm" / "job7", root / "slurm"
        limit, usage = "memory.max", "memory.current"
    else:
        proc.write_text("7:cpuset:/\n4:cpuacct,memory:/docker/abc\n0::/\n")
        own, parent = root / "memory" / "docker" / "abc", root / "memory" / "docker"
        limit, usage = "memory.limit_in_bytes", "memory.usage_in_bytes"
    own.mkdir(parents=True)
    (own / limit).write_text(f"{3 * GIB // 2}\n")  # a 1.5 GiB job; the root has no limit
    (own / usage).write_text(f"{GIB // 2}\n")
    assert _cgroup_left(root, proc) == GIB
    (parent / limit).write_text(f"{GIB // 4}\n")  # a tighter limit above it counts too
    assert _cgroup_left(root, proc) == GIB // 4
    (own / usage).write_text(f"{3 * GIB // 2}\n")  # at its limit: nothing left
    assert _cgroup_left(root, proc) == 0
    cache = "inactive_file" if version == "v2" else "total_inactive_file"
    (own / "memory.stat").write_text(f"anon 5\n{cache} {GIB // 8}\n")  # but reclaimable cache
    assert _cgroup_left(root, proc) == GIB // 8


def test_a_cgroup_at_its_limit_leaves_no_memory(monkeypatch):
    from mapets_rl import memory

    monkeypatch.setattr(memory, "_cgroup_left", lambda: 0)
    assert memory.available_memory("cpu") == 0


# ------------------------------------------------- compare names a run's bad metric value
@pytest.mark.parametrize("value", [float("nan"), "x", None])
def test_compare_names_the_run_and_metric_of_a_value_that_is_no_number(
    tmp_path, csv_toy_run, toy_scenario, value
):
    from mapets_rl.app.comparison import compare

    other = tmp_path / "other"
    ToyLearner(ToyConfig(total_frames=20, seed=1), other).train()
    data = json.loads((csv_toy_run / "results.json").read_text())
    data["evaluations"][0]["metrics"]["return"] = value
    (csv_toy_run / "results.json").write_text(json.dumps(data))
    with pytest.raises(ValueError, match=r"run_dir '.*run': metric 'return' at frames 20 is "):
        compare([csv_toy_run, other], tmp_path / "out")


# ------------------------------------------- a full disk before the first checkpoint, told
def test_a_full_disk_at_the_first_checkpoint_says_none_is_kept(
    tmp_path, toy_recipe, capsys, monkeypatch
):
    real_fsync = os.fsync

    def disk_full(fd: int) -> None:
        if os.readlink(f"/proc/self/fd/{fd}").endswith(".pt"):
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        real_fsync(fd)

    monkeypatch.setattr(os, "fsync", disk_full)
    run = tmp_path / "run"
    argv = ["train", "toy", "--env", "toy", "--run-dir", str(run), "total_frames=20"]
    code, _, err = run_cli(argv, capsys)
    assert code == 2 and err.count("\n") == 1, err
    assert "No space left on device" in err and "before its first checkpoint" in err
    assert "earlier checkpoints are kept" not in err


# ------------------------------------------------ which program simulated the run, recorded
def test_the_simulator_program_of_the_batched_freeway_is_told():
    from torchrl.envs import StepCounter

    from mapets_rl.envs import make_env

    batched = make_env("freeway", backend="torch", kernel="torch", num_envs=2)
    assert runner.simulator_program(batched) == "torch"
    assert runner.simulator_program(batched.append_transform(StepCounter())) == "torch"
    assert runner.simulator_program(ToyAgentsEnv()) is None


def test_a_resume_on_another_simulator_is_refused(tmp_path, toy_scenario, monkeypatch):
    monkeypatch.setattr(runner, "simulator_program", lambda env: "native")
    run = tmp_path / "run"
    ToyLearner(ToyConfig(total_frames=20), run).train()
    assert json.loads((run / "run.json").read_text())["simulator"] == "native"
    assert json.loads((run / "results.json").read_text())["simulator"] == "native"
    ToyLearner.from_run_dir(run, ["total_frames=30"]).close()  # the same simulator: fine
    monkeypatch.setattr(runner, "simulator_program", lambda env: "torch")
    before = _run_files(run)
    with pytest.raises(ValueError, match="simulated by the fused C\\+\\+ kernel .* torch program"):
        ToyLearner.from_run_dir(run, ["total_frames=40"])
    assert _run_files(run) == before


def test_compare_groups_runs_of_different_simulators_apart(tmp_path, toy_scenario, monkeypatch):
    from mapets_rl.app.comparison import compare

    runs = []
    for seed, simulator in enumerate(["native", "torch"]):
        monkeypatch.setattr(runner, "simulator_program", lambda env, s=simulator: s)
        runs.append(tmp_path / simulator)
        ToyLearner(ToyConfig(total_frames=20, seed=seed), runs[-1]).train()
    out = compare(runs, tmp_path / "out")
    summary = json.loads(out["summary"].read_text())
    assert sorted(summary) == ["toy (native simulator)", "toy (torch simulator)"]


class IdleToy(ToyLearner):
    """The toy learner whose training step stores the batch and never updates (as a replay
    recipe whose budget ends before its warm-up)."""

    def train_step(self, batch: TensorDict) -> dict[str, float]:
        self.buffer.extend(batch.reshape(-1).select(("agents", "observation")))
        return {}


def test_a_run_that_made_no_update_says_so(tmp_path, toy_scenario, caplog):
    with caplog.at_level("WARNING", logger="mapets_rl.experiment.runner"):
        ToyLearner(ToyConfig(total_frames=20), tmp_path / "trained").train()
        assert not caplog.records
        IdleToy(ToyConfig(total_frames=20), tmp_path / "idle").train()
    [record] = caplog.records
    assert "toy: the run made no training update" in record.getMessage()
    assert "2 batches (20 frames)" in record.getMessage()


def test_a_second_sweep_into_a_busy_out_is_refused_naming_the_holder(tmp_path, sweep_here):
    out = tmp_path / "sweep"
    out.mkdir()
    with RunDirLock.acquire(out, "out"):  # a first sweep still running
        with pytest.raises(ValueError, match=r"out '.*sweep' is in use by another writer \(pid"):
            sweep_here(out)
    assert not (out / "trials").exists() and not (out / "sweep.json").exists()
    assert not sweep_here(out).failed  # once it is done, the sweep runs


# ---------------------------------------------------- a run that fails to start leaves nothing
class RefusingToy(ToyLearner):
    """The toy learner refusing its scenario once the base class has made the run directory
    (as a recipe refuses categorical actions while it builds its modules)."""

    def __init__(self, config: ToyConfig, run_dir: Any = None) -> None:
        super().__init__(config, run_dir)
        raise ValueError("env action ('agents', 'action') must be a Bounded continuous ...")


def test_a_new_run_that_fails_to_start_leaves_no_half_made_run_dir(tmp_path, toy_scenario):
    with pytest.raises(ValueError, match="Bounded continuous"):
        RefusingToy(ToyConfig(total_frames=20), tmp_path / "new")
    assert not (tmp_path / "new").exists()
    given = tmp_path / "given"  # a directory the user made is left (with what the run wrote)
    given.mkdir()
    with pytest.raises(ValueError, match="Bounded continuous"):
        RefusingToy(ToyConfig(total_frames=20), given)
    assert given.is_dir()
    ToyLearner(ToyConfig(total_frames=20), given).train()  # and it can be used


# ------------------------------------- the batched freeway's arguments, checked before building
def _torch_freeway(**kwargs: Any):
    from mapets_rl.envs import make_env

    return make_env("freeway", backend="torch", kernel="torch", **{"num_envs": 2, **kwargs})


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"device": "meta"}, "device must be 'cpu', 'cuda', 'cuda:N' or 'mps', got 'meta'"),
        ({"device": "bogus"}, "device must be 'cpu', 'cuda', 'cuda:N' or 'mps', got 'bogus'"),
        ({"device": "mps"}, "device='mps': this machine has no MPS device"),
        ({"seed": -1}, r"seed must be None or an integer in \[0, 2\*\*62 - 1\], got -1"),
        ({"seed": 2**64}, r"seed must be None or an integer in \[0, 2\*\*62 - 1\], got 1844"),
        ({"seed": True}, r"seed must be None or an integer in \[0, 2\*\*62 - 1\], got True"),
        ({"categorical_actions": "no"}, "categorical_actions must be True or False, got 'no'"),
        (
            {"simulation_frequency": 10**7},
            r"simulation_frequency must be a multiple of policy_frequency=1 in \[1, 1000\] \[Hz\]",
        ),
        ({"shield_passes": 3}, "shield_passes=3 needs shield=True"),
        ({"shield_horizon": 5}, "shield_horizon=5 needs shield=True"),
    ],
)
def test_the_batched_freeway_refuses_a_bad_argument_naming_it(kwargs, message):
    if kwargs.get("device") == "mps" and torch.backends.mps.is_available():
        pytest.skip("this machine has an MPS device")
    with pytest.raises(ValueError, match=message) as err:
        _torch_freeway(**kwargs)
    assert "\n" not in str(err.value)


def test_a_gpu_the_machine_lacks_is_refused_naming_device():
    from mapets_rl.envs import FreewayEnv, wrap_pettingzoo
    from mapets_rl.envs.torch_freeway.env import TorchFreewayEnv

    if torch.cuda.is_available():
        pytest.skip("this machine has a GPU")
    message = r"device='cuda:0': no such CUDA device here \(0 GPUs\)"
    with pytest.raises(ValueError, match=message):
        TorchFreewayEnv(FreewayEnv, num_envs=2, device="cuda:0", kernel="torch")
    with pytest.raises(ValueError, match=message):
        wrap_pettingzoo(_Wrapped.line()(), position="xy", device="cuda:0")


def test_the_batched_freeway_takes_a_numpy_road_count_and_seed():
    env = _torch_freeway(num_envs=np.int64(3), seed=np.int64(5))
    assert env.batch_size == (3,)
    reference = _torch_freeway(num_envs=3, seed=5)
    assert torch.equal(
        env.reset()["agents", "observation"], reference.reset()["agents", "observation"]
    )


def test_a_bool_one_hot_action_steps_as_its_integer_one():
    runs = []
    for dtype in (torch.bool, torch.int64):
        env = _torch_freeway(seed=3)
        td = env.reset()
        action = torch.zeros(2, env.sim.n_cavs, 4, dtype=dtype)
        action[..., 1] = 1  # change left, every CAV
        td["agents", "action"] = action
        runs.append(env.step(td)["next", "agents", "observation"])
    assert torch.equal(*runs)


def test_a_categorical_action_of_floats_is_refused():
    env = _torch_freeway(categorical_actions=True)
    td = env.reset()
    td["agents", "action"] = torch.full((2, env.sim.n_cavs), 1.5)
    with pytest.raises(ValueError, match=r"must hold integer indices .* got dtype torch.float32"):
        env.step(td)


@pytest.fixture(scope="module")
def freeway_sim():
    """The simulator of a 2-road freeway (the torch program)."""
    return _torch_freeway(seed=0).sim


@pytest.mark.parametrize(
    ("call", "message"),
    [
        (lambda sim: sim.restore({"a": 1}), "snapshot must be a TensorDict taken with snapshot"),
        (lambda sim: sim.branch(0, 2.5), r"copies must be an integer >= 1, got 2.5"),
        (lambda sim: sim.branch(0, True), r"copies must be an integer >= 1, got True"),
        (lambda sim: sim.branch(0.0, 2), r"road must be in \[0, 1\] \(an integer\), got 0.0"),
        (
            lambda sim: sim.branch(0, 10**9),
            r"copies=1000000000 roads need about .* GiB on cpu \(\d+ KiB each while they step\),"
            r" more than the .* GiB available: copies must be at most \d+",
        ),
        (
            lambda sim: sim.shield(torch.zeros(3, 1, dtype=torch.long)),
            r"action must be a tensor of the CAVs' decisions \[2, 30\], got \[3, 1\]",
        ),
        (
            lambda sim: sim.step(torch.full((2, 30), 9)),
            r"action must hold integer decisions in \[0, 3\] .* got values in \[9, 9\]",
        ),
        (
            lambda sim: sim.predicted_crashes(torch.full((2, 30), -3)),
            r"action must hold integer decisions in \[0, 3\] .* got values in \[-3, -3\]",
        ),
        (
            lambda sim: sim.step(torch.full((2, 30), 1.0)),
            r"action must hold integer decisions .* got dtype torch.float32",
        ),
        (
            lambda sim: sim.rollout_returns(lambda obs: obs[..., 0].long() * 0, gamma=True),
            r"gamma must be in \[0, 1\] \(a number\), got True",
        ),
    ],
)
def test_the_simulator_refuses_bad_arguments_naming_them(freeway_sim, call, message):
    before = freeway_sim.snapshot()
    with pytest.raises(ValueError, match=message) as err:
        call(freeway_sim)
    assert "\n" not in str(err.value)
    _assert_equal(freeway_sim.snapshot().to_dict(), before.to_dict())


# ------------------------------------------------ the batched freeway's roads must fit in memory
def test_the_memory_estimate_is_the_state_of_a_road_times_a_step_working_set():
    from mapets_rl.envs.torch_freeway import simulator

    for name, merge in (("freeway", False), ("freeway-merge", True)):
        sim = _torch_freeway().sim if not merge else _merge_sim()
        state = sum(t.numel() * t.element_size() for t in sim.state.values(True, True))
        assert simulator.road_bytes(sim.config, merge) * sim.n_roads == (
            simulator.STEP_WORKING_SET * state
        ), name


def _merge_sim():
    from mapets_rl.envs import make_env

    return make_env("freeway-merge", backend="torch", kernel="torch", num_envs=2).sim


@pytest.mark.parametrize("roads", [100_000, 2**63])
def test_roads_that_do_not_fit_in_memory_are_refused_in_one_line(monkeypatch, roads):
    from mapets_rl.envs.torch_freeway import simulator

    monkeypatch.setattr(simulator, "available_memory", lambda device: GIB)
    per_road = simulator.road_bytes(_torch_freeway().sim.config, merge=False)
    with pytest.raises(ValueError) as err:
        _torch_freeway(num_envs=roads)
    assert str(err.value).startswith(f"num_envs={roads} roads need about ")
    assert str(err.value).endswith(f"GiB available: num_envs must be at most {GIB // per_road}")
    assert "\n" not in str(err.value)
    _torch_freeway(num_envs=GIB // per_road // 1000)  # what fits is built


def test_a_run_whose_roads_do_not_fit_is_refused_before_its_run_dir(tmp_path, monkeypatch, capsys):
    from mapets_rl.envs.torch_freeway import simulator

    monkeypatch.setattr(simulator, "available_memory", lambda device: 2**20)  # one road fits
    run = tmp_path / "run"
    argv = ["train", "maddpg", "--env", "freeway", "--run-dir", str(run)]
    argv += ["env_config.backend=torch", "env_config.kernel=torch", "env_config.num_envs=64"]
    code, _, err = run_cli([*argv, "frames_per_batch=64", "total_frames=64"], capsys)
    assert code == 2 and err.count("\n") == 1, err
    assert "env_config.num_envs=64 roads need about" in err
    assert "env_config.num_envs must be at most 16" in err
    assert not run.exists()


def test_env_config_seed_is_refused_naming_the_run_seed(toy_scenario):
    from mapets_rl.config import ConfigError

    with pytest.raises(ConfigError, match=r"env_config.seed must be left out \(the run's seed "):
        ToyConfig(total_frames=20, env_config={"seed": 3})


# ----------------------------------- wrap_pettingzoo checks its device and the env's API, naming
class _Wrapped:
    """Variants of the wrapper tests' LineEnv, each breaking one part of PettingZoo's API."""

    @staticmethod
    def line():
        from tests.envs.test_pettingzoo_wrapper import LineEnv

        return LineEnv

    @classmethod
    def stepping(cls, change: Callable[[tuple], tuple]):
        class Broken(cls.line()):
            def step(self, actions):
                return change(super().step(actions))

        return Broken()

    @classmethod
    def with_method(cls, name: str, method: Callable):
        return type("Broken", (cls.line(),), {name: method})()


def _drop(part: int, agent: str) -> Callable[[tuple], tuple]:
    def change(out: tuple) -> tuple:
        out[part].pop(agent)
        return out

    return change


def _add_info_key(out: tuple) -> tuple:
    out[4]["a"]["extra"] = 1.0
    return out


def _reshape_observation(out: tuple) -> tuple:
    out[0]["b"] = np.zeros(3, dtype=np.float32)
    return out


def _stranger(out: tuple) -> tuple:
    values = (np.zeros(2, np.float32), 1.0, False, False, {"xy": np.zeros(2), "speed": 1.0})
    for part, value in zip(out, values, strict=True):
        part["zz"] = value
    return out


PETTINGZOO_CASES = {
    "a reward missing": (
        lambda: _Wrapped.stepping(_drop(1, "c")),
        "the env's step gives agent 'c' an observation but no entry in its rewards",
    ),
    "a truncation missing": (
        lambda: _Wrapped.stepping(_drop(3, "a")),
        "the env's step gives agent 'a' an observation but no entry in its truncations",
    ),
    "info keys changing": (
        lambda: _Wrapped.stepping(_add_info_key),
        r"the env's step gives agent 'a' the info keys \['extra', 'speed', 'xy'\], its first "
        r"reset gave \['speed', 'xy'\]",
    ),
    "an old-API reset": (
        lambda: _Wrapped.with_method(
            "reset", lambda self, seed=None, options=None: _Wrapped.line().reset(self)[0]
        ),
        r"the env's reset must return \(observations, infos\), two dicts .* got a dict",
    ),
    "a 3-tuple step": (
        lambda: _Wrapped.stepping(lambda out: out[:3]),
        r"the env's step must return \(observations, rewards, .* got a tuple of 3",
    ),
    "a Discrete observation space": (
        lambda: _Wrapped.with_method("observation_space", lambda self, a: spaces.Discrete(3)),
        r"observation_space\('a'\) must be a gymnasium Box .* got Discrete\(3\)",
    ),
    "a Dict observation space": (
        lambda: _Wrapped.with_method(
            "observation_space", lambda self, a: spaces.Dict({"x": spaces.Box(-1, 1, (2,))})
        ),
        r"observation_space\('a'\) must be a gymnasium Box .* got Dict\(",
    ),
    "a Tuple action space": (
        lambda: _Wrapped.with_method(
            "action_space", lambda self, a: spaces.Tuple((spaces.Discrete(2),) * 2)
        ),
        r"action_space\('a'\) must be a gymnasium Box or Discrete, got Tuple\(",
    ),
    "an observation unlike its space": (
        lambda: _Wrapped.stepping(_reshape_observation),
        r"the env's step gives agent 'b' an observation of shape \[3\], its observation_space "
        r"has \[2\]",
    ),
    "an agent not in possible_agents": (
        lambda: _Wrapped.stepping(_stranger),
        r"the env's step observes agent 'zz', which is not in possible_agents \['a', 'b', 'c'\]",
    ),
}


@pytest.mark.parametrize("case", list(PETTINGZOO_CASES))
def test_wrap_pettingzoo_refuses_an_env_off_the_api_naming_agent_and_key(case):
    from mapets_rl.envs import wrap_pettingzoo

    make, message = PETTINGZOO_CASES[case]
    with pytest.raises(ValueError, match=message) as err:
        wrap_pettingzoo(make(), position="xy").rollout(4)
    assert "\n" not in str(err.value)


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"device": "bogus"}, "device must be 'cpu', 'cuda', 'cuda:N' or 'mps', got 'bogus'"),
        ({"device": "meta"}, "device must be 'cpu', 'cuda', 'cuda:N' or 'mps', got 'meta'"),
        ({"seed": "x"}, r"seed must be None or an integer in \[0, 2\*\*62 - 1\], got 'x'"),
        ({"categorical_actions": "no"}, "categorical_actions must be True or False, got 'no'"),
    ],
)
def test_wrap_pettingzoo_refuses_a_bad_argument_naming_it(kwargs, message):
    from mapets_rl.envs import wrap_pettingzoo

    with pytest.raises(ValueError, match=message):
        wrap_pettingzoo(_Wrapped.line()(), position="xy", **kwargs)


# ------------------------------------------ SIGTERM to every process of a multi-process run
def _ignores_sigterm(pid: int) -> bool:
    """Whether process ``pid`` ignores SIGTERM (its ``SigIgn`` mask in ``/proc``)."""
    line = next(x for x in Path(f"/proc/{pid}/status").read_text().splitlines() if "SigIgn" in x)
    return bool(int(line.split()[1], 16) >> (signal.SIGTERM - 1) & 1)


def test_collector_workers_are_started_ignoring_sigterm(tmp_path, toy_scenario, monkeypatch):
    import subprocess

    started = []

    class Workers:
        """Stands for torchrl's MultiSyncCollector: starts a process as it would."""

        def __init__(self, *args: Any, **kwargs: Any) -> None:
            started.append(subprocess.Popen(["sleep", "30"]))

        def shutdown(self) -> None:
            started[-1].kill()

    monkeypatch.setattr(runner, "MultiSyncCollector", Workers)
    handler = signal.getsignal(signal.SIGTERM)
    learner = ToyLearner(ToyConfig(total_frames=20, collector_workers=2), tmp_path / "run")
    try:
        [worker] = started
        assert _ignores_sigterm(worker.pid)  # timeout / Slurm's SIGTERM is left to the run
        assert signal.getsignal(signal.SIGTERM) is handler  # the run's own handling unchanged
        unprotected = subprocess.Popen(["sleep", "30"])
        assert not _ignores_sigterm(unprotected.pid)
        unprotected.kill()
        unprotected.wait()
    finally:
        learner.collector.shutdown()
        learner.close()
        worker.wait()


@pytest.mark.parametrize(
    "key, reset",
    [
        ("_reset", torch.tensor([0.1, 0.0, 0.0])),
        ("_reset", torch.tensor([float("nan")] * 3)),
        ("_reset", torch.zeros(3, 2, dtype=torch.bool)),
        ("_reset", torch.tensor([1, 0, 0])),
        (("agents", "_reset"), torch.ones(3, 5, 1)),
    ],
)
def test_a_partial_reset_that_is_no_bool_mask_of_the_roads_is_refused(key, reset):
    """A ``_reset`` of another dtype or shape used to reset the wrong roads (or raise an
    IndexError): now one line naming the key, the shape wanted and what came."""
    from mapets_rl.envs import make_env

    env = make_env("freeway", backend="torch", num_envs=3, n_vehicles=5)
    td = env.reset()
    td[key] = reset
    with pytest.raises(ValueError, match=r"_reset'?\)? must be a bool tensor \[3"):
        env.reset(td)
    td[key] = torch.zeros((3, 5, 1) if key == ("agents", "_reset") else (3,), dtype=torch.bool)
    td[key][0] = True
    assert env.reset(td).batch_size == (3,)
