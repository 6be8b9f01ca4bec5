"""The published SUMO configurations of the figure-eights (the MA-PETS paper's Figs. 3-4 on
SUMO, issue 54): each is its scenario's MA-PETS setting on the SUMO back end, and differs from
its highway-env twin in the back end only."""

from __future__ import annotations

import pytest

from mapets_rl.experiment.published import available_configs, load_published

SCENARIOS = ("figure-eight", "figure-eight-multilane")
BUDGET = {"figure-eight": 3000, "figure-eight-multilane": 6000}
"""MA-PETS's 15 episodes of 200 (one lane) and 400 (two lanes) steps, in frames."""
MODEL_FREE = ("dqn", "firl", "maddpg", "mappo", "sac", "svmix")
TWINNED = ("mapets", *MODEL_FREE)
"""The recipes whose highway-env figure-eight config the SUMO one includes: all of them."""


def sumo_name(scenario: str, recipe: str) -> str:
    """The published name of ``recipe``'s SUMO config on ``scenario``."""
    return f"{scenario}/{recipe}-sumo"


def test_every_recipe_of_the_figures_has_a_sumo_config_on_both_figure_eights() -> None:
    names = {c.name for c in available_configs()}
    for scenario in SCENARIOS:
        for recipe in ("mapets", *MODEL_FREE):
            assert sumo_name(scenario, recipe) in names
            assert load_published(sumo_name(scenario, recipe)).recipe == recipe


@pytest.mark.parametrize("scenario", SCENARIOS)
@pytest.mark.parametrize("recipe", ("mapets", *MODEL_FREE))
def test_a_sumo_config_is_the_mapets_scenario_on_sumo(scenario: str, recipe: str) -> None:
    """The same CAVs, episode length and observation as MA-PETS's config, on SUMO; the
    model-free ones at MA-PETS's budget, one episode per batch, evaluated every episode."""
    fields = load_published(sumo_name(scenario, recipe)).fields
    mapets = load_published(f"{scenario}/mapets").fields
    assert fields["env"] == scenario
    assert fields["env_config"] == {**mapets["env_config"], "backend": "sumo"}
    if recipe != "mapets":
        horizon = mapets["env_config"]["horizon"]
        assert fields["total_frames"] == BUDGET[scenario] == mapets["episodes"] * horizon
        assert fields["frames_per_batch"] == fields["eval_interval"] == horizon


@pytest.mark.parametrize("scenario", SCENARIOS)
@pytest.mark.parametrize("recipe", TWINNED)
def test_a_twinned_sumo_config_differs_from_its_highway_env_one_in_the_back_end_only(
    scenario: str, recipe: str
) -> None:
    sumo = load_published(sumo_name(scenario, recipe)).fields
    highway = load_published(f"{scenario}/{recipe}").fields
    assert {k for k in sumo.keys() | highway.keys() if sumo.get(k) != highway.get(k)} == {
        "env_config"
    }
    assert sumo["env_config"] == {**highway["env_config"], "backend": "sumo"}
    assert "backend" not in highway["env_config"]
