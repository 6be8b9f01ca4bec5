"""Issue 34, security and data loss: no code from a shared torch.compile cache, nothing written,
truncated or deleted outside the run directory, no foreign directory overwritten, no run
directory outside ``runs/`` by a scenario's name, nothing imported from the working directory.

Each test fails on the code before the fix (the foreign-owner cases need root, to make a file
of another user; they are skipped otherwise)."""

from __future__ import annotations

import json
import os
import pickle
import shutil
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest
from toy_recipe import ToyConfig, ToyLearner

from mapets_rl import _compile_cache
from mapets_rl._compile_cache import CACHE_ENV, HEADERS_ENV, prepare_compile_cache
from mapets_rl.app.plugins import load_recipe
from mapets_rl.experiment import checkpoint
from mapets_rl.experiment.files import LOCK_FILE, RunDirLock, check_run_subdirs
from mapets_rl.experiment.runner import default_run_dir
from mapets_rl.planning import compiled

ROOT = Path(__file__).resolve().parents[1]
OTHER_UID = 54321
needs_root = pytest.mark.skipif(os.geteuid() != 0, reason="a file of another user needs root")
needs_compiler = pytest.mark.skipif(
    compiled.compiler_unavailable() is not None, reason="no C++ compiler for inductor"
)


def _env(**extra: str) -> dict[str, str]:
    """The environment of a child process that imports this checkout of the project."""
    env = {k: v for k, v in os.environ.items() if k not in (CACHE_ENV, HEADERS_ENV)}
    env["PYTHONPATH"] = os.pathsep.join([str(ROOT), env.get("PYTHONPATH", "")]).rstrip(os.pathsep)
    env.update(extra)
    return env


def _cli(args: list[str], cwd: Path, **extra: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "mapets_rl.app.cli", *args],
        cwd=cwd,
        env=_env(**extra),
        capture_output=True,
        text=True,
        timeout=300,
    )


# ------------------------------------------------------------------ torch.compile's cache
@pytest.fixture
def fresh_choice(monkeypatch) -> None:
    """Forget the cache directory chosen earlier in this process."""
    monkeypatch.setattr(_compile_cache, "_chosen", None)


def test_the_default_compile_cache_is_private_to_the_user(tmp_path, fresh_choice):
    env = {"XDG_CACHE_HOME": str(tmp_path / "xdg")}
    chosen = prepare_compile_cache(env)
    assert chosen == str(tmp_path / "xdg" / "mapets_rl" / "torchinductor")
    assert env[CACHE_ENV] == chosen and env[HEADERS_ENV] == "0"
    st = os.stat(chosen)
    assert st.st_uid == os.geteuid() and st.st_mode & 0o777 == 0o700
    assert prepare_compile_cache(env) == chosen  # a second call keeps it


def test_inductors_own_temp_default_counts_as_unset(tmp_path, fresh_choice):
    """Importing torch first writes $TMPDIR/torchinductor_<user> into the variable."""
    env = {CACHE_ENV: _compile_cache._inductor_default(), "XDG_CACHE_HOME": str(tmp_path)}
    assert prepare_compile_cache(env) == str(tmp_path / "mapets_rl" / "torchinductor")


def test_an_unusable_default_falls_back_to_a_private_temp_dir(tmp_path, fresh_choice):
    (tmp_path / "file").write_text("")
    env = {"XDG_CACHE_HOME": str(tmp_path / "file")}
    chosen = prepare_compile_cache(env)
    assert not chosen.startswith(str(tmp_path)) and os.stat(chosen).st_mode & 0o777 == 0o700


@pytest.mark.parametrize("case", ["file", "under a file", "world-writable", "group-writable"])
def test_a_bad_user_cache_dir_is_refused_naming_the_variable(tmp_path, fresh_choice, case):
    target = tmp_path / "cache"
    if case in ("file", "under a file"):
        target.write_text("")
        if case == "under a file":
            target = target / "sub"
    else:
        target.mkdir()
        target.chmod(0o777 if case == "world-writable" else 0o770)
    with pytest.raises(ValueError, match=rf"^{CACHE_ENV}=.* cannot be torch.compile's cache"):
        prepare_compile_cache({CACHE_ENV: str(target)})


@needs_root
def test_a_cache_dir_of_another_user_is_refused(tmp_path, fresh_choice):
    target = tmp_path / "theirs"
    target.mkdir(mode=0o700)
    os.chown(target, OTHER_UID, -1)
    with pytest.raises(ValueError, match="owned by another user"):
        prepare_compile_cache({CACHE_ENV: str(target)})


def test_a_user_cache_dir_is_created_private(tmp_path, fresh_choice):
    target = tmp_path / "a" / "b"
    assert prepare_compile_cache({CACHE_ENV: str(target)}) == str(target)
    assert target.stat().st_mode & 0o777 == 0o700


@pytest.mark.parametrize("case", ["file", "uncreatable"])
def test_the_cli_refuses_a_bad_cache_dir_in_one_line(tmp_path, case):
    """It used to be a FileExistsError / FileNotFoundError traceback at `import tensordict`."""
    (tmp_path / "file").write_text("")
    value = tmp_path / "file" if case == "file" else tmp_path / "file" / "sub"
    out = _cli(["train", "mapets", "--env", "figure-eight"], tmp_path, **{CACHE_ENV: str(value)})
    assert out.returncode == 2, out.stderr
    assert out.stderr.startswith(f"mapets-rl: error: {CACHE_ENV}=")
    assert "Traceback" not in out.stderr and len(out.stderr.splitlines()) == 1


