"""Bad input never ends in a traceback nor is silently accepted: each case below is refused with
a one-line ValueError naming the parameter (Python API) or exits with code 2 and one line
``mapets-rl: error: ...`` (CLI), before any work starts."""

from __future__ import annotations

import importlib.util
import os
import re
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch
from tensordict import TensorDict
from toy_recipe import ToyConfig, ToyLearner
from toy_scenario import ToyAgentsEnv

from mapets_rl.envs import FigureEightEnv, FreewayEnv, make_env
from mapets_rl.experiment import register_env, runner
from mapets_rl.experiment.cli import main
from mapets_rl.shapley import exact_shapley, sampled_shapley
from recipes.maddpg import MADDPGConfig
from recipes.mapets import MAPETSConfig
from recipes.mappo import MAPPOConfig
from recipes.sac import SACConfig
from recipes.shapley_ac import ShapleyACConfig

INF, NAN = float("inf"), float("nan")
NO_CUDA_DEVICE = "cuda" if not torch.cuda.is_available() else f"cuda:{torch.cuda.device_count()}"

pytestmark = pytest.mark.usefixtures("toy_scenario")


def _refused(call: Callable[[], Any], match: str) -> str:
    """Run ``call``; it must raise a ValueError whose one-line message matches ``match``."""
    with pytest.raises(ValueError, match=match) as err:
        call()
    message = str(err.value)
    assert "\n" not in message, message
    return message


# ------------------------------------------------------------------- configs (Python API)
CONFIG_CASES = [
    ("lr=inf", lambda: ToyConfig(lr=INF), "lr must be a finite number"),
    ("lr=nan", lambda: ToyConfig(lr=NAN), "lr must be a finite number"),
    (
        "lr=1e400 override",
        lambda: ToyConfig().with_overrides(["lr=1e400"]),
        "lr must be a finite number",
    ),
    (
        "lr=.inf override",
        lambda: ToyConfig().with_overrides(["lr=.inf"]),
        "lr must be a finite number",
    ),
    ("mapets lr=inf", lambda: MAPETSConfig(model={"lr": INF}), "model.lr must be a finite number"),
    (
        "mapets epsilon=inf",
        lambda: MAPETSConfig(planner={"epsilon": INF}),
        "planner.epsilon must be a finite",
    ),
    (
        "mapets collision_gap=inf",
        lambda: MAPETSConfig(collision_gap=INF),
        "collision_gap must be a finite",
    ),
    (
        "mapets collision_reward=-inf",
        lambda: MAPETSConfig(collision_reward=-INF),
        "collision_reward must be a finite",
    ),
    (
        "mapets comm_range=nan",
        lambda: MAPETSConfig(comm={"comm_range": NAN}),
        r"comm.comm_range must be a number \(inf allowed\), not NaN",
    ),
    ("mappo lr=inf", lambda: MAPPOConfig(lr=INF), "lr must be a finite number"),
    (
        "mappo max_grad_norm=inf",
        lambda: MAPPOConfig(max_grad_norm=INF),
        "max_grad_norm must be a finite number",
    ),
    ("maddpg tau=nan", lambda: MADDPGConfig(tau=NAN), "tau must be a finite number"),
    ("sac alpha_init=inf", lambda: SACConfig(alpha_init=INF), "alpha_init must be a finite"),
    (
        "shapley lr_critic=inf",
        lambda: ShapleyACConfig(lr_critic=INF),
        "lr_critic must be a finite number",
    ),
    ("device=tpu", lambda: ToyConfig(device="tpu"), r"device must be one of \['cpu'"),
    ("device=bogus", lambda: ToyConfig(device="bogus"), "device must be one of"),
    ("device=cuda without cuda", lambda: ToyConfig(device=NO_CUDA_DEVICE), "device must be one of"),
    (
        "env=nowhere",
        lambda: ToyConfig(env="nowhere"),
        "env must be one of the registered scenarios",
    ),
    ("seed=-1", lambda: ToyConfig(seed=-1), r"seed must be in \[0, 4611686018427387903\]"),
]


@pytest.mark.parametrize(
    "call, match", [c[1:] for c in CONFIG_CASES], ids=[c[0] for c in CONFIG_CASES]
)
def test_config_refuses(call: Callable[[], Any], match: str) -> None:
    _refused(call, match)


