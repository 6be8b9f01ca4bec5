"""Bad input never ends in a traceback nor is silently accepted: each case below is refused with
a one-line ValueError naming the parameter (Python API; a TypeError where a tensor of the
wrong dtype or a string for a torch.dtype is given) or exits with code 2 and one line
``mapets-rl: error: ...`` (CLI), before any work starts."""

from __future__ import annotations

import importlib.util
import os
import re
import warnings
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModule
from toy_recipe import ToyConfig, ToyLearner
from toy_scenario import ToyAgentsEnv

from mapets_rl.app.cli import main
from mapets_rl.comm import CommunicationRange, communication_graph
from mapets_rl.envs import FigureEightEnv, FreewayEnv, make_env, registry
from mapets_rl.experiment import register_env, runner
from mapets_rl.models import ProbabilisticEnsemble
from mapets_rl.objectives import COMACritic, COMALoss, EnsembleNLLLoss, ShapleyActorCriticLoss
from mapets_rl.planning import TrajectorySamplingCEM
from mapets_rl.recipes.maddpg import MADDPGConfig
from mapets_rl.recipes.mapets import MAPETSConfig
from mapets_rl.recipes.mappo import MAPPOConfig
from mapets_rl.recipes.sac import SACConfig
from mapets_rl.recipes.shapley_ac import ShapleyACConfig
from mapets_rl.shapley import (
    CoalitionCritic,
    RandomCoalition,
    exact_shapley,
    make_coalition_actor,
    sampled_shapley,
)

INF, NAN = float("inf"), float("nan")
NO_CUDA_DEVICE = "cuda" if not torch.cuda.is_available() else f"cuda:{torch.cuda.device_count()}"

pytestmark = pytest.mark.usefixtures("toy_scenario")