_STEP_SCRIPT = textwrap.dedent(
    """
    import torch  # before the project: inductor has already chosen $TMPDIR/torchinductor_<user>

    from mapets_rl.envs.figure_eight import FigureEightPlannerReward
    from mapets_rl.models import ProbabilisticEnsemble
    from mapets_rl.planning.compiled import CompiledStep

    torch.manual_seed(0)
    model = ProbabilisticEnsemble(10, 1, 2, 2, (8,))
    rows = 4
    args = (
        model, torch.rand(2, rows, 10), torch.rand(2, rows, 1), torch.randn(2, 1, 10), None,
        torch.zeros(2, rows), torch.ones(2, rows, dtype=torch.bool),
        torch.zeros(2, rows, dtype=torch.long), FigureEightPlannerReward().reward,
        FigureEightPlannerReward().collision,
        "ts_inf", torch.float32,
    )
    step = CompiledStep()
    with torch.no_grad():
        step(*args)
    print(step.fallback_reason)
    """
)


class _Marker:
    """Unpickling it creates the file ``path``: stands for any code a planted pickle runs."""

    def __init__(self, path: str) -> None:
        self.path = path

    def __reduce__(self):
        return (open, (self.path, "w"))


@needs_root
@needs_compiler
def test_a_pickle_planted_in_the_shared_inductor_cache_is_never_loaded(tmp_path):
    """Another user pre-creates $TMPDIR/torchinductor_<user> (mode 0777) and plants a pickle
    under the key of the compiled planner step (copied from a cache the same step filled);
    the next compiling process neither loads it nor writes anything there."""
    script = tmp_path / "step.py"
    script.write_text(_STEP_SCRIPT)
    shared = tmp_path / "shared"
    shared.mkdir()

    def run(**env: str) -> str:
        """The compiled step in a new process: why it fell back to eager, or "None"."""
        done = subprocess.run(
            [sys.executable, str(script)],
            env=_env(TMPDIR=str(shared), **env),
            capture_output=True,
            text=True,
            timeout=600,
        )
        assert done.returncode == 0, done.stderr[-2000:]
        return done.stdout.strip()

    filled = tmp_path / "filled"
    assert run(**{CACHE_ENV: str(filled)}) == "None"
    entries = [p for p in (filled / "fxgraph").rglob("*") if p.is_file()]
    assert entries, "the first run cached no compiled graph"
    planted = shared / Path(_compile_cache._inductor_default()).name
    marker = tmp_path / "marker"
    for entry in entries:
        target = planted / entry.relative_to(filled)
        target.parent.mkdir(parents=True, exist_ok=True)
        target.write_bytes(pickle.dumps(_Marker(str(marker))))
    for path in [planted, *planted.rglob("*")]:
        os.chown(path, OTHER_UID, -1)
        path.chmod(0o777)
    before = sorted(p.relative_to(planted) for p in planted.rglob("*"))

    fallback = run(XDG_CACHE_HOME=str(tmp_path / "fresh"))
    assert not marker.exists(), "a planted pickle was loaded"
    assert fallback == "None"
    assert sorted(p.relative_to(planted) for p in planted.rglob("*")) == before
    assert any((tmp_path / "fresh" / "mapets_rl" / "torchinductor" / "fxgraph").rglob("*"))


# ------------------------------------------------------------------------ the .lock file
def _victim(tmp_path: Path) -> Path:
    victim = tmp_path / "victim.txt"
    victim.write_text("precious\n")
    return victim


def test_a_symlinked_lock_is_refused_and_its_target_kept(tmp_path):
    run_dir = tmp_path / "run"
    run_dir.mkdir()
    victim = _victim(tmp_path)
    (run_dir / LOCK_FILE).symlink_to(victim)
    with pytest.raises(ValueError, match="symbolic link"):
        RunDirLock.acquire(run_dir)
    assert victim.read_text() == "precious\n"


def test_a_hard_linked_lock_is_refused_and_its_target_kept(tmp_path):
    run_dir = tmp_path / "run"
    run_dir.mkdir()
    victim = _victim(tmp_path)
    os.link(victim, run_dir / LOCK_FILE)
    with pytest.raises(ValueError, match="2 names"):
        RunDirLock.acquire(run_dir)
    assert victim.read_text() == "precious\n"


@pytest.mark.parametrize("kind", ["fifo", "directory"])
def test_a_lock_that_is_not_a_regular_file_is_refused(tmp_path, kind):
    run_dir = tmp_path / "run"
    run_dir.mkdir()
    if kind == "fifo":
        os.mkfifo(run_dir / LOCK_FILE)
    else:
        (run_dir / LOCK_FILE).mkdir()
    with pytest.raises(ValueError, match="cannot be locked"):
        RunDirLock.acquire(run_dir)


@needs_root
def test_a_lock_file_of_another_user_is_refused(tmp_path):
    run_dir = tmp_path / "run"
    run_dir.mkdir()
    (run_dir / LOCK_FILE).write_text("")
    os.chown(run_dir / LOCK_FILE, OTHER_UID, -1)
    with pytest.raises(ValueError, match="another user"):
        RunDirLock.acquire(run_dir)