def test_inf_comm_range_stays_allowed() -> None:
    assert MAPETSConfig(comm={"comm_range": INF}).comm.comm_range == INF


@pytest.mark.skipif(importlib.util.find_spec("wandb") is not None, reason="wandb installed")
def test_logger_without_its_package_is_refused_by_the_config() -> None:
    _refused(lambda: ToyConfig(logger="wandb"), "logger='wandb' needs the wandb package")


@pytest.mark.parametrize(
    "content, match",
    [
        ("lr: [1, 2\n", r"is not valid YAML: .* at line 2"),
        ("lr: 1\n  bad: indent\n", "is not valid YAML"),
        ("- lr\n", "must hold a mapping of config fields, got a list"),
        ("lr: .inf\n", "lr must be a finite number"),
        ("nokey: 1\n", "unknown config key 'nokey'"),
    ],
    ids=["unclosed list", "bad indent", "a list", "inf", "unknown key"],
)
def test_config_file_errors_name_the_file(tmp_path: Path, content: str, match: str) -> None:
    path = tmp_path / "cfg.yaml"
    path.write_text(content)
    assert "cfg.yaml" in _refused(lambda: ToyConfig.from_yaml(path), match)


def test_missing_config_file_is_one_line() -> None:
    _refused(lambda: ToyConfig.from_yaml("/nonexistent/cfg.yaml"), "cannot be read")


# -------------------------------------------------------------------------------- the CLI
@pytest.fixture
def a_file(tmp_path: Path) -> Path:
    path = tmp_path / "a_file"
    path.write_text("not a directory")
    return path


@pytest.fixture
def bad_yaml(tmp_path: Path) -> Path:
    path = tmp_path / "bad.yaml"
    path.write_text("total_frames: [40\n")
    return path


@pytest.fixture
def dup_yaml(tmp_path: Path) -> Path:
    path = tmp_path / "dup.yaml"
    path.write_text("lr: 0.1\ntotal_frames: 40\nlr: 0.2\n")
    return path


@pytest.fixture
def alias_yaml(tmp_path: Path) -> Path:
    """A "billion laughs" document: each line doubles the last (2**9 here, unbounded in
    general)."""
    lines = ["a0: &a0 [x, x]"] + [f"a{i}: &a{i} [*a{i - 1}, *a{i - 1}]" for i in range(1, 9)]
    path = tmp_path / "bomb.yaml"
    path.write_text("\n".join(lines) + "\n")
    return path


@pytest.fixture
def finished_run(tmp_path: Path) -> Path:
    run = tmp_path / "done"
    ToyLearner(ToyConfig(total_frames=20), run).train()
    return run


