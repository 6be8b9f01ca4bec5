"""``mapets-rl sweep``: grids x seeds as run directories on the local process pool and on a
local Ray instance, resumption of a half-finished sweep, failed trials reported, and input
checked before any trial starts."""

from __future__ import annotations

import dataclasses
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from toy_recipe import ToyConfig, ToyLearner

from mapets_rl.app.sweep import SweepSpec, parse_grid, plan_trials, trial_id
from mapets_rl.experiment import (
    ConfigError,
    list_checkpoints,
    read_results,
    verified_checkpoints,
)
from mapets_rl.experiment.files import RunDirLock
from tests.cli_run import run_cli
from tests.sweep_helpers import SLOW_ENV

TINY = ["total_frames=20", "frames_per_batch=10", "eval_interval=10", "checkpoint_interval=10"]


@dataclasses.dataclass
class FailingToyConfig(ToyConfig):
    """The toy recipe's config plus ``fail``: raise in the first training step."""

    fail: bool = False


class FailingToy(ToyLearner):
    """The toy learner, failing on purpose when ``config.fail``."""

    name = "failtoy"
    Config = FailingToyConfig

    def train_step(self, batch):
        if self.config.fail:
            raise RuntimeError("deliberate failure of this trial")
        return super().train_step(batch)


@pytest.fixture
def failing_recipe(add_entry_point, toy_scenario) -> str:
    add_entry_point("mapets_rl.recipes", "failtoy", f"{__name__}:FailingToy")
    return "failtoy"


def _mtimes(out, trials) -> dict[str, int]:
    return {t: (out / "trials" / t / "results.json").stat().st_mtime_ns for t in trials}


def test_parse_grid_values_and_lists():
    grid = parse_grid(["comm.comm_range=0,50,12.5", "model.hidden=[[32,32],[64]]", "a=x,true"])
    assert grid == {
        "comm.comm_range": [0, 50, 12.5],
        "model.hidden": [[32, 32], [64]],
        "a": ["x", True],
    }
    assert trial_id({"comm.comm_range": 50.0, "model.hidden": [32, 32]}, 3) == (
        "comm.comm_range=50__model.hidden=32-32__seed=3"
    )
    for bad in (["x"], ["x="], ["a=1", "a=2"], ["a=1,,2"], ["a=[1"]):
        with pytest.raises(ConfigError, match="grid"):
            parse_grid(bad)


def test_bad_input_is_refused_before_any_trial(toy_recipe, tmp_path):
    out = tmp_path / "sweep"

    def spec(**kw):
        base = dict(recipe="toy", env="toy", seeds=[0], out=out, overrides=list(TINY))
        return SweepSpec(**{**base, **kw})

    with pytest.raises(ConfigError, match="unknown config key 'lrr'"):
        plan_trials(spec(grid={"lrr": [0.1]}))
    with pytest.raises(ConfigError, match="lr must be > 0"):
        plan_trials(spec(grid={"lr": [0.1, -1.0]}))
    with pytest.raises(ConfigError, match="seed"):
        spec(grid={"seed": [1, 2]})
    with pytest.raises(ConfigError, match="seeds must be without repeats"):
        spec(seeds=[1, 1])
    with pytest.raises(ConfigError, match="grid must be keys that no key=value"):
        spec(grid={"lr": [0.1]}, overrides=["lr=0.2"])
    with pytest.raises(ConfigError, match="gpus_per_trial must be 0 with the local backend"):
        spec(gpus_per_trial=1)
    with pytest.raises(ConfigError, match="env must be one of"):
        plan_trials(spec(env="nowhere"))
    with pytest.raises(ValueError, match="unknown recipe 'nope'"):
        plan_trials(spec(recipe="nope"))
    # a bad env_config key fails when the scenario is built, still before any trial
    with pytest.raises(TypeError, match="n_agentz"):
        plan_trials(spec(grid={"env_config.n_agentz": [2]}))
    assert not out.exists()