def test_the_lock_is_never_truncated_and_names_its_holder(tmp_path):
    run_dir = tmp_path / "run"
    run_dir.mkdir()
    (run_dir / LOCK_FILE).write_text("x" * 100)
    lock = RunDirLock.acquire(run_dir)
    text = (run_dir / LOCK_FILE).read_text()
    assert len(text) == 100 and text.split()[0] == str(os.getpid())
    lock.release()
    assert len((run_dir / LOCK_FILE).read_text()) == 100
    with RunDirLock.acquire(run_dir):  # a cleared record: the next holder writes its own
        with pytest.raises(ValueError, match=f"pid {os.getpid()}"):
            RunDirLock.acquire(run_dir)


# ---------------------------------------------------- symlinked directories of a run directory
def _foreign_checkpoints(tmp_path: Path) -> Path:
    """A directory outside the run with two old checkpoints and a file named like a temp."""
    theirs = tmp_path / "theirs"
    theirs.mkdir()
    for step in (1, 2):
        checkpoint.save_checkpoint({"step": step}, tmp_path / "elsewhere", step, keep_last=5)
    for path in (tmp_path / "elsewhere" / "checkpoints").iterdir():
        shutil.copy(path, theirs / path.name)
    (theirs / ".notes.abcdefgh.tmp").write_text("mine")
    return theirs


@pytest.mark.parametrize("write", ["save_checkpoint", "remove_stale_files"])
def test_pruning_never_deletes_through_a_symlinked_checkpoints_dir(tmp_path, write):
    theirs = _foreign_checkpoints(tmp_path)
    before = sorted(p.name for p in theirs.iterdir())
    run_dir = tmp_path / "run"
    run_dir.mkdir()
    (run_dir / "checkpoints").symlink_to(theirs)
    with pytest.raises(ValueError, match="symbolic link"):
        if write == "save_checkpoint":
            checkpoint.save_checkpoint({"step": 9}, run_dir, 9, keep_last=1)
        else:
            checkpoint.remove_stale_files(run_dir)
    assert sorted(p.name for p in theirs.iterdir()) == before


@pytest.mark.parametrize("where", ["videos", "logs", "logs/exp/scalars"])
def test_a_symlink_anywhere_below_the_written_dirs_is_refused(tmp_path, where):
    run_dir = tmp_path / "run"
    link = run_dir / where
    link.parent.mkdir(parents=True)
    link.symlink_to(tmp_path)
    with pytest.raises(ValueError, match=rf"{where}' is a symbolic link"):
        check_run_subdirs(run_dir)


@needs_root
def test_a_checkpoints_dir_of_another_user_is_refused(tmp_path):
    run_dir = tmp_path / "run"
    (run_dir / "checkpoints").mkdir(parents=True)
    os.chown(run_dir / "checkpoints", OTHER_UID, -1)
    with pytest.raises(ValueError, match="belongs to another user"):
        checkpoint.save_checkpoint({"step": 1}, run_dir, 1)


# --------------------------------------------------------- scenario and recipe names
@pytest.mark.parametrize("name", ["../../escape", "a/b", "x\nline", "..", "tab\there", " pad"])
def test_register_env_refuses_a_name_that_is_not_a_plain_name(name, monkeypatch):
    from mapets_rl.envs import registry

    monkeypatch.setattr(registry, "_SCENARIOS", dict(registry._SCENARIOS))
    with pytest.raises(ValueError, match="scenario name .* is refused"):
        registry.register_env(name, lambda **_: None)
    assert name not in registry.available_envs()


@pytest.mark.parametrize("recipe, env", [("../up", "figure-eight"), ("mapets", "a/b")])
def test_the_default_run_dir_stays_below_runs(recipe, env, tmp_path):
    with pytest.raises(ValueError, match="name .* is refused"):
        default_run_dir(recipe, env, 0, tmp_path / "runs")


def test_valid_names_keep_working(tmp_path):
    path = default_run_dir("mapets", "figure-eight", 3, tmp_path)
    assert path.parent == tmp_path and path.name.startswith("mapets_figure-eight_seed3_")


# ------------------------------------------------------------- run directories of others
@pytest.fixture
def finished_toy_run(tmp_path, toy_scenario) -> Path:
    run_dir = tmp_path / "run"
    ToyLearner(ToyConfig(total_frames=20), run_dir).train()
    return run_dir


@pytest.mark.parametrize("entry", [LOCK_FILE, "checkpoints"])
def test_resume_of_a_run_dir_with_a_symlinked_entry_changes_nothing_outside(
    tmp_path, finished_toy_run, entry
):
    victim = tmp_path / "victim"
    if entry == "checkpoints":
        victim.mkdir()
        (finished_toy_run / "checkpoints").rename(victim / "moved")
        (victim / ".notes.abcdefgh.tmp").write_text("mine")
        (finished_toy_run / "checkpoints").symlink_to(victim / "moved")
    else:
        victim.write_text("precious\n")
        (finished_toy_run / LOCK_FILE).unlink()
        (finished_toy_run / LOCK_FILE).symlink_to(victim)
    before = {p: p.read_bytes() for p in [victim, *victim.rglob("*")] if p.is_file()}
    with pytest.raises(ValueError, match="symbolic link"):
        ToyLearner.from_run_dir(finished_toy_run, ["total_frames=40"])
    assert {p: p.read_bytes() for p in [victim, *victim.rglob("*")] if p.is_file()} == before