TRAIN = ["train", "toy", "--env", "toy"]
CLI_CASES = [
    ("lr=.inf", TRAIN + ["lr=.inf"], "lr must be a finite number"),
    ("lr=1e400", TRAIN + ["lr=1e400"], "lr must be a finite number"),
    ("lr=nan", TRAIN + ["lr=nan"], "lr must be a finite number"),
    ("device=bogus", TRAIN + ["device=bogus"], "device must be one of"),
    ("device=cuda", TRAIN + [f"device={NO_CUDA_DEVICE}"], "device must be one of"),
    (
        "env=nowhere override",
        TRAIN + ["env=nowhere"],
        r"chosen by --env \(toy\), not by 'env=nowhere'",
    ),
    ("--env and env=", TRAIN + ["env=freeway"], r"chosen by --env \(toy\), not by 'env=freeway'"),
    ("--seed and seed=", TRAIN + ["--seed", "1", "seed=2"], "--seed 1 and 'seed=2' both set"),
    ("a key twice", TRAIN + ["lr=0.1", "lr=0.2"], r"lr is set twice \('lr=0.1' and 'lr=0.2'\)"),
    ("--run-dir ''", TRAIN + ["--run-dir", ""], "--run-dir must be a non-empty path"),
    (
        "--run-dir name too long",
        TRAIN + ["--run-dir", "{tmp_path}/" + "x" * 300],
        "run_dir cannot be created: the name .* is 300 bytes, this file system allows",
    ),
    (
        "total_frames below one batch",
        TRAIN + ["total_frames=20", "frames_per_batch=200"],
        "total_frames must be >= frames_per_batch=200",
    ),
    ("seed=2**64", TRAIN + [f"seed={2**64}"], r"seed must be in \[0, 4611686018427387903\]"),
    ("--config /dev/zero", TRAIN + ["--config", "/dev/zero"], "larger than 1048576 bytes"),
    (
        "--config duplicate key",
        TRAIN + ["--config", "{dup_yaml}"],
        "key 'lr' given twice at line 3",
    ),
    ("--config alias bomb", TRAIN + ["--config", "{alias_yaml}"], r"aliases \(\*name\) are not"),
    (
        "coma on continuous actions",
        ["train", "coma", "--env", "figure-eight", "total_frames=20"],
        "coma needs discrete actions; scenario 'figure-eight' has continuous actions",
    ),
    ("malformed --config", TRAIN + ["--config", "{bad_yaml}"], "is not valid YAML"),
    ("missing --config", TRAIN + ["--config", "/nonexistent/c.yaml"], "cannot be read"),
    (
        "--run-dir under a file",
        TRAIN + ["--run-dir", "{a_file}/run"],
        "run_dir .* cannot be created: .* is not a directory",
    ),
    (
        "--run-dir is a file",
        TRAIN + ["--run-dir", "{a_file}"],
        "run_dir .* cannot be created: .* is not a directory",
    ),
    (
        "--runs-root under a file",
        TRAIN + ["--runs-root", "{a_file}/runs"],
        "--runs-root .* cannot be created",
    ),
    (
        "env_config length=inf",
        ["train", "toy", "--env", "figure-eight", "env_config.length=.inf"],
        "length must be a finite number > 0",
    ),
    (
        "env_config n_hvs=many",
        ["train", "toy", "--env", "figure-eight", "env_config.n_hvs=many"],
        "n_hvs must be an int >= 0 or a range",
    ),
    (
        "compare --out under a file",
        ["compare", "{finished_run}", "--out", "{a_file}/cmp"],
        "out_dir .* cannot be created",
    ),
    (
        "compare --metrics ,",
        ["compare", "{finished_run}", "--out", "{tmp_path}/cmp", "--metrics", ","],
        "--metrics must name at least one metric",
    ),
    (
        "compare unknown metric",
        ["compare", "{finished_run}", "--out", "{tmp_path}/cmp", "--metrics", "nope"],
        r"metrics \['nope'\] are not in every run",
    ),
    (
        "resume env override",
        ["resume", "{finished_run}", "env=freeway"],
        "env cannot change when resuming",
    ),
    ("resume device=bogus", ["resume", "{finished_run}", "device=bogus"], "device must be one of"),
]


@pytest.mark.parametrize("argv, match", [c[1:] for c in CLI_CASES], ids=[c[0] for c in CLI_CASES])
def test_cli_exits_2_with_one_line(
    argv: list[str], match: str, toy_recipe, tmp_path: Path, request, capsys
) -> None:
    names = {"a_file", "bad_yaml", "dup_yaml", "alias_yaml", "finished_run", "tmp_path"}
    values = {n: request.getfixturevalue(n) for n in names if any(f"{{{n}}}" in a for a in argv)}
    argv = [a.format(**values) for a in argv]
    capsys.readouterr()
    try:
        code = main(argv)
    except SystemExit as exc:
        code = exc.code
    _, err = capsys.readouterr()
    assert code == 2, err
    assert err.count("\n") == 1 and err.startswith("mapets-rl: error: "), err
    assert re.search(match, err), err
    assert not (tmp_path / "cmp").exists()


def test_read_only_run_dir_is_refused_before_anything_starts(tmp_path: Path, monkeypatch) -> None:
    read_only = tmp_path / "ro"
    read_only.mkdir()
    real_access = os.access
    monkeypatch.setattr(
        os, "access", lambda p, mode, **kw: Path(p) != read_only and real_access(p, mode, **kw)
    )
    built = []
    monkeypatch.setattr(ToyLearner, "make_env", lambda self: built.append(1))
    _refused(
        lambda: ToyLearner(ToyConfig(), read_only / "run"),
        "run_dir .* cannot be written: .* is not writable",
    )
    assert built == [] and list(read_only.iterdir()) == []