def test_cli_bad_grid_exits_2(toy_recipe, tmp_path, capsys):
    out = tmp_path / "sweep"
    code, _, err = run_cli(
        ["sweep", "toy", "--env", "toy", "--out", str(out), "--grid", "lr=0.1,-1", *TINY], capsys
    )
    assert code == 2
    assert err.startswith("mapets-rl: error: lr must be > 0, got -1")
    assert not out.exists()


def test_local_sweep_runs_grid_x_seeds_and_resumes(toy_recipe, tmp_path, capsys):
    """2 x 2 trials on the local pool; then a half-finished state is made (one trial loses
    its final checkpoint and its finished record, as if killed): the rerun resumes only it."""
    out = tmp_path / "sweep"
    argv = ["sweep", "toy", "--env", "toy", "--seeds", "0", "1", "--grid", "lr=0.05,0.2"]
    code, stdout, err = run_cli([*argv, *TINY, "--out", str(out)], capsys)
    assert code == 0, err
    manifest = json.loads((out / "sweep.json").read_text())
    ids = [t["id"] for t in manifest["trials"]]
    assert ids == ["lr=0.05__seed=0", "lr=0.05__seed=1", "lr=0.2__seed=0", "lr=0.2__seed=1"]
    assert all(t["state"] == "done" and t["ran"] for t in manifest["trials"])
    for t in manifest["trials"]:
        res = read_results(out / t["run_dir"])
        assert res["seed"] == t["seed"] and res["config"]["lr"] == t["values"]["lr"]
        assert [e["frames"] for e in res["evaluations"]] == [10, 20]
    summary = json.loads((out / "summary" / "summary.json").read_text())
    assert sorted(summary) == ["toy lr=0.05", "toy lr=0.2"]
    assert all(row["return"]["n"] == 2 for row in summary.values())
    assert (out / "summary" / "learning_curves.png").stat().st_size > 0
    assert "| toy lr=0.05 |" in stdout

    # half-finished: trial lr=0.2__seed=1 was killed after its checkpoint at frame 10
    victim = out / "trials" / "lr=0.2__seed=1"
    (victim / "checkpoints" / f"ckpt_{20:012d}.pt").unlink()
    record = json.loads((victim / "trial.json").read_text())
    (victim / "trial.json").write_text(json.dumps({**record, "state": "running"}))
    others = [i for i in ids if i != victim.name]
    before = _mtimes(out, others)
    code, _, err = run_cli([*argv, *TINY, "--out", str(out)], capsys)
    assert code == 0, err
    assert _mtimes(out, others) == before  # finished trials are not run again
    manifest = json.loads((out / "sweep.json").read_text())
    rec = {t["id"]: t for t in manifest["trials"]}
    assert all(not rec[i]["ran"] for i in others)
    assert rec[victim.name]["ran"] and rec[victim.name]["resumed"]
    assert rec[victim.name]["frames"] == 20
    assert [e["frames"] for e in read_results(victim)["evaluations"]] == [10, 20]


def test_failed_trial_is_reported_and_others_finish(failing_recipe, tmp_path, capsys):
    out = tmp_path / "sweep"
    argv = ["sweep", "failtoy", "--env", "toy", "--grid", "fail=false,true", "--out", str(out)]
    code, _, err = run_cli([*argv, *TINY], capsys)
    assert code == 1
    assert "1 of 2 trials failed: fail=true__seed=0" in err
    assert "deliberate failure of this trial" in err
    manifest = {t["id"]: t for t in json.loads((out / "sweep.json").read_text())["trials"]}
    assert manifest["fail=false__seed=0"]["state"] == "done"
    assert manifest["fail=true__seed=0"]["state"] == "failed"
    assert "RuntimeError: deliberate failure" in manifest["fail=true__seed=0"]["error"]
    tail = (out / "trials" / "fail=true__seed=0" / "error.txt").read_text()
    assert "Traceback" in tail and "train_step" in tail
    assert read_results(out / "trials" / "fail=false__seed=0")["evaluations"]
    assert (out / "summary" / "final_metrics.md").is_file()