def test_a_new_run_refuses_a_foreign_non_empty_directory(tmp_path, toy_scenario):
    theirs = tmp_path / "theirs"
    theirs.mkdir()
    (theirs / "config.yaml").write_text("their: config\n")
    (theirs / "results.json").write_text('{"their": "results"}')
    with pytest.raises(ValueError, match="is not empty and is not a run directory"):
        ToyLearner(ToyConfig(total_frames=20), theirs)
    assert sorted(p.name for p in theirs.iterdir()) == ["config.yaml", "results.json"]
    assert (theirs / "config.yaml").read_text() == "their: config\n"


def test_the_cli_refuses_a_foreign_run_dir_in_one_line(tmp_path):
    theirs = tmp_path / "theirs"
    theirs.mkdir()
    (theirs / "config.yaml").write_text("their: config\n")
    out = _cli(
        ["train", "mappo", "--env", "figure-eight", "--run-dir", str(theirs)],
        tmp_path,
        **{CACHE_ENV: str(tmp_path / "cache")},
    )
    assert out.returncode == 2 and "is not empty and is not a run directory" in out.stderr
    assert (theirs / "config.yaml").read_text() == "their: config\n"


def test_an_empty_dir_or_one_of_an_attempt_that_never_checkpointed_is_used(tmp_path, toy_scenario):
    empty = tmp_path / "empty"
    empty.mkdir()
    (empty / LOCK_FILE).write_text("")  # left by an attempt that failed at once
    ToyLearner(ToyConfig(total_frames=20), empty).close()
    assert (empty / "run.json").is_file()
    ToyLearner(ToyConfig(total_frames=20), empty).close()  # not checkpointed: started afresh


# ------------------------------------------------ what `python -m ... cli` imports
def _planted_run_dir(tmp_path: Path) -> Path:
    """A run directory naming recipe ``evil``, with an entry point and module of that name
    planted in it; importing the module creates ``tmp_path/marker``."""
    run_dir = tmp_path / "run"
    info = run_dir / "evil-1.0.dist-info"
    info.mkdir(parents=True)
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: evil\nVersion: 1.0\n")
    (info / "entry_points.txt").write_text("[mapets_rl.recipes]\nevil = evilmod:Evil\n")
    (run_dir / "evilmod.py").write_text(
        f"open({str(tmp_path / 'marker')!r}, 'w').close()\nEvil = object\n"
    )
    (run_dir / "run.json").write_text('{"recipe": "evil", "env": "figure-eight", "seed": 0}')
    (run_dir / "config.yaml").write_text("env: figure-eight\n")
    return run_dir


def test_python_m_cli_imports_nothing_from_the_working_directory(tmp_path):
    run_dir = _planted_run_dir(tmp_path)
    out = _cli(["resume", "."], run_dir, **{CACHE_ENV: str(tmp_path / "cache")})
    assert out.returncode == 2 and "unknown recipe 'evil'" in out.stderr, out.stderr
    assert not (tmp_path / "marker").exists()


def test_a_recipe_entry_point_must_name_an_experiment_class(add_entry_point):
    add_entry_point("mapets_rl.recipes", "notarecipe", "os:path")
    with pytest.raises(ValueError, match="recipe 'notarecipe' .* is not an Experiment subclass"):
        load_recipe("notarecipe")


def test_a_scenario_entry_point_must_name_a_factory(add_entry_point):
    from mapets_rl.envs.registry import build_env

    add_entry_point("mapets_rl.scenarios", "notafactory", "os:sep")
    with pytest.raises(ValueError, match="scenario 'notafactory' .* is not a factory"):
        build_env("notafactory")


# ===================================================== work lost or silently changed
def test_a_resume_that_asks_for_less_than_was_done_is_refused(finished_toy_run):
    config_before = (finished_toy_run / "config.yaml").read_bytes()
    with pytest.raises(ValueError, match="has done 20 frames, more than the 10"):
        ToyLearner.from_run_dir(finished_toy_run, ["total_frames=10", "frames_per_batch=10"])
    assert (finished_toy_run / "config.yaml").read_bytes() == config_before
    resumed = ToyLearner.from_run_dir(finished_toy_run, ["total_frames=40"])  # forwards: fine
    resumed.train()
    assert resumed.frames == 40


def test_a_mapets_resume_to_fewer_episodes_is_refused(tmp_path):
    """It used to rewrite config.yaml to 1 episode, train nothing and exit 0."""
    from mapets_rl.recipes.mapets import MAPETS, MAPETSConfig

    tiny = dict(
        env_config={"n_cavs": 2, "n_hvs": 1, "horizon": 5},
        preset="cpu",
        planner={"horizon": 2, "population": 4, "elites": 2, "iterations": 1, "particles": 5},
        model={"hidden": [8], "buffer_size": 16, "batch_size": 4, "epochs": 1},
        num_threads=1,
        progress=False,
        episodes=2,
    )
    run_dir = tmp_path / "run"
    MAPETS(MAPETSConfig(**tiny), run_dir).train()
    config_before = (run_dir / "config.yaml").read_bytes()
    with pytest.raises(ValueError, match="has done 2 episodes, more than the 1"):
        MAPETS.from_run_dir(run_dir, ["episodes=1"])
    assert (run_dir / "config.yaml").read_bytes() == config_before