# ------------------------------------------------------------------- scenario constructors
ENV_CASES = [
    ("length=inf", lambda: FigureEightEnv({"length": INF}), "length must be a finite number > 0"),
    ("length=-1", lambda: FigureEightEnv({"length": -1.0}), "length must be a finite number > 0"),
    (
        "max_speed=-5",
        lambda: FigureEightEnv({"max_speed": -5.0}),
        "max_speed must be a finite number > 0",
    ),
    (
        "max_speed=nan",
        lambda: FigureEightEnv({"max_speed": NAN}),
        "max_speed must be a finite number > 0",
    ),
    (
        "initial_speed low > high",
        lambda: FigureEightEnv({"initial_speed": (8.0, 4.0)}),
        "initial_speed must be a range",
    ),
    (
        "initial_speed negative",
        lambda: FigureEightEnv({"initial_speed": (-5.0, -1.0)}),
        "initial_speed must be a range .* 0 <= lo <= hi",
    ),
    (
        "initial_speed above max_speed",
        lambda: FigureEightEnv({"initial_speed": (4.0, 30.0)}),
        r"initial_speed .* hi <= 13.89",
    ),
    (
        "hv_target_speed nan",
        lambda: FigureEightEnv({"hv_target_speed": (NAN, 10.0)}),
        "hv_target_speed must be a range",
    ),
    ("n_hvs=many", lambda: FigureEightEnv({"n_hvs": "many"}), "n_hvs must be an int >= 0"),
    ("n_hvs=2.5", lambda: FigureEightEnv({"n_hvs": 2.5}), "n_hvs must be an int >= 0"),
    ("lanes=1.5", lambda: FigureEightEnv({"lanes": 1.5}), "lanes must be 1 or 2"),
    (
        "collision_reward=nan",
        lambda: FigureEightEnv({"collision_reward": NAN}),
        "collision_reward must be a finite number",
    ),
    ("n_cavs=True", lambda: FigureEightEnv({"n_cavs": True}), "n_cavs must be an integer"),
    (
        "min_spacing=nan",
        lambda: FigureEightEnv({"min_spacing": NAN}),
        "min_spacing must be a finite number >= 7",
    ),
    (
        "freeway velocity_weight=nan",
        lambda: FreewayEnv({"velocity_weight": NAN}),
        "velocity_weight must be a finite number",
    ),
    (
        "freeway speed_limit=-1",
        lambda: FreewayEnv({"speed_limit": -1.0}),
        "speed_limit must be a finite number > 0",
    ),
    (
        "freeway cav_ratio='half'",
        lambda: FreewayEnv({"cav_ratio": "half"}),
        r"cav_ratio must be a number in \[0, 1\]",
    ),
    (
        "freeway initial_speed low > high",
        lambda: FreewayEnv({"initial_speed": (28.0, 22.0)}),
        "initial_speed must be a range",
    ),
    (
        "freeway perception=0",
        lambda: FreewayEnv({"perception": 0.0}),
        "perception must be a finite number > 0",
    ),
    (
        "freeway collision_reward=nan",
        lambda: FreewayEnv({"collision_reward": NAN}),
        "collision_reward must be a finite number",
    ),
    (
        "torchrl env length=inf",
        lambda: make_env("figure-eight", length=INF),
        "length must be a finite number",
    ),
    (
        "torchrl env speed_limit=nan",
        lambda: make_env("freeway", speed_limit=NAN),
        "speed_limit must be a finite number",
    ),
]


@pytest.mark.parametrize("call, match", [c[1:] for c in ENV_CASES], ids=[c[0] for c in ENV_CASES])
def test_scenario_config_refused(call: Callable[[], Any], match: str) -> None:
    _refused(call, match)


# ------------------------------------------------------------------------------- actions
@pytest.fixture(scope="module")
def freeway() -> Any:
    return make_env("freeway", n_vehicles=4, seed=0)


def _one_hot_rows(rows: list[list[float]]) -> torch.Tensor:
    return torch.tensor(rows, dtype=torch.float32)


KL = [1.0, 0.0, 0.0, 0.0]
FREEWAY_ACTIONS = [
    ("all-zero", [KL, KL, KL, [0.0, 0.0, 0.0, 0.0]]),
    ("two-hot", [KL, [1.0, 1.0, 0.0, 0.0], KL, KL]),
    ("fractional", [KL, KL, [0.25, 0.25, 0.25, 0.25], KL]),
    ("nan", [[NAN, 0.0, 0.0, 0.0], KL, KL, KL]),
    ("negative", [KL, KL, KL, [2.0, -1.0, 0.0, 0.0]]),
]


