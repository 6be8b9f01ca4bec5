"""Defaults that work on a batched env: ``frames_per_batch`` left out is the recipe's one-road
batch rounded up to a multiple of the roads (and of the collector workers), the off-policy
``init_random_frames`` left out is 200 rounded up to a multiple of it, an explicit value that
does not fit is still refused, and the collector's process count ``collector_workers`` still
reads under its old name ``num_envs`` with a DeprecationWarning."""

from __future__ import annotations

import warnings
from pathlib import Path

import pytest
import yaml

from mapets_rl.experiment import ConfigError
from mapets_rl.recipes.coma import COMAConfig
from mapets_rl.recipes.maddpg import MADDPG, MADDPGConfig
from mapets_rl.recipes.mappo import MAPPOConfig
from mapets_rl.recipes.shapley_ac import ShapleyACConfig

ROADS = {"backend": "torch", "num_envs": 256}


def test_defaults_on_one_road_are_the_recipes_batches() -> None:
    assert (MADDPGConfig().frames_per_batch, MADDPGConfig().init_random_frames) == (200, 200)
    assert (ShapleyACConfig().frames_per_batch, ShapleyACConfig().init_random_frames) == (40, 200)
    assert (COMAConfig().frames_per_batch, MAPPOConfig().frames_per_batch) == (40, 200)


@pytest.mark.parametrize(
    "config_cls, batch, random_frames",
    [(MADDPGConfig, 256, 256), (ShapleyACConfig, 256, 256), (COMAConfig, 256, None)],
)
def test_batched_defaults_are_multiples_of_the_roads(
    config_cls: type, batch: int, random_frames: int | None
) -> None:
    config = config_cls(env="freeway-merge", env_config=ROADS)
    assert config.frames_per_batch == batch
    assert getattr(config, "init_random_frames", None) == random_frames
    # 3 roads: 200 -> 201 frames (67 steps per road), 201 random frames
    three = MADDPGConfig(env="freeway-merge", env_config={"backend": "torch", "num_envs": 3})
    assert (three.frames_per_batch, three.init_random_frames) == (201, 201)
    assert MAPPOConfig(collector_workers=3).frames_per_batch == 201


def test_overrides_derive_the_defaults_again_and_explicit_values_win() -> None:
    base = MADDPGConfig(env="freeway-merge")
    batched = base.with_overrides(["env_config.backend=torch", "env_config.num_envs=256"])
    assert (batched.frames_per_batch, batched.init_random_frames) == (256, 256)
    explicit = batched.with_overrides(["frames_per_batch=1024"])
    assert (explicit.frames_per_batch, explicit.init_random_frames) == (1024, 1024)
    kept = explicit.with_overrides(["init_random_frames=0"]).with_overrides(["lr_actor=0.01"])
    assert (kept.frames_per_batch, kept.init_random_frames) == (1024, 0)
    with pytest.raises(ConfigError, match=r"frames_per_batch must be a multiple of env_config"):
        base.with_overrides(
            ["env_config.backend=torch", "env_config.num_envs=256", "frames_per_batch=200"]
        )


def test_a_default_batched_run_builds_its_collector_without_warnings(tmp_path: Path) -> None:
    config = MADDPGConfig(
        env="freeway-merge",
        env_config={"backend": "torch", "num_envs": 3, "n_vehicles": 6, "cav_ratio": 1.0},
        total_frames=201,
        num_cells=[8],
        progress=False,
        logger="none",
    )
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        exp = MADDPG(config, tmp_path / "run")
    exp.collector.shutdown()
    assert not [w for w in caught if "multiple" in str(w.message)]


def test_num_envs_reads_as_collector_workers_with_a_deprecation_warning(tmp_path: Path) -> None:
    with pytest.warns(DeprecationWarning, match="'num_envs' .* now 'collector_workers'"):
        assert MAPPOConfig(num_envs=2).collector_workers == 2
    with pytest.warns(DeprecationWarning, match="'num_envs'"):
        assert MAPPOConfig().with_overrides(["num_envs=2"]).collector_workers == 2
    old = {k: v for k, v in MAPPOConfig(collector_workers=2).to_dict().items()}
    old["num_envs"] = old.pop("collector_workers")
    (tmp_path / "old.yaml").write_text(yaml.safe_dump(old))
    with pytest.warns(DeprecationWarning, match="'num_envs'"):
        assert MAPPOConfig.from_yaml(tmp_path / "old.yaml").collector_workers == 2
    with pytest.warns(DeprecationWarning, match="'num_envs'"):
        renamed = MAPPOConfig.rename_old_keys(old, "config.yaml")  # what resuming reads
    assert renamed["collector_workers"] == 2 and "num_envs" not in renamed
    with pytest.raises(ConfigError, match="'num_envs' is the deprecated name of"):
        MAPPOConfig(num_envs=2, collector_workers=2)