@pytest.mark.parametrize(
    "key, value",
    [
        ("screen_width", -5),
        ("scaling", float("nan")),
        ("centering_position", "middle"),
        ("screen_height", 100000),
        ("stock_neighbour_search", "no"),
        ("real_time_rendering", "yes"),
        ("offscreen_rendering", 5),
    ],
)
@pytest.mark.parametrize("scenario", ["figure-eight", "freeway", "freeway-merge"])
def test_rendering_keys_are_validated_when_the_env_is_built(scenario, key, value):
    from mapets_rl.envs import make_env

    with pytest.raises(ValueError, match=f"^{key} must be"):
        make_env(scenario, **{key: value})


def test_a_bad_rendering_key_fails_before_the_run_dir_exists(tmp_path):
    from mapets_rl.recipes.mappo import MAPPO, MAPPOConfig

    config = MAPPOConfig(video=True, env_config={"screen_width": -5})
    with pytest.raises(ValueError, match="screen_width must be"):
        MAPPO(config, tmp_path / "run")
    assert not (tmp_path / "run").exists()


def test_a_failing_final_evaluation_still_writes_the_final_checkpoint(
    tmp_path, toy_scenario, monkeypatch
):
    run_dir = tmp_path / "run"
    exp = ToyLearner(ToyConfig(total_frames=40, eval_interval=40), run_dir)

    def fail(*args, **kwargs):
        raise ValueError("the video cannot be written")

    monkeypatch.setattr(exp, "evaluate", fail)
    with pytest.raises(ValueError, match="video cannot be written"):
        exp.train()
    assert [p.name for p in checkpoint.list_checkpoints(run_dir)][-1] == "ckpt_000000000040.pt"
    assert ToyLearner.from_run_dir(run_dir).frames == 40  # the training is kept


@pytest.mark.parametrize(
    "overrides",
    [
        ["planner={horizon: 6}", "planner.horizon=5"],
        ["planner.horizon=5", "planner={horizon: 6}"],
        ["env_config={n_cavs: 2}", "env_config.n_cavs=4"],
    ],
)
def test_conflicting_nested_overrides_are_refused(overrides):
    from mapets_rl.config import ConfigError
    from mapets_rl.recipes.mapets import MAPETSConfig

    with pytest.raises(ConfigError, match="both set (planner|env_config): give it once"):
        MAPETSConfig().with_overrides(overrides)


def test_a_config_file_is_validated_with_the_overrides(tmp_path):
    """total_frames: 20 alone is refused (< frames_per_batch=200); with frames_per_batch=20
    it is a valid config."""
    from mapets_rl.recipes.sac import SACConfig

    path = tmp_path / "c.yaml"
    path.write_text("total_frames: 20\n")
    config = SACConfig.from_yaml(path, ["frames_per_batch=20"])
    assert (config.total_frames, config.frames_per_batch) == (20, 20)


def test_a_config_file_with_a_preset_takes_section_overrides(tmp_path):
    from mapets_rl.recipes.mapets import MAPETSConfig

    path = tmp_path / "c.yaml"
    path.write_text("preset: cpu\n")
    config = MAPETSConfig.from_yaml(path, ["planner.horizon=5"])
    cpu = MAPETSConfig(preset="cpu")
    assert config.planner == cpu.planner.replace(horizon=5)


@pytest.mark.parametrize("text, value", [("1e3", 1000.0), ("3e-4", 3e-4), ("1.5e3", 1500.0)])
def test_exponent_floats_are_numbers(text, value):
    from mapets_rl.recipes.mappo import MAPPOConfig

    config = MAPPOConfig().with_overrides([f"env_config.length={text}"])
    assert config.env_config["length"] == value and isinstance(config.env_config["length"], float)


def test_a_fifo_as_config_file_is_refused_at_once(tmp_path):
    from mapets_rl.config import ConfigError, read_yaml_mapping

    fifo = tmp_path / "fifo"
    os.mkfifo(fifo)
    with pytest.raises(ConfigError, match="is not a regular file"):
        read_yaml_mapping(fifo)


def test_a_config_file_larger_than_the_bound_is_still_refused(tmp_path):
    from mapets_rl.config import MAX_CONFIG_BYTES, ConfigError, read_yaml_mapping

    path = tmp_path / "big.yaml"
    path.write_bytes(b"#" * (MAX_CONFIG_BYTES + 1))
    with pytest.raises(ConfigError, match=f"larger than {MAX_CONFIG_BYTES} bytes"):
        read_yaml_mapping(path)


# ============================================================== tracebacks left
def test_a_deeply_nested_config_file_is_one_error(tmp_path):
    from mapets_rl.config import ConfigError, read_yaml_mapping

    path = tmp_path / "deep.yaml"
    path.write_text("a: " + "[" * 50_000 + "]" * 50_000 + "\n")  # 100 kB, no aliases
    with pytest.raises(ConfigError, match="nested deeper than 32 levels"):
        read_yaml_mapping(path)


@pytest.mark.parametrize(
    "override", ["env_config.x=" + "[" * 5000 + "]" * 5000, "env_config." + "a." * 2000 + "b=1"]
)
def test_a_deeply_nested_override_is_one_error(override):
    from mapets_rl.config import ConfigError
    from mapets_rl.recipes.mappo import MAPPOConfig

    with pytest.raises(ConfigError, match="deeper than 32 levels"):
        MAPPOConfig().with_overrides([override])