def _refused(call: Callable[[], Any], match: str, error: type[Exception] = ValueError) -> str:
    """Run ``call``; it must raise ``error`` whose one-line message matches ``match``."""
    with pytest.raises(error, match=match) as err:
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
        "mapets planner_reward.collision_gap=inf",
        lambda: MAPETSConfig(planner_reward={"collision_gap": INF}),
        "planner_reward.collision_gap must be a finite",
    ),
    (
        "mapets planner_reward.collision_reward=-inf",
        lambda: MAPETSConfig(planner_reward={"collision_reward": -INF}),
        "planner_reward.collision_reward must be a finite",
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
    ("--config /dev/zero", TRAIN + ["--config", "/dev/zero"], "is not a regular file"),
    (
        "--config duplicate key",
        TRAIN + ["--config", "{dup_yaml}"],
        "key 'lr' given twice at line 3",
    ),
    ("--config alias bomb", TRAIN + ["--config", "{alias_yaml}"], r"aliases \(\*name\) are not"),
    (
        "num_cells too large",
        ["train", "mappo", "--env", "figure-eight", "num_cells=[1000000, 1000000]"],
        r"num_cells must be layers whose weights fit in memory \(at least 14901.2 GiB",
    ),
    (
        "critic_cells too large",
        ["train", "coma", "--env", "freeway", "critic_cells=[1000000, 1000000]"],
        r"critic_cells must be layers whose weights fit in memory",
    ),
    (
        "mapets ts1 particles that do not split over the members",
        [
            "train",
            "mapets",
            "--env",
            "figure-eight",
            "--run-dir",
            "{tmp_path}/ts1",
            "preset=cpu",
            "planner.propagation=ts1",
            "planner.particles=3",
        ],
        r"planner.particles \* population \(24\) must be divisible by the ensemble size \(5\)",
    ),
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
    assert not (tmp_path / "ts1").exists()  # refused before the run directory exists


def test_read_only_run_dir_is_refused_before_anything_starts(tmp_path: Path, monkeypatch) -> None:
    read_only = tmp_path / "ro"
    read_only.mkdir()
    real_access = os.access
    monkeypatch.setattr(
        os, "access", lambda p, mode, **kw: Path(p) != read_only and real_access(p, mode, **kw)
    )
    built = []
    monkeypatch.setattr(runner, "build_env", lambda *args, **kwargs: built.append(1))
    _refused(
        lambda: ToyLearner(ToyConfig(), read_only / "run"),
        "run_dir .* cannot be written: .* is not writable",
    )
    assert built == [] and list(read_only.iterdir()) == []


# ------------------------------------------------------------------- scenario constructors
ENV_CASES = [
    (
        "highway-env's other_vehicles_type",
        lambda: FigureEightEnv({"other_vehicles_type": "x.IDMVehicle"}),
        r"unknown config key\(s\) \['other_vehicles_type'\]",
    ),
    (
        "highway-env's action dict",
        lambda: FreewayEnv({"action": {"type": "ContinuousAction"}}),
        r"unknown config key\(s\) \['action'\]",
    ),
    (
        "highway-env's observation dict on the freeway",
        lambda: FreewayEnv({"observation": {"type": "Kinematics"}}),
        r"unknown config key\(s\) \['observation'\]",
    ),
    (
        "the freeway's derived n_cavs",
        lambda: FreewayEnv({"n_cavs": 3}),
        r"unknown config key\(s\) \['n_cavs'\]",
    ),
    ("max_speed=1e9", lambda: FigureEightEnv({"max_speed": 1e9}), "max_speed must be .* <= 60"),
    (
        "hv_target_speed above max_speed",
        lambda: FigureEightEnv({"hv_target_speed": (10.0, 1e9)}),
        r"hv_target_speed must be a range .* hi <= 13.89",
    ),
    (
        "freeway speed_limit=1e9",
        lambda: FreewayEnv({"speed_limit": 1e9}),
        "speed_limit must be .* <= 60",
    ),
    (
        "freeway hv_target_speed above the limit",
        lambda: FreewayEnv({"hv_target_speed": (10.0, 1e9)}),
        r"hv_target_speed must be a range .* hi <= 31.3",
    ),
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
    assert "x" not in registry._SCENARIOS


def test_register_env_does_not_silently_replace_a_scenario(monkeypatch) -> None:
    monkeypatch.setattr(registry, "_SCENARIOS", dict(registry._SCENARIOS))
    _refused(lambda: register_env("freeway", ToyAgentsEnv), "'freeway' is a built-in scenario")
    _refused(lambda: register_env("toy", lambda: None), "'toy' is already registered")
    _refused(lambda: register_env("", ToyAgentsEnv), "name must be a non-empty scenario name")
    register_env("toy", ToyAgentsEnv)  # the same factory again: a no-op
    register_env("freeway", ToyAgentsEnv, overwrite=True)
    assert registry._SCENARIOS["freeway"].factory is ToyAgentsEnv


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


# ---------------------------------------------------------- tensors at module boundaries
OBS, ACT, MASK = ("agents", "observation"), ("agents", "action"), ("agents", "mask")
NEXT_OBS = ("next", "agents", "observation")
COALITION = ("agents", "coalition")
N_AG, OBS_DIM, ACT_DIM, ROWS = 3, 4, 2, 32


def _td(entries: dict, batch: int | tuple[int, ...], **changes: Any) -> TensorDict:
    """``entries`` with ``changes`` (keyed by the entry's name; ``None`` drops the key)."""
    named = {**entries, **changes}
    return TensorDict(dict(item for item in named.values() if item is not None), batch)


def _ensemble(n_agents: int = N_AG) -> ProbabilisticEnsemble:
    torch.manual_seed(0)
    return ProbabilisticEnsemble(OBS_DIM, ACT_DIM, n_agents, ensemble_size=2, hidden=(8,))


def _model_batch(n_agents: int = N_AG, **changes: Any) -> TensorDict:
    g = torch.Generator().manual_seed(0)
    entries = {
        "obs": (OBS, torch.randn(ROWS, n_agents, OBS_DIM, generator=g)),
        "action": (ACT, torch.randn(ROWS, n_agents, ACT_DIM, generator=g)),
        "next_obs": (NEXT_OBS, torch.randn(ROWS, n_agents, OBS_DIM, generator=g)),
    }
    changes = {
        k: None if v is None else (entries.get(k, (MASK,))[0], v) for k, v in changes.items()
    }
    return _td(entries, [ROWS], **changes)


def _planner(**kwargs: Any) -> TrajectorySamplingCEM:
    settings = dict(horizon=3, population=8, elites=2, iterations=2, particles=2, dtype="fp32")
    low, high = kwargs.pop("action_low", -1.0), kwargs.pop("action_high", 1.0)

    def reward(obs: torch.Tensor, action: torch.Tensor, next_obs: torch.Tensor) -> torch.Tensor:
        return -next_obs.pow(2).sum(-1)

    return TrajectorySamplingCEM(_ensemble(), reward, low, high, seed=0, **{**settings, **kwargs})


def _warm_planner() -> TrajectorySamplingCEM:
    """A planner that has planned for 4 envs (so that ``is_init`` is read)."""
    planner = _planner()
    planner.plan(torch.zeros(4, N_AG, OBS_DIM))
    return planner


def _critic() -> CoalitionCritic:
    torch.manual_seed(0)
    return CoalitionCritic(N_AG, OBS_DIM, ACT_DIM, num_cells=(8, 8))


def _critic_batch(**changes: Any) -> TensorDict:
    keys = {"obs": OBS, "action": ACT, "coalition": COALITION}
    g = torch.Generator().manual_seed(0)
    entries = {
        "obs": (OBS, torch.randn(5, N_AG, OBS_DIM, generator=g)),
        "action": (ACT, torch.randn(5, N_AG, ACT_DIM, generator=g)),
        "coalition": (COALITION, torch.ones(5, N_AG, dtype=torch.bool)),
    }
    return _td(entries, [5], **{k: None if v is None else (keys[k], v) for k, v in changes.items()})


def _shapley_loss(**kwargs: Any) -> ShapleyActorCriticLoss:
    torch.manual_seed(0)
    actor = make_coalition_actor(N_AG, OBS_DIM, ACT_DIM, discrete=True, num_cells=(8,))
    return ShapleyActorCriticLoss(actor, _critic(), **kwargs)


SHAPLEY_KEYS = {
    "obs": OBS,
    "action": ACT,
    "coalition": COALITION,
    "next_obs": NEXT_OBS,
    "reward": ("next", "agents", "reward"),
    "terminated": ("next", "agents", "terminated"),
}


def _shapley_batch(**changes: Any) -> TensorDict:
    g = torch.Generator().manual_seed(0)
    action = torch.nn.functional.one_hot(torch.randint(ACT_DIM, (6, N_AG), generator=g), ACT_DIM)
    values = {
        "obs": torch.randn(6, N_AG, OBS_DIM, generator=g),
        "action": action.float(),
        "coalition": torch.ones(6, N_AG, dtype=torch.bool),
        "next_obs": torch.randn(6, N_AG, OBS_DIM, generator=g),
        "reward": torch.rand(6, N_AG, 1, generator=g),
        "terminated": torch.zeros(6, N_AG, 1, dtype=torch.bool),
        **changes,
    }
    return TensorDict({SHAPLEY_KEYS[k]: v for k, v in values.items() if v is not None}, [6])


def _coma_loss(**kwargs: Any) -> COMALoss:
    torch.manual_seed(0)
    actor = TensorDictModule(
        torch.nn.Linear(OBS_DIM, ACT_DIM), in_keys=[OBS], out_keys=[("agents", "logits")]
    )
    critic = TensorDictModule(
        COMACritic(N_AG, OBS_DIM, ACT_DIM, num_cells=[8]),
        in_keys=[OBS, ACT],
        out_keys=[("agents", "action_value")],
    )
    return COMALoss(actor, critic, **kwargs)


COMA_KEYS = {
    "obs": OBS,
    "action": ACT,
    "next_obs": NEXT_OBS,
    "reward": ("next", "agents", "reward"),
    "done": ("next", "done"),
    "terminated": ("next", "terminated"),
}


def _coma_batch(**changes: Any) -> TensorDict:
    g = torch.Generator().manual_seed(0)
    action = torch.nn.functional.one_hot(torch.randint(ACT_DIM, (5, N_AG), generator=g), ACT_DIM)
    values = {
        "obs": torch.randn(5, N_AG, OBS_DIM, generator=g),
        "action": action.float(),
        "next_obs": torch.randn(5, N_AG, OBS_DIM, generator=g),
        "reward": torch.randn(5, N_AG, 1, generator=g),
        "done": torch.zeros(5, 1, dtype=torch.bool),
        "terminated": torch.zeros(5, 1, dtype=torch.bool),
        **changes,
    }
    return TensorDict({COMA_KEYS[k]: v for k, v in values.items() if v is not None}, [5])


HAND = torch.tensor([[0.0, 0.0], [30.0, 40.0], [100.0, 0.0]])


def _positions(position: torch.Tensor, mask: torch.Tensor | None = None) -> TensorDict:
    agents = {"position": position} if mask is None else {"position": position, "mask": mask}
    return TensorDict({"agents": TensorDict(agents, position.shape[:-1])}, position.shape[:-2])


def _half(shape: tuple[int, ...]) -> torch.Tensor:
    return torch.full(shape, 0.5)


def _nan_at(shape: tuple[int, ...], agent: int, value: float = NAN) -> torch.Tensor:
    x = torch.randn(shape)
    x[..., agent, 0] = value
    return x


MISSING_KEY_CASES = [
    (
        "ensemble forward without the action",
        lambda: _ensemble()(_model_batch(action=None)),
        r"ProbabilisticEnsemble needs \('agents', 'action'\) \[\*, 3, 2\] .* missing",
    ),
    (
        "NLL loss without the next observation",
        lambda: EnsembleNLLLoss(_ensemble())(_model_batch(next_obs=None)),
        r"EnsembleNLLLoss needs \('next', 'agents', 'observation'\) \[\*, 3, 4\] .* missing",
    ),
    (
        "planner forward without the observation",
        lambda: _planner()(TensorDict({}, [])),
        r"TrajectorySamplingCEM needs \('agents', 'observation'\) \[\*, n_agents=3, obs_dim=4\]",
    ),
    (
        "critic without the coalition",
        lambda: _critic()(_critic_batch(coalition=None)),
        r"CoalitionCritic needs \('agents', 'coalition'\) \[\*, n_agents=3\] bool .* missing",
    ),
    (
        "Shapley loss without terminated",
        lambda: _shapley_loss()(_shapley_batch(terminated=None)),
        r"ShapleyActorCriticLoss needs \('next', 'agents', 'terminated'\) .* missing",
    ),
    (
        "Shapley actor loss without the action",
        lambda: _shapley_loss().loss_actor(_shapley_batch(action=None)),
        r"ShapleyActorCriticLoss needs \('agents', 'action'\) .* missing",
    ),
    (
        "COMA loss without terminated",
        lambda: _coma_loss()(_coma_batch(terminated=None)),
        r"COMALoss needs \('next', 'terminated'\) \[\*, T, 1\] .* missing",
    ),
    (
        "COMA loss without the reward",
        lambda: _coma_loss()(_coma_batch(reward=None)),
        r"COMALoss needs \('next', 'agents', 'reward'\) \[\*, T, n, 1\] .* missing",
    ),
    (
        "COMA loss without the action",
        lambda: _coma_loss()(_coma_batch(action=None)),
        r"COMALoss needs \('agents', 'action'\) .* missing",
    ),
    (
        "CommunicationRange episode graph without positions",
        lambda: CommunicationRange(10.0).episode_graph(
            TensorDict({("next", "agents", "speed"): torch.zeros(4, N_AG)}, [4])
        ),
        r"episode_graph needs \('next', 'agents', 'position'\) \[\*B, T, I, 2\] .* missing",
    ),
]

SHAPE_AND_DTYPE_CASES = [
    (
        "NLL mask [32, 3] for 2 agents",
        lambda: EnsembleNLLLoss(_ensemble(2))(
            _model_batch(2, mask=torch.ones(ROWS, 3, dtype=torch.bool))
        ),
        r"\('agents', 'mask'\) must have shape \[32, 2\] \(or \[32, 2, 1\]\), got \[32, 3\]",
        ValueError,
    ),
    (
        "NLL bool observations",
        lambda: EnsembleNLLLoss(_ensemble())(
            _model_batch(obs=torch.ones(ROWS, N_AG, OBS_DIM, dtype=torch.bool))
        ),
        r"obs must be a float \(or int\) tensor \[N, n_agents=3, 4\], got dtype torch.bool",
        TypeError,
    ),
    (
        "ensemble forward bool observations",
        lambda: _ensemble()(_model_batch(obs=torch.ones(ROWS, N_AG, OBS_DIM, dtype=torch.bool))),
        r"\('agents', 'observation'\) must be a float \(or int\) tensor .* got dtype torch.bool",
        TypeError,
    ),
    (
        "planner bool observations",
        lambda: _planner().plan(torch.ones(N_AG, OBS_DIM, dtype=torch.bool)),
        r"observation must be a float \(or int\) tensor .* got dtype torch.bool",
        TypeError,
    ),
    (
        "planner is_init of the wrong size",
        lambda: _warm_planner().plan(
            torch.zeros(4, N_AG, OBS_DIM), is_init=torch.zeros(3, 1, dtype=torch.bool)
        ),
        r"is_init must have shape \[4\] or \[4, 1\] .* got \[3, 1\]",
        ValueError,
    ),
    (
        "predict dtype 'fp16'",
        lambda: _ensemble().predict(
            torch.zeros(N_AG, 2, 5, OBS_DIM), torch.zeros(N_AG, 2, 5, ACT_DIM), "fp16"
        ),
        r"dtype must be a torch.dtype \(e.g. torch.bfloat16\) or None, got 'fp16'",
        TypeError,
    ),
]

NON_FINITE_CASES = [
    (
        "ensemble forward NaN observation",
        lambda: _ensemble()(_model_batch(obs=_nan_at((ROWS, N_AG, OBS_DIM), 1))),
        r"\('agents', 'observation'\) contains NaN or inf values for agent\(s\) \[1\]",
    ),
    (
        "critic NaN observation",
        lambda: _critic()(_critic_batch(obs=_nan_at((5, N_AG, OBS_DIM), 2))),
        r"\('agents', 'observation'\) contains NaN or inf values for agent\(s\) \[2\]",
    ),
    (
        "Shapley loss NaN reward",
        lambda: _shapley_loss()(_shapley_batch(reward=torch.full((6, N_AG, 1), NAN))),
        r"\('next', 'agents', 'reward'\) must be finite, got 18 NaN or infinite entries of 18",
    ),
    (
        "COMA loss NaN reward",
        lambda: _coma_loss()(_coma_batch(reward=_nan_at((5, N_AG, 1), 1))),
        r"\('next', 'agents', 'reward'\) contains NaN or inf values for agent\(s\) \[1\]",
    ),
    (
        "CommunicationRange NaN position",
        lambda: CommunicationRange(1000.0)(_positions(_nan_at((N_AG, 2), 1))),
        r"position must be finite for every unmasked agent, got NaN or inf for agent\(s\) \[1\]",
    ),
    (
        "planner NaN observation",
        lambda: _planner().plan(_nan_at((N_AG, OBS_DIM), 0)),
        r"observation contains NaN or inf values for agent\(s\) \[0\]",
    ),
    (
        "planner inf observation",
        lambda: _planner().plan(_nan_at((2, N_AG, OBS_DIM), 2, INF)),
        r"observation contains NaN or inf values for agent\(s\) \[2\]",
    ),
    (
        "planner action_low=-inf, action_high=inf",
        lambda: _planner(action_low=-INF, action_high=INF),
        r"action_low must be finite in every dimension .* got -inf",
    ),
    (
        "planner action_high=[1, inf]",
        lambda: _planner(action_high=[1.0, INF]),
        r"action_high must be finite in every dimension .* got \[1.0, inf\]",
    ),
]

BOOL_AND_MASK_CASES = [
    ("ensemble obs_dim=True", lambda: ProbabilisticEnsemble(True, 1, 1), "obs_dim must be a"),
    ("planner horizon=True", lambda: _planner(horizon=True), "horizon must be an integer"),
    (
        "CommunicationRange(True)",
        lambda: CommunicationRange(True),
        r"comm_range must be a number in \[0, inf\], got True",
    ),
    (
        "NLL mask 0.5",
        lambda: EnsembleNLLLoss(_ensemble())(_model_batch(mask=_half((ROWS, N_AG)))),
        r"\('agents', 'mask'\) must be a bool tensor \[32, 3\] \(or hold only 0 and 1\), got "
        r"dtype torch.float32 with values such as \[0.5, 0.5, 0.5\]",
    ),
    (
        "NLL mask 2",
        lambda: EnsembleNLLLoss(_ensemble())(_model_batch(mask=torch.full((ROWS, N_AG), 2.0))),
        r"\('agents', 'mask'\) must be a bool tensor .* values such as \[2.0, 2.0, 2.0\]",
    ),
    (
        "critic coalition 0.5",
        lambda: _critic()(_critic_batch(coalition=_half((5, N_AG)))),
        r"\('agents', 'coalition'\) must be a bool tensor \[\*, 3\] .* such as \[0.5",
    ),
    (
        "Shapley loss coalition 2",
        lambda: _shapley_loss()(_shapley_batch(coalition=torch.full((6, N_AG), 2))),
        r"\('agents', 'coalition'\) must be a bool tensor .* dtype torch.int64 .* \[2, 2, 2\]",
    ),
    (
        "Shapley actor loss mask 0.5",
        lambda: _shapley_loss().loss_actor(_shapley_batch().set(MASK, _half((6, N_AG)))),
        r"\('agents', 'mask'\) must be a bool tensor \[6, 3\]",
    ),
    (
        "COMA loss mask 0.5",
        lambda: _coma_loss()(_coma_batch().set(MASK, _half((5, N_AG)))),
        r"\('agents', 'mask'\) must be a bool tensor \[\*, n\]",
    ),
    (
        "random coalition mask 0.5",
        lambda: RandomCoalition(N_AG)(_critic_batch().set(MASK, _half((5, N_AG)))),
        r"\('agents', 'mask'\) must be a bool tensor \[5, 3\]",
    ),
    (
        "CommunicationRange mask 0.5",
        lambda: CommunicationRange(1000.0)(_positions(HAND.clone(), _half((N_AG,)))),
        r"mask must be a bool tensor \(3,\) \(or hold only 0 and 1\)",
    ),
    (
        "planner is_init 0.5",
        lambda: _warm_planner().plan(torch.zeros(4, N_AG, OBS_DIM), is_init=_half((4, 1))),
        r"is_init must be a bool tensor \[4, 1\]",
    ),
]

COEFFICIENT_CASES = [
    (
        "logvar_bound_coef=inf",
        lambda: EnsembleNLLLoss(_ensemble(), logvar_bound_coef=INF),
        "logvar_bound_coef must be a finite number >= 0, got inf",
    ),
    (
        "logvar_bound_coef=nan",
        lambda: EnsembleNLLLoss(_ensemble(), logvar_bound_coef=NAN),
        "logvar_bound_coef must be a finite number >= 0, got nan",
    ),
    (
        "Shapley reward_scale=inf",
        lambda: _shapley_loss(reward_scale=INF),
        "reward_scale must be a finite number > 0, got inf",
    ),
    (
        "Shapley logits_reg=inf",
        lambda: _shapley_loss(logits_reg=INF),
        "logits_reg must be a finite number >= 0, got inf",
    ),
    (
        "Shapley gumbel_temperature=inf",
        lambda: _shapley_loss(gumbel_temperature=INF),
        "gumbel_temperature must be a finite number > 0, got inf",
    ),
    (
        "COMA entropy_coeff=inf",
        lambda: _coma_loss(entropy_coeff=INF),
        "entropy_coeff must be a finite number >= 0, got inf",
    ),
    (
        "COMA reward_scale=inf",
        lambda: _coma_loss(reward_scale=INF),
        "reward_scale must be a finite number > 0, got inf",
    ),
    (
        "CommunicationRange seed='abc'",
        lambda: CommunicationRange(10.0, seed="abc"),
        "seed must be None or an int >= 0, got 'abc'",
    ),
]

VALUE_ERROR_CASES = MISSING_KEY_CASES + NON_FINITE_CASES + BOOL_AND_MASK_CASES + COEFFICIENT_CASES


@pytest.mark.parametrize(
    "call, match", [c[1:] for c in VALUE_ERROR_CASES], ids=[c[0] for c in VALUE_ERROR_CASES]
)
def test_module_refuses_bad_tensors_and_arguments(call: Callable[[], Any], match: str) -> None:
    _refused(call, match)


@pytest.mark.parametrize(
    "call, match, error",
    [c[1:] for c in SHAPE_AND_DTYPE_CASES],
    ids=[c[0] for c in SHAPE_AND_DTYPE_CASES],
)
def test_module_refuses_wrong_shapes_and_dtypes(
    call: Callable[[], Any], match: str, error: type[Exception]
) -> None:
    _refused(call, match, error)


def test_planner_refuses_a_nan_observation_before_any_rollout() -> None:
    """Refused at plan entry: no rollout ran, so no reward_fn warning and no counted reward."""
    planner = _planner()
    with warnings.catch_warnings(record=True) as record:
        warnings.simplefilter("always")
        _refused(lambda: planner.plan(_nan_at((N_AG, OBS_DIM), 1)), r"agent\(s\) \[1\]")
    assert [str(w.message) for w in record] == []
    assert int(planner.nonfinite_rewards.sum()) == 0


def test_communication_range_accepts_int_positions() -> None:
    """int64 metres are a legitimate input: cast, the same graph as in float."""
    ints = torch.tensor([[0, 0], [30, 40], [100, 0]])
    for comm_range in (50.0, 100.0, INF):
        expected = communication_graph(ints.float(), comm_range)
        out = CommunicationRange(comm_range)(_positions(ints))["agents", "neighbors"]
        assert torch.equal(out, expected) and out.dtype == torch.bool
    assert int(communication_graph(ints, 50.0).sum()) == 2  # 0-1 at exactly 50 m, both ways


def test_masked_agents_may_hold_non_finite_positions() -> None:
    """Only the unmasked agents' positions must be finite (a removed agent may be anywhere)."""
    position = HAND.clone()
    position[1] = NAN
    mask = torch.tensor([True, False, True])
    out = CommunicationRange(1000.0)(_positions(position, mask))["agents", "neighbors"]
    assert out.tolist() == [[False, False, True], [False, False, False], [True, False, False]]


def test_zero_one_masks_of_any_dtype_act_as_bool_masks() -> None:
    """Float and int masks holding only 0 and 1 stay accepted, with the bool mask's result."""
    mask = torch.rand(ROWS, N_AG, generator=torch.Generator().manual_seed(1)) > 0.3
    loss = EnsembleNLLLoss(_ensemble(), bootstrap=False)
    expected = loss(_model_batch(mask=mask))["nll_per_member"]
    for dtype in (torch.float32, torch.int64, torch.uint8):
        out = loss(_model_batch(mask=mask.to(dtype)))["nll_per_member"]
        torch.testing.assert_close(out, expected)
    critic = _critic()
    coalition = torch.tensor([[1.0, 0.0, 1.0]]).expand(5, N_AG)
    values = critic(_critic_batch(coalition=coalition))["coalition_value"]
    bool_values = critic(_critic_batch(coalition=coalition.bool()))["coalition_value"]
    torch.testing.assert_close(values, bool_values)


def test_predict_still_takes_torch_dtypes_inside_and_outside_frozen_parameters() -> None:
    """The dtype check (behind the cache hit of the planner's ``frozen_parameters`` path)
    leaves valid calls unchanged: None, float32 and bfloat16, inside and outside the block."""
    model = _ensemble()
    obs, action = torch.randn(N_AG, 2, 5, OBS_DIM), torch.randn(N_AG, 2, 5, ACT_DIM)
    with torch.no_grad():
        outside = model.predict(obs, action)
        torch.testing.assert_close(model.predict(obs, action, torch.float32), outside)
        with model.frozen_parameters():
            torch.testing.assert_close(model.predict(obs, action), outside)
        bf16 = model.predict(obs, action, torch.bfloat16)
        with model.frozen_parameters(torch.bfloat16):
            torch.testing.assert_close(model.predict(obs, action, torch.bfloat16), bf16)
    torch.testing.assert_close(bf16, outside, atol=0.1, rtol=0.05)


# ------------------------------------------------------------- MA-PETS: refusals before writing
@pytest.mark.parametrize(
    "env, overrides, match",
    [
        ("freeway", [], "must have continuous actions for mapets"),
        (
            "figure-eight",
            ["planner.population=100000000", "planner.elites=2"],
            r"need about .* GiB on cpu .* more than the .* GiB available: lower",
        ),
        (
            "figure-eight",
            ["model.hidden=[100000, 100000, 100000]"],
            r"need about .* GiB on cpu .* model.hidden=\[100000, 100000, 100000\]",
        ),
    ],
    ids=["discrete actions", "planner too large", "ensemble too large"],
)
def test_mapets_refuses_a_scenario_or_size_before_writing_the_run_dir(
    env: str, overrides: list[str], match: str, tmp_path: Path
) -> None:
    from mapets_rl.recipes.mapets import MAPETS, MAPETSConfig

    config = MAPETSConfig(env=env, preset="cpu").with_overrides(overrides)
    _refused(lambda: MAPETS(config, tmp_path / "run"), match)
    assert not (tmp_path / "run").exists()


def test_mapets_refuses_planner_reward_settings_beside_a_reward_fn(tmp_path: Path) -> None:
    """planner_reward.collision_gap & co. configure the scenario's planner reward; with a
    reward_fn of the user's (argument or config field) they were silently ignored."""
    from mapets_rl.envs import FigureEightPlannerReward
    from mapets_rl.recipes.mapets import MAPETS, MAPETSConfig

    config = MAPETSConfig(env="figure-eight", preset="cpu", planner_reward={"collision_gap": 3})
    reward = FigureEightPlannerReward().reward
    _refused(
        lambda: MAPETS(config, tmp_path / "run", reward_fn=reward),
        r"planner_reward.collision_gap=3.0 configures the scenario's planner reward, which a "
        "given reward_fn replaces",
    )
    _refused(
        lambda: MAPETS(
            config.with_overrides(["reward_fn=mapets_rl.envs:FigureEightPlannerReward"]),
            tmp_path / "run",
        ),
        "planner_reward.collision_gap=3.0 configures",
    )
    assert not (tmp_path / "run").exists()


@pytest.mark.parametrize(
    ("value", "why"),
    [
        ("no_such_package_xyz.rewards:speed", "ModuleNotFoundError"),
        ("mapets_rl.envs:no_such_reward", "AttributeError"),
        ("mapets_rl.envs.figure_eight:COLLISION_REWARD", "a float, not callable"),
        ("not a name", "ValueError"),
    ],
)
def test_mapets_reward_fn_must_name_an_importable_callable(value: str, why: str) -> None:
    from mapets_rl.recipes.mapets import MAPETSConfig

    _refused(
        lambda: MAPETSConfig(preset="cpu").with_overrides([f"reward_fn={value}"]),
        rf"reward_fn must be 'package.module:function', an importable callable .*{why}",
    )


def test_mapets_refuses_a_reward_fn_given_twice(tmp_path: Path) -> None:
    from mapets_rl.recipes.mapets import MAPETS, MAPETSConfig

    config = MAPETSConfig(preset="cpu", reward_fn="tests.recipes.test_recipe_mapets:speed_reward")
    _refused(
        lambda: MAPETS(config, tmp_path / "run", reward_fn=lambda o, a, n: n[..., 0]),
        "reward_fn is given twice",
    )
    assert not (tmp_path / "run").exists()


def test_mapets_planner_reward_is_refused_for_a_scenario_without_one() -> None:
    from mapets_rl.recipes.mapets import MAPETSConfig

    _refused(
        lambda: MAPETSConfig(env="freeway").with_overrides(["planner_reward.headway=1"]),
        "planner_reward must be left out for env 'freeway', whose scenario registers no "
        "planner reward",
    )