def test_ray_sweep_of_the_communication_range(tmp_path, capsys):
    """The d ablation end to end on a local Ray instance: MA-PETS, d in {0, 100} x 2 seeds,
    tiny episodes; every trial a MA-PETS run directory, the summary grouped by d."""
    ray = pytest.importorskip("ray", reason="ray is not installed (pip install 'mapets-rl[ray]')")
    was_running = ray.is_initialized()  # a Ray of this process would be used as it is
    out = tmp_path / "d_sweep"
    code, stdout, err = run_cli(
        [
            "sweep",
            "mapets",
            "--env",
            "figure-eight",
            "--seeds",
            "0",
            "1",
            "--grid",
            "comm.comm_range=0,100",
            "--backend",
            "ray",
            "--out",
            str(out),
            "preset=cpu",
            "episodes=2",
            "env_config.n_cavs=3",
            "env_config.horizon=8",
            "planner.horizon=5",
            "planner.population=8",
            "planner.elites=2",
            "planner.particles=5",
            "model.epochs=2",
            "logger=none",
        ],
        capsys,
    )
    assert ray.is_initialized() == was_running  # it shut down only the instance it started
    assert code == 0, err
    manifest = json.loads((out / "sweep.json").read_text())
    assert manifest["backend"] == "ray"
    assert len(manifest["trials"]) == 4
    for t in manifest["trials"]:
        res = read_results(out / t["run_dir"])
        assert res["config"]["comm"]["comm_range"] == t["values"]["comm.comm_range"]
        assert [e["metrics"]["episode"] for e in res["train"]] == [1.0, 2.0]
        shared = res["train"][0]["metrics"]["transitions_shared"]
        assert shared == 0.0 if t["values"]["comm.comm_range"] == 0 else shared >= 0.0
    curves = json.loads((out / "summary" / "curves.json").read_text())
    assert curves["x"] == "episode"
    assert sorted(g["group"]["comm.comm_range"] for g in curves["groups"].values()) == [0, 100]
    assert "comm.comm_range=100" in stdout


# ------------------------------------------------------------- model-free collectors by config
COLLECTOR_RUN = {
    "env": "figure-eight",
    "env_config": {"n_cavs": 3, "n_hvs": 2, "horizon": 40},
    "total_frames": 80,
    "frames_per_batch": 40,
    "collector_workers": 2,
    "eval_interval": 0,
    "checkpoint_interval": 0,
    "progress": False,
    "logger": "none",
    "minibatch_size": 20,
    "epochs": 1,
}


def test_collector_field_is_validated_and_old_configs_get_auto():
    from mapets_rl.recipes.mappo import MAPPOConfig

    with pytest.raises(ConfigError, match="collector must be one of"):
        MAPPOConfig(collector="threads")
    with pytest.raises(ConfigError, match="collector_workers must be 1 with collector='single'"):
        MAPPOConfig(collector="single", collector_workers=2)
    old = {k: v for k, v in MAPPOConfig(collector_workers=2).to_dict().items() if k != "collector"}
    assert MAPPOConfig.upgrade_dict(old)["collector"] == "auto"