def test_a_run_dir_with_a_deeply_nested_config_yaml_is_one_error(finished_toy_run):
    (finished_toy_run / "config.yaml").write_text("env_config: " + "{a: " * 3000 + "1" + "}" * 3000)
    with pytest.raises(ValueError, match="nested deeper than 32 levels"):
        ToyLearner.from_run_dir(finished_toy_run)


def test_a_huge_population_decay_is_no_overflow():
    from mapets_rl.recipes.mapets import MAPETSConfig

    config = MAPETSConfig(planner={"optimizer": "icem", "population_decay": 1e200, "iterations": 3})
    sizes = config.planner.candidates_per_iteration()
    assert len(sizes) == 3 and sizes[1] == sizes[2] < sizes[0]


# ----------------------------------------------------------------- memory estimates
@pytest.mark.parametrize("settings", [{"ensemble_size": 10**7}, {"hidden": (10**6, 10**6)}])
def test_an_ensemble_too_large_for_memory_is_refused_before_allocating(settings):
    from mapets_rl.models import ProbabilisticEnsemble

    with pytest.raises(ValueError, match="the ensemble's weights .* GiB available"):
        ProbabilisticEnsemble(10, 1, 3, **settings)


def test_a_planner_too_large_for_memory_is_refused_at_construction():
    from mapets_rl.models import ProbabilisticEnsemble
    from mapets_rl.planning import TrajectorySamplingCEM

    model = ProbabilisticEnsemble(10, 1, 3, 5, (8,))
    with pytest.raises(ValueError, match="one planner decision .* GiB available"):
        TrajectorySamplingCEM(model, lambda o, a, n: o.sum(-1), -1.0, 1.0, population=10**9)


def test_the_mapets_estimate_counts_the_datasets(tmp_path):
    from mapets_rl.recipes.mapets import MAPETS, MAPETSConfig

    config = MAPETSConfig(preset="cpu", model={"buffer_size": 10**12})
    with pytest.raises(ValueError, match="model.buffer_size=1000000000000"):
        MAPETS(config, tmp_path / "run")
    assert not (tmp_path / "run").exists()


def test_available_memory_respects_ulimit_v():
    script = textwrap.dedent(
        """
        import resource
        from mapets_rl.memory import available_memory
        free = available_memory()
        resource.setrlimit(resource.RLIMIT_AS, (8 * 2**30, resource.RLIM_INFINITY))
        limited = available_memory()
        assert limited is not None and limited < 8 * 2**30 and limited <= free, (free, limited)
        """
    )
    done = subprocess.run(
        [sys.executable, "-c", script], env=_env(), capture_output=True, text=True, timeout=120
    )
    assert done.returncode == 0, done.stderr[-2000:]


@pytest.mark.parametrize("version", ["v2", "v1"])
def test_a_cgroup_limit_bounds_the_available_memory(tmp_path, version):
    from mapets_rl.memory import _cgroup_left

    if version == "v2":
        (tmp_path / "memory.max").write_text(f"{3 * 2**30}\n")
        (tmp_path / "memory.current").write_text(f"{2**30}\n")
    else:
        (tmp_path / "memory").mkdir()
        (tmp_path / "memory" / "memory.limit_in_bytes").write_text(f"{3 * 2**30}\n")
        (tmp_path / "memory" / "memory.usage_in_bytes").write_text(f"{2**30}\n")
    assert _cgroup_left(tmp_path) == 2 * 2**30
    (tmp_path / "memory.max").write_text("max\n")
    if version == "v2":
        assert _cgroup_left(tmp_path) is None


# ------------------------------------------------------------------- bad input
def test_a_figure_eight_of_a_petametre_is_refused():
    from mapets_rl.envs import make_env

    with pytest.raises(ValueError, match=r"length must be a finite number > 0 and <= 20000"):
        make_env("figure-eight", length=1e15)


@pytest.mark.parametrize(
    "obs, dtype, match",
    [
        ((2, 1, 3, 4), "int32", "dtype must be a floating-point"),
        ((2, 3, 4), None, r"obs must be \[I=2, B, N, 4\]"),
    ],
)
def test_ensemble_predict_checks_its_dtype_and_shapes(obs, dtype, match):
    import torch

    from mapets_rl.models import ProbabilisticEnsemble

    model = ProbabilisticEnsemble(4, 1, 2, 2, (8,))
    action = torch.zeros(*obs[:-1], 1)
    with pytest.raises(ValueError, match=match):
        model.predict(torch.zeros(obs), action, None if dtype is None else getattr(torch, dtype))


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"fraction": 0.9}, r"fraction must be in \[0, 0.5\)"),
        ({"fraction": -1}, "fraction must be a finite number >= 0"),
        ({"fraction": True}, "fraction must be a finite number"),
        ({"mask": "wrong shape"}, r"mask must be \[rows=10, n_agents=2\]"),
    ],
)
def test_holdout_split_checks_its_arguments(kwargs, match):
    import torch

    from mapets_rl.objectives import holdout_split

    args = {"mask": None, "rows": 10, "n_agents": 2, "fraction": 0.2, **kwargs}
    if args["mask"] == "wrong shape":
        args["mask"] = torch.ones(10, 3, dtype=torch.bool)
    with pytest.raises(ValueError, match=match):
        holdout_split(**args)