@pytest.mark.parametrize(
    "rows", [a[1] for a in FREEWAY_ACTIONS], ids=[a[0] for a in FREEWAY_ACTIONS]
)
def test_freeway_torchrl_env_refuses_actions_that_are_not_one_hot(freeway, rows) -> None:
    td = freeway.reset()
    td["agents", "action"] = _one_hot_rows(rows)
    _refused(lambda: freeway.step(td), "must be one-hot per CAV")
    # a valid one passes, also as a straight-through estimator writes it (1 - 6e-8)
    td["agents", "action"] = _one_hot_rows([KL] * 3 + [[0.99999994, 0.0, 0.0, 0.0]])
    assert freeway.step(td)["next", "agents", "reward"].shape == (4, 1)


def test_torchrl_env_refuses_a_wrong_batch_shape_and_a_missing_action(freeway) -> None:
    td = freeway.reset()
    td["agents"] = TensorDict({"action": torch.zeros(2, 4, 4)}, [])
    _refused(lambda: freeway.step(td), r"must have shape \[4, 4\], got \[2, 4, 4\]")
    _refused(lambda: freeway.step(freeway.reset()), "step needs the CAVs' actions")


RAW_ACTIONS = [
    ("None", None, r"step needs the CAVs' action \(got None\)"),
    ("strings", [["fast"]] * 8, "action must be an array of numbers, got a list of dtype <U4"),
    ("dict", {"cav_0": 3.0}, "action must be an array of numbers, got a dict"),
    ("ragged", [[1.0], [2.0, 3.0]], "action must be an array of numbers"),
    ("bools", np.ones((8, 1), dtype=bool), "action must be an array of numbers"),
    ("wrong shape", np.ones((7, 1)), r"action must have shape \(8, 1\)"),
    ("nan", np.full((8, 1), NAN), "action must be finite"),
]


@pytest.mark.parametrize(
    "action, match", [a[1:] for a in RAW_ACTIONS], ids=[a[0] for a in RAW_ACTIONS]
)
def test_raw_env_refuses_bad_actions(action: Any, match: str) -> None:
    env = FigureEightEnv({"n_hvs": 4})
    _refused(lambda: env.step(action), match)


def test_raw_env_refuses_a_step_after_the_episode_ended() -> None:
    env = FigureEightEnv({"n_hvs": 2, "horizon": 2})
    env.reset(seed=0)
    action = np.full((8, 1), 5.0, dtype=np.float32)
    assert [env.step(action)[3] for _ in range(2)] == [False, True]
    _refused(lambda: env.step(action), r"the episode is over .* call reset\(\)")
    env.reset(seed=1)
    assert env.step(action)[3] is False  # a reset makes it usable again


# ------------------------------------------------------------------------------ registry
def test_register_env_refuses_a_non_callable_factory() -> None:
    _refused(lambda: register_env("x", 42), "factory must be callable")
    assert "x" not in runner._ENV_REGISTRY


def test_register_env_does_not_silently_replace_a_scenario(monkeypatch) -> None:
    monkeypatch.setattr(runner, "_ENV_REGISTRY", dict(runner._ENV_REGISTRY))
    _refused(lambda: register_env("freeway", ToyAgentsEnv), "'freeway' is a built-in scenario")
    _refused(lambda: register_env("toy", lambda: None), "'toy' is already registered")
    _refused(lambda: register_env("", ToyAgentsEnv), "name must be a non-empty scenario name")
    register_env("toy", ToyAgentsEnv)  # the same factory again: a no-op
    register_env("freeway", ToyAgentsEnv, overwrite=True)
    assert runner._ENV_REGISTRY["freeway"] is ToyAgentsEnv


# ------------------------------------------------------------------------------- Shapley
@pytest.mark.parametrize("bad", [NAN, INF], ids=["nan", "inf"])
def test_exact_shapley_refuses_non_finite_values(bad: float) -> None:
    values = torch.zeros(3, 8)
    values[1, 5] = bad
    _refused(lambda: exact_shapley(values, 3), "values must be finite")


def test_sampled_shapley_refuses_non_finite_value_fn_outputs() -> None:
    def value_fn(masks: torch.Tensor) -> torch.Tensor:
        out = masks.float().sum(-1)
        out[-1] = NAN
        return out

    _refused(lambda: sampled_shapley(value_fn, 4, 8), "value_fn's values must be finite")