@pytest.mark.parametrize("kind", ["multi_sync", "ray"])
def test_model_free_recipe_collects_with_torchrl_collector(kind, tmp_path):
    """MAPPO trains with ``collector_workers`` environment copies gathered by torchrl's
    ``MultiSyncCollector`` (worker processes) or ``RayCollector`` (remote collectors on a local
    Ray instance): batches of the configured size, the budget reached, the policy moved."""
    if kind == "ray":
        pytest.importorskip("ray", reason="ray is not installed (pip install 'mapets-rl[ray]')")
    import torch
    from torchrl.collectors import MultiSyncCollector
    from torchrl.collectors.distributed import RayCollector

    from mapets_rl.recipes.mappo import MAPPO, MAPPOConfig

    exp = MAPPO(MAPPOConfig(**COLLECTOR_RUN, collector=kind), tmp_path)
    assert isinstance(exp.collector, MultiSyncCollector if kind == "multi_sync" else RayCollector)
    before = torch.cat([p.detach().flatten().clone() for p in exp.loss.parameters()])
    sizes = []
    step = exp.train_step

    def recording(batch):
        sizes.append(batch.numel())
        return step(batch)

    exp.train_step = recording
    evaluations = exp.train()
    assert sizes == [40, 40]
    assert evaluations[-1]["frames"] == 80
    assert torch.isfinite(torch.tensor(evaluations[-1]["metrics"]["safety"]))
    after = torch.cat([p.detach().flatten() for p in exp.loss.parameters()])
    assert not torch.equal(before, after)


def test_overrides_after_seeds_are_overrides(toy_recipe, tmp_path):
    from mapets_rl.app.cli import build_parser
    from mapets_rl.app.sweep import spec_from_args

    argv = ["sweep", "toy", "--env", "toy", "--seeds", "3", "1", "lr=0.1", "--out", str(tmp_path)]
    args, extra = build_parser().parse_known_args(argv)
    args.overrides += extra
    spec = spec_from_args(args)
    assert spec.seeds == [3, 1] and spec.overrides == ["lr=0.1"]
    args.seeds = ["1", "x"]
    with pytest.raises(ConfigError, match="seeds must be integers >= 0, got 'x'"):
        spec_from_args(args)


# --------------------------------------------------------------- a sweep killed with kill -9
_SWEEP_SCRIPT = """
import sys
sys.path[:0] = [{tests!r}, {extending!r}]
from importlib import metadata
_installed = metadata.entry_points
def _entry_points(**params):
    found = _installed(**params)
    if params.get("group") == "mapets_rl.recipes":
        slow = metadata.EntryPoint("slowtoy", "sweep_helpers:SlowToy", "mapets_rl.recipes")
        return metadata.EntryPoints([*found, slow])
    return found
metadata.entry_points = _entry_points
from mapets_rl.experiment import register_env
from toy_scenario import ToyAgentsEnv
register_env("toy", ToyAgentsEnv)
from mapets_rl.app.cli import main
sys.exit(main({argv!r}))
"""