@pytest.mark.parametrize("beta", [float("nan"), float("inf"), True, -1.0])
def test_colored_noise_refuses_a_beta_that_is_not_a_finite_number(beta):
    from mapets_rl.planning.cem import colored_noise

    with pytest.raises(ValueError, match="beta must be a finite number >= 0"):
        colored_noise((2, 5, 1), beta)


def test_fit_ensemble_refuses_an_agent_without_any_row():
    import torch
    from tensordict import TensorDict

    from mapets_rl.models import ProbabilisticEnsemble
    from mapets_rl.objectives import EnsembleNLLLoss, fit_ensemble

    model = ProbabilisticEnsemble(3, 1, 2, 2, (8,))
    loss = EnsembleNLLLoss(model)
    mask = torch.ones(40, 2, dtype=torch.bool)
    mask[:, 1] = False
    data = TensorDict(
        {
            ("agents", "observation"): torch.randn(40, 2, 3),
            ("agents", "action"): torch.randn(40, 2, 1),
            ("next", "agents", "observation"): torch.randn(40, 2, 3),
            ("agents", "mask"): mask,
        },
        batch_size=[40],
    )
    optimizer = torch.optim.Adam(loss.parameters(), 1e-3)
    with pytest.raises(ValueError, match=r"no valid row .* for agents \[1\]"):
        fit_ensemble(loss, optimizer, data, epochs=2, batch_size=8, holdout=0.2)


@pytest.mark.parametrize("epsilon", [float("inf"), True, float("nan")])
def test_minimax_perturbation_refuses_a_bad_epsilon(epsilon):
    import torch

    from mapets_rl.objectives import minimax_action_perturbation

    with pytest.raises(ValueError, match="epsilon must be a finite number >= 0"):
        minimax_action_perturbation(lambda a: a.sum((-1, -2)), torch.zeros(2, 1), epsilon)


def test_minimax_perturbation_refuses_nan_actions():
    import torch

    from mapets_rl.objectives import minimax_action_perturbation

    actions = torch.tensor([[0.0], [float("nan")]])
    with pytest.raises(ValueError, match="actions must be finite"):
        minimax_action_perturbation(lambda a: a.sum((-1, -2)), actions, 0.1)


@pytest.mark.parametrize("field", ["epsilon_critic", "epsilon_actor"])
def test_m3ddpg_loss_refuses_a_boolean_epsilon(field):
    from mapets_rl.objectives import M3DDPGLoss

    epsilons = {"epsilon_critic": 0.1, "epsilon_actor": 0.1, field: True}
    with pytest.raises(ValueError, match=f"{field} must be a finite number"):
        M3DDPGLoss(None, None, action_key="action", value_key="q", **epsilons)


