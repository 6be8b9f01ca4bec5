"""Bad configs never end in a traceback nor are silently accepted: each is refused with a
one-line ValueError naming the parameter before any work starts (non-finite numbers, unknown
devices, scenarios and seeds, a logger without its package), and a bad config file is named in
the message."""

from __future__ import annotations

import importlib.util
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
from toy_recipe import ToyConfig

from mapets_rl.recipes.maddpg import MADDPGConfig
from mapets_rl.recipes.mapets import MAPETSConfig
from mapets_rl.recipes.mappo import MAPPOConfig
from mapets_rl.recipes.sac import SACConfig
from mapets_rl.recipes.shapley_ac import ShapleyACConfig
from tests.refusals import INF, NAN, NO_CUDA_DEVICE, refused

pytestmark = pytest.mark.usefixtures("toy_scenario")


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
    refused(call, match)


def test_inf_comm_range_stays_allowed() -> None:
    assert MAPETSConfig(comm={"comm_range": INF}).comm.comm_range == INF


@pytest.mark.skipif(importlib.util.find_spec("wandb") is not None, reason="wandb installed")
def test_logger_without_its_package_is_refused_by_the_config() -> None:
    refused(lambda: ToyConfig(logger="wandb"), "logger='wandb' needs the wandb package")


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
    assert "cfg.yaml" in refused(lambda: ToyConfig.from_yaml(path), match)


def test_missing_config_file_is_one_line() -> None:
    refused(lambda: ToyConfig.from_yaml("/nonexistent/cfg.yaml"), "cannot be read")