def _alive(pid: int) -> bool:
    """Whether process ``pid`` exists and is not a zombie (via /proc, psutil-free)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return True  # no /proc: kill(pid, 0) succeeded
    return stat.rpartition(")")[2].split()[0] != "Z"


def _sweep_process(out: Path, slow: float, log: Path) -> subprocess.Popen:
    """``mapets-rl sweep slowtoy`` (2 trials) in a subprocess writing to ``log`` (not to pipes:
    an orphaned worker would keep them open)."""
    argv = ["sweep", "slowtoy", "--env", "toy", "--seeds", "0", "1", *TINY, "--out", str(out)]
    tests = Path(__file__).resolve().parents[1]
    script = _SWEEP_SCRIPT.format(
        tests=str(tests), extending=str(tests.parent / "examples" / "extending"), argv=argv
    )
    env = {**os.environ, "PYTHONPATH": str(tests.parent), SLOW_ENV: str(slow)}
    with open(log, "w") as fh:
        return subprocess.Popen(
            [sys.executable, "-c", script],
            cwd=tests.parent,
            env=env,
            stdout=fh,
            stderr=subprocess.STDOUT,
        )


@pytest.mark.skipif(not Path("/proc").is_dir(), reason="needs /proc to find the workers")
def test_killed_sweep_leaves_no_worker_and_a_rerun_finishes_every_trial(tmp_path):
    out = tmp_path / "sweep"
    log = tmp_path / "sweep.log"
    proc = _sweep_process(out, 4.0, log)  # a training step takes 4 s: trials run a while
    records = [out / "trials" / f"seed={seed}" / "trial.json" for seed in (0, 1)]
    workers: list[int] = []
    deadline = time.monotonic() + 120
    while not workers and time.monotonic() < deadline and proc.poll() is None:
        time.sleep(0.2)
        for path in records:
            try:
                record = json.loads(path.read_text())
            except (OSError, ValueError):
                continue
            if record.get("state") == "running":
                workers.append(int(record["pid"]))
    assert workers, f"no trial started: {log.read_text()}"
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    deadline = time.monotonic() + 3.0  # a trial would run on for 8 s
    while any(_alive(pid) for pid in workers) and time.monotonic() < deadline:
        time.sleep(0.1)
    orphans = [pid for pid in workers if _alive(pid)]
    for pid in orphans:  # do not leave them behind when the assertion fails
        os.kill(pid, signal.SIGKILL)
    assert not orphans, "pool workers outlived the killed sweep"
    assert {t["state"] for t in json.loads((out / "sweep.json").read_text())["trials"]} == {
        "pending"
    }
    rerun = _sweep_process(out, 0.0, log)
    assert rerun.wait(timeout=300) == 0, log.read_text()
    manifest = json.loads((out / "sweep.json").read_text())
    assert [t["state"] for t in manifest["trials"]] == ["done", "done"]
    for t in manifest["trials"]:
        run = out / t["run_dir"]
        assert [e["frames"] for e in read_results(run)["evaluations"]] == [10, 20]
        assert verified_checkpoints(run) == list_checkpoints(run)
        assert json.loads((run / "trial.json").read_text())["state"] == "done"


def test_a_trial_whose_run_dir_another_writer_holds_is_left_alone(toy_recipe, tmp_path, capsys):
    out = tmp_path / "sweep"
    argv = ["sweep", "toy", "--env", "toy", "--seeds", "0", "1", *TINY, "--out", str(out)]
    held = out / "trials" / "seed=1"
    held.mkdir(parents=True)
    (held / "trial.json").write_text('{"state": "running", "pid": 1}')
    with RunDirLock.acquire(held):  # e.g. a worker of a killed sweep, still running it
        before = {p.name: p.read_bytes() for p in held.iterdir()}
        code, _, err = run_cli([*argv], capsys)
        assert code == 1 and "in use by another writer" in err
        assert {p.name: p.read_bytes() for p in held.iterdir()} == before  # nothing written
        manifest = {t["id"]: t for t in json.loads((out / "sweep.json").read_text())["trials"]}
        assert manifest["seed=0"]["state"] == "done"
        assert manifest["seed=1"]["state"] == "failed"
    code, _, err = run_cli([*argv], capsys)  # the writer is gone: the re-run finishes it
    assert code == 0, err
    assert [e["frames"] for e in read_results(held)["evaluations"]] == [10, 20]


def test_an_unreachable_ray_address_is_one_line_and_bounded(
    tmp_path, monkeypatch, toy_recipe, capsys
):
    """RAY_ADDRESS naming no cluster: the sweep exits 2 with one line naming the address within
    the connect timeout, instead of Ray's minutes of retries and its own process exit."""
    pytest.importorskip("ray", reason="ray is not installed (pip install 'mapets-rl[ray]')")
    import mapets_rl.ray_runtime as ray_runtime

    monkeypatch.setattr(ray_runtime, "RAY_CONNECT_TIMEOUT_S", 3)
    monkeypatch.setenv("RAY_ADDRESS", "127.0.0.1:1")
    start = time.monotonic()
    code, _, err = run_cli(
        ["sweep", "toy", "--env", "toy", "--seeds", "0", "--backend", "ray"]
        + ["--out", str(tmp_path / "s"), *TINY],
        capsys,
    )
    assert code == 2 and err.count("\n") == 1, err
    assert "no Ray cluster answered at '127.0.0.1:1' within 3 s" in err
    assert time.monotonic() - start < 60