def test_a_new_run_under_a_file_size_limit_is_one_line(tmp_path):
    script = (
        "import resource, sys; resource.setrlimit(resource.RLIMIT_FSIZE, (1024, 1024)); "
        "sys.argv[0] = 'mapets-rl'; from mapets_rl.app.cli import main; "
        "sys.exit(main(sys.argv[1:]))"
    )
    argv = ["train", "mappo", "--env", "figure-eight", "--run-dir", str(tmp_path / "run")]
    argv += ["total_frames=200", "frames_per_batch=100", "minibatch_size=50", "progress=false"]
    done = subprocess.run(
        [sys.executable, "-c", script, *argv],
        cwd=tmp_path,
        env=_env(**{CACHE_ENV: str(tmp_path / "cache")}),
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert done.returncode == 2, done.stderr[-2000:]
    assert "Traceback" not in done.stderr and "ulimit -f" in done.stderr


# ===================================================== byte-identical checkpoints and results
def test_identical_mapets_runs_write_byte_identical_checkpoints_and_results(tmp_path):
    """Wall-clock metrics (train_time, step_time) go to timings.json: the checkpoints and
    results.json of two identical runs are equal byte for byte."""
    import hashlib

    from mapets_rl.experiment.results import read_results
    from mapets_rl.recipes.mapets import MAPETS, MAPETSConfig

    tiny = dict(
        env_config={"n_cavs": 2, "n_hvs": 1, "horizon": 5},
        preset="cpu",
        planner={"horizon": 2, "population": 4, "elites": 2, "iterations": 1, "particles": 5},
        model={"hidden": [8], "buffer_size": 16, "batch_size": 4, "epochs": 1},
        num_threads=1,
        progress=False,
        episodes=2,
        seed=5,
    )
    runs = [tmp_path / "a", tmp_path / "b"]
    for run_dir in runs:
        MAPETS(MAPETSConfig(**tiny), run_dir).train()

    def digests(run_dir: Path) -> dict[str, str]:
        files = [*sorted((run_dir / "checkpoints").iterdir()), run_dir / "results.json"]
        return {p.name: hashlib.sha256(p.read_bytes()).hexdigest() for p in files}

    assert digests(runs[0]) == digests(runs[1])
    assert len(digests(runs[0])) == 5  # 2 checkpoints, 2 digest files, results.json
    assert "train_time" not in (runs[0] / "results.json").read_text()
    timings = json.loads((runs[0] / "timings.json").read_text())
    assert [sorted(t["metrics"]) for t in timings["train"]] == [["step_time", "train_time"]] * 2
    entries = read_results(runs[0])["train"]  # read back with their timings
    assert all(e["metrics"]["train_time"] >= 0 and "agility" in e["metrics"] for e in entries)


def test_a_resume_keeps_the_timings_of_the_entries_its_checkpoint_holds(tmp_path, toy_scenario):
    from mapets_rl.experiment.results import ResultsWriter

    writer = ResultsWriter(tmp_path, "toy", "toy", 0, {})
    writer.add_train(10, {"reward": 1.0, "train_time": 0.5})
    state = writer.state_dict()
    writer.add_train(20, {"reward": 2.0, "train_time": 0.7})  # after the checkpoint
    resumed = ResultsWriter(tmp_path, "toy", "toy", 0, {})
    resumed.load_state_dict(state)
    resumed.add_train(20, {"reward": 2.0, "train_time": 0.9})
    timings = json.loads((tmp_path / "timings.json").read_text())["train"]
    assert timings == [
        {"frames": 10, "metrics": {"train_time": 0.5}},
        {"frames": 20, "metrics": {"train_time": 0.9}},
    ]


def test_a_resume_hides_no_tensorboard_point_logged_before_its_checkpoint(tmp_path, monkeypatch):
    """MA-PETS logs model/nll by epoch (10 per episode here), ahead of the frames (5 per
    episode): the purge step must lie past the epochs, or TensorBoard hides epochs 6-10."""
    from mapets_rl.experiment import results
    from mapets_rl.recipes.mapets import MAPETS, MAPETSConfig

    tiny = dict(
        env_config={"n_cavs": 2, "n_hvs": 1, "horizon": 5},
        preset="cpu",
        planner={"horizon": 2, "population": 4, "elites": 2, "iterations": 1, "particles": 5},
        model={"hidden": [8], "buffer_size": 16, "batch_size": 4, "epochs": 10},
        num_threads=1,
        progress=False,
        episodes=1,
    )
    run_dir = tmp_path / "run"
    MAPETS(MAPETSConfig(**tiny), run_dir).train()
    purged = []
    make_logger = results.make_logger

    def recording(kind, run_dir, exp_name, purge_step=None):
        purged.append(purge_step)
        return make_logger(kind, run_dir, exp_name, purge_step)

    monkeypatch.setattr(results, "make_logger", recording)
    resumed = MAPETS.from_run_dir(run_dir, ["episodes=2"])
    assert resumed.frames == 5
    resumed.train()
    assert purged == [11]  # past model/nll's epochs 1-10, not frames + 1 = 6


# ================================================================ a killed Ray sweep
def _descendants(root: int) -> dict[int, str]:
    """pid -> command name of every live (not zombie) descendant of process ``root``."""
    parents, names = {}, {}
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            stat = (entry / "stat").read_text().rpartition(")")[2].split()
            name = (entry / "cmdline").read_bytes().split(b"\0")[0].decode(errors="replace")
        except OSError:
            continue
        if stat[0] != "Z":
            parents[int(entry.name)], names[int(entry.name)] = int(stat[1]), name
    found, frontier = {}, {root}
    while frontier:
        frontier = {pid for pid, parent in parents.items() if parent in frontier}
        found.update({pid: names[pid] for pid in frontier})
    return found


@pytest.mark.skipif(not Path("/proc").is_dir(), reason="needs /proc to find Ray's processes")
def test_a_ray_sweep_killed_with_kill_9_leaves_no_ray_agent(tmp_path):
    pytest.importorskip("ray", reason="ray is not installed (pip install 'mapets-rl[ray]')")
    import signal
    import time

    from mapets_rl.ray_runtime import RAY_AGENTS
    from tests.app.test_sweep import _SWEEP_SCRIPT, TINY
    from tests.sweep_helpers import SLOW_ENV

    out = tmp_path / "sweep"
    argv = ["sweep", "slowtoy", "--env", "toy", "--seeds", "0", *TINY, "--out", str(out)]
    argv += ["--backend", "ray"]
    script = _SWEEP_SCRIPT.format(
        tests=str(ROOT / "tests"), extending=str(ROOT / "examples" / "extending"), argv=argv
    )
    with open(tmp_path / "sweep.log", "w") as log:
        proc = subprocess.Popen(
            [sys.executable, "-c", script],
            cwd=ROOT,
            env=_env(**{SLOW_ENV: "4.0"}),
            stdout=log,
            stderr=subprocess.STDOUT,
        )
    record = out / "trials" / "seed=0" / "trial.json"
    deadline = time.monotonic() + 180
    while time.monotonic() < deadline and proc.poll() is None:
        time.sleep(0.5)
        try:
            if json.loads(record.read_text()).get("state") == "running":
                break
        except (OSError, ValueError):
            continue
    ray_processes = _descendants(proc.pid)
    agents = [pid for pid, name in ray_processes.items() if name.strip() in RAY_AGENTS]
    try:
        assert len(agents) == 2, (ray_processes, (tmp_path / "sweep.log").read_text()[-2000:])
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait()
        deadline = time.monotonic() + 10.0  # they used to live on for about a minute
        alive = agents
        while alive and time.monotonic() < deadline:
            time.sleep(0.2)
            alive = [pid for pid in agents if _is_running(pid)]
        assert not alive, "Ray agents outlived the killed sweep"
    finally:
        for pid in ray_processes:
            if _is_running(pid):
                os.kill(pid, signal.SIGKILL)


def _is_running(pid: int) -> bool:
    try:
        stat = Path(f"/proc/{pid}/stat").read_text().rpartition(")")[2].split()
    except OSError:
        return False
    return stat[0] != "Z"
