"""Tile coding (MA-PETS's discretised variant): the coder's cells, the figure-eight's feature
bounds, the TorchRL transform's specs, and the recipe acting and learning on the grid."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from torchrl.envs.utils import check_env_specs

from mapets_rl.envs import figure_eight_observation_bounds, make_env
from mapets_rl.experiment import ConfigError
from mapets_rl.modules import TileCodedObservation, TileCoder, TileCodingConfig
from mapets_rl.recipes.mapets import MAPETS, MAPETSConfig
from tests.recipes.test_recipe_mapets import tiny

OBS = ("agents", "observation")
ACTION = ("agents", "action")


def test_quantise_maps_every_point_to_the_centre_of_its_cell():
    coder = TileCoder([0.0, -5.0], [10.0, 75.0], bins=4, tilings=3)
    x = torch.rand(10_000, 2) * torch.tensor([10.0, 80.0]) + torch.tensor([0.0, -5.0])
    q = coder.quantise(x)
    cell = torch.tensor([10.0, 80.0]) / (4 * 3)  # intersection of the active tiles
    expected = (
        torch.tensor([0.0, -5.0])
        + (torch.floor((x - torch.tensor([0.0, -5.0])) / cell) + 0.5) * cell
    )
    torch.testing.assert_close(q, expected)
    assert bool(((q - x).abs() <= cell / 2 + 1e-5).all())
    torch.testing.assert_close(coder.quantise(q), q)  # idempotent
    assert coder.levels == 12
    assert len(torch.unique(q[:, 0])) == 12  # bins * tilings values per dimension


def test_tiles_identify_the_cell():
    coder = TileCoder([0.0], [1.0], bins=2, tilings=4)
    x = torch.linspace(0.0, 0.999, 200)[:, None]
    tiles = coder.tiles(x)  # [200, 1, 4]
    assert tiles.shape == (200, 1, 4) and int(tiles.min()) == 0 and int(tiles.max()) <= 2
    cells = torch.floor(x[:, 0] * 8).long()
    for i in range(200):  # same tiles in every tiling <=> same cell
        same_tiles = (tiles == tiles[i]).all(-1).all(-1)
        assert torch.equal(same_tiles, cells == cells[i])


def test_points_outside_the_box_are_clamped_onto_it():
    coder = TileCoder([0.0], [1.0], bins=2, tilings=2)
    q = coder.quantise(torch.tensor([[-3.0], [7.0]]))
    torch.testing.assert_close(q, torch.tensor([[0.125], [0.875]]))


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(low=[0.0], high=[0.0], bins=2, tilings=2), "high must exceed low"),
        (dict(low=[0.0], high=[float("inf")], bins=2, tilings=2), "finite"),
        (dict(low=[0.0], high=[1.0], bins=0, tilings=2), "bins must be >= 1"),
        (dict(low=[0.0], high=[1.0], bins=2, tilings=0), "tilings must be >= 1"),
        (dict(low=[0.0, 1.0], high=[1.0], bins=2, tilings=1), "one shape"),
    ],
)
def test_bad_coder_arguments_raise(kwargs, match):
    with pytest.raises(ValueError, match=match):
        TileCoder(**kwargs)


@pytest.mark.parametrize(
    "kwargs, field",
    [
        (dict(tilings=-1), "tilings"),
        (dict(bins=0), "bins"),
        (dict(action_bins=0), "action_bins"),
        (dict(obs_low=[0.0]), "obs_low"),
        (dict(obs_low=[0.0, 1.0], obs_high=[1.0, 0.5]), "obs_high"),
    ],
)
def test_bad_tile_coding_config_names_the_field(kwargs, field):
    with pytest.raises(ConfigError, match=field):
        TileCodingConfig(**kwargs)


@pytest.mark.parametrize(
    "env_config",
    [{"observation": "crossing"}, {"observation": "paper"}, {"lanes": 2, "n_hvs": 6}],
)
def test_figure_eight_observations_stay_inside_their_bounds(env_config):
    env = make_env("figure-eight", horizon=150, **env_config)
    low, high = figure_eight_observation_bounds(env_config)
    env.set_seed(0)
    td = env.rollout(150, break_when_any_done=False)
    obs = torch.cat([td.get(OBS), td.get(("next", *OBS))]).reshape(-1, low.size).numpy()
    assert obs.shape[1] == low.size
    assert np.all(obs >= low - 1e-4) and np.all(obs <= high + 1e-4)


def test_tile_coded_env_passes_check_env_specs_and_observes_the_grid():
    env = make_env("figure-eight", n_cavs=3, n_hvs=2, horizon=20)
    coder = TileCoder(*figure_eight_observation_bounds(), bins=4, tilings=2)
    env = env.append_transform(TileCodedObservation(coder))
    check_env_specs(env, seed=0)
    td = env.rollout(10)
    for key in (OBS, ("next", *OBS)):
        torch.testing.assert_close(coder.quantise(td.get(key)), td.get(key))


def test_tile_coded_mapets_acts_stores_and_learns_on_the_grid(tmp_path):
    config = tiny(episodes=2, seed=0).with_overrides(
        ["tile_coding.tilings=2", "tile_coding.bins=4", "tile_coding.action_bins=3"]
    )
    exp = MAPETS(config, tmp_path / "run")
    assert exp.action_coder.levels == 6 and exp.obs_coder.levels == 8
    for random_actions in (True, False):
        td = exp.run_episode(random_actions)
        obs, action = td.get(OBS), td.get(ACTION)
        torch.testing.assert_close(exp.obs_coder.quantise(obs), obs)
        torch.testing.assert_close(exp.action_coder.quantise(action), action)
        assert len(torch.unique(action)) <= 6
    entries = exp.train()
    assert [e["metrics"]["episode"] for e in entries] == [1.0, 2.0]
    data = next(iter(exp.datasets.iter_epoch(int(exp.datasets.sizes.max()))))  # [I, N]
    for key in ("observation", "next_observation"):
        torch.testing.assert_close(exp.obs_coder.quantise(data[key]), data[key])
    assert MAPETS.from_run_dir(tmp_path / "run").config.tile_coding.tilings == 2


def test_tile_coding_needs_bounds_of_the_right_length(tmp_path):
    config = MAPETSConfig(
        env_config={"n_cavs": 2, "n_hvs": 2, "horizon": 10},
        preset="cpu",
        tile_coding={"tilings": 2, "obs_low": [0.0] * 3, "obs_high": [1.0] * 3},
    )
    with pytest.raises(ConfigError, match="tile_coding.obs_low"):
        MAPETS(config, tmp_path / "run")
