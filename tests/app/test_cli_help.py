"""``mapets-rl train RECIPE --help``: the values of the chosen preset, whole sentences in plain
text, and a warm start without torch (the text is cached under a key of what it is made of)."""

from __future__ import annotations

import ast
import json
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

from mapets_rl.app import help as recipe_help_module
from tests.cli_run import run_cli

ROOT = Path(__file__).resolve().parents[2]
HEAVY = ("torch", "tensordict", "torchrl", "highway_env")


@pytest.fixture
def help_cache(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    return tmp_path / "cache" / "mapets_rl" / "help"


def _descriptions(out: str) -> list[str]:
    """Each field's description, its wrapped lines joined."""
    described: list[list[str]] = []
    for line in out.split("fields of ", 1)[1].splitlines()[2:]:
        if line.startswith("      "):
            described[-1].append(line.strip())
        else:
            described.append([])
    return [" ".join(d) for d in described if d]


@pytest.mark.parametrize(
    ("options", "population", "hidden", "which"),
    [
        ([], 400, "[300, 300, 300]", "preset 'paper', the default; preset=NAME shows another's"),
        (["preset=cpu"], 8, "[64, 64, 64]", "preset 'cpu', given on the command line"),
    ],
)
def test_mapets_help_shows_the_chosen_presets_values(
    options, population, hidden, which, help_cache, capsys
) -> None:
    code, out, err = run_cli(["train", "mapets", *options, "--help"], capsys)
    assert code == 0 and err == ""
    lines = out.splitlines()
    assert f"  (the values of {which})" in lines
    assert f"  planner.population: int = {population}" in lines
    assert f"  model.hidden: list[int] = {hidden}" in lines


def test_mapets_help_is_whole_sentences_without_markup(help_cache, capsys) -> None:
    code, out, _ = run_cli(["train", "mapets", "--help"], capsys)
    assert code == 0
    assert "``" not in out and not re.search(r":[a-z]+:`", out), out
    assert not re.search(r"\.\.\.$", out, re.MULTILINE)
    descriptions = _descriptions(out)
    assert len(descriptions) > 40
    # the longest entry is not cut: every word of its first sentence is there
    assert (
        "run each rollout step through torch.compile (inductor), which fuses its elementwise ops"
        " into a few loops around the GEMMs (CompiledStep): compiled once per run at its first "
        "decision (seconds), equal to eager planning up to floating-point reassociation; eager, "
        "with a warning, where no C++ compiler is found." in descriptions
    )
    assert all(len(line) <= recipe_help_module.WIDTH for line in out.splitlines()[1:])


def test_a_bad_option_in_recipe_help_is_one_line(help_cache, capsys) -> None:
    code, out, err = run_cli(["train", "mapets", "preset=gpu", "--help"], capsys)
    assert code == 2 and out == "" and err.count("\n") == 1 and "preset" in err


def test_the_help_is_cached_under_its_options(help_cache, capsys, monkeypatch) -> None:
    """A second call with the same options reads the cache (nothing is made again); other
    options make and keep another text."""
    first = recipe_help_module.recipe_help("mapets", ["preset=cpu"])
    assert [p.suffix for p in help_cache.iterdir()] == [".txt"]

    def made_again(*args: object) -> str:
        raise AssertionError("the help was made again")

    monkeypatch.setattr(recipe_help_module, "render_recipe_help", made_again)
    assert recipe_help_module.recipe_help("mapets", ["preset=cpu"]) == first
    monkeypatch.undo()
    monkeypatch.setenv("XDG_CACHE_HOME", str(help_cache.parents[1]))
    other = recipe_help_module.recipe_help("mapets", ["preset=cpu", "episodes=3"])
    assert "  episodes: int = 3 [episodes]" in other.splitlines()
    assert len(list(help_cache.glob("*.txt"))) == 2


def test_a_warm_recipe_help_imports_no_torch(tmp_path: Path) -> None:
    """The same help in a fresh interpreter, once made: read back without importing torch."""
    code = (
        "import json, sys\n"
        "from mapets_rl.app.cli import main\n"
        "main(['train', 'mapets', 'preset=cpu', '--help'])\n"
        f"print(json.dumps([m for m in {HEAVY!r} if m in sys.modules]))\n"
    )
    env = {**os.environ, "XDG_CACHE_HOME": str(tmp_path / "cache")}

    def run() -> tuple[str, list[str]]:
        proc = subprocess.run(
            [sys.executable, "-c", code],
            cwd=ROOT,
            env=env,
            capture_output=True,
            text=True,
            timeout=300,
            check=True,
        )
        text, _, heavy = proc.stdout.rpartition("\n[")
        return text, json.loads("[" + heavy)

    cold, cold_heavy = run()
    warm, warm_heavy = run()
    assert "torch" in cold_heavy and warm_heavy == []
    assert warm == cold and "planner.population: int = 8" in warm


def _env_config_keys(out: str) -> dict[str, str]:
    """The help's ``env_config`` keys -> what each accepts (wrapped lines joined)."""
    section = out.split("env_config keys of ", 1)[1].split("\n\n", 1)[0].splitlines()[1:]
    keys: dict[str, str] = {}
    key = ""
    for line in section:
        if line.startswith("      "):
            keys[key] += " " + line.strip()
        else:
            key, _, words = line.strip().partition(": ")
            keys[key] = words
    return keys


def test_help_lists_the_chosen_scenarios_env_config_keys_with_their_values(
    help_cache, capsys
) -> None:
    """``--env freeway``: make_env's keys (backend, num_envs) and the scenario's, each with what
    it accepts, in the words of the scenario's own refusal of a wrong value."""
    code, out, err = run_cli(["train", "mappo", "--env", "freeway", "--help"], capsys)
    assert code == 0 and err == ""
    assert "env_config keys of freeway (set as env_config.KEY=VALUE):" in out
    keys = _env_config_keys(out)
    assert keys["backend"] == "one of ['highway-env', 'torch'] (default 'highway-env')"
    assert keys["num_envs"].startswith("None (one road) or an integer >= 1")
    assert keys["shield"] == "True or False; default False"
    assert keys["team_reward"] == "True or False; default False"
    assert keys["velocity_weight"] == "a finite number; default 0.1"
    assert keys["lane_change_comfort"] == "a finite number >= 0 and <= 3; default 1.0"
    assert keys["n_vehicles"] == "an integer >= 1; default 30"
    # the figure-eight (the default scenario of MA-PETS) has no batched backend
    code, out, _ = run_cli(["train", "mapets", "--help"], capsys)
    keys = _env_config_keys(out)
    assert code == 0 and "num_envs" not in keys
    assert keys["backend"] == "one of ['highway-env', 'sumo'] (default 'highway-env')"
    assert keys["lanes"] == "1 or 2; default 1"


def test_help_of_a_plugin_scenario_names_its_factory(help_cache, toy_recipe, capsys) -> None:
    code, out, _ = run_cli(["train", "toy", "--env", "toy", "--help"], capsys)
    assert code == 0
    assert "env_config keys of toy: the keyword arguments of its factory" in out.splitlines()


def test_the_refusal_of_an_unknown_env_config_key_lists_every_accepted_key(
    tmp_path, capsys
) -> None:
    """It listed the scenario's 35 keys but not backend or num_envs, which work."""
    argv = ["train", "mappo", "--env", "freeway", "--run-dir", str(tmp_path / "run")]
    code, _, err = run_cli([*argv, "env_config.bogus=1"], capsys)
    assert code == 2 and err.count("\n") == 1
    assert "unknown config key(s) ['bogus'] for scenario 'freeway'; accepted keys:" in err
    accepted = ast.literal_eval(err.split("accepted keys: ", 1)[1].strip())
    from mapets_rl.envs.factory import env_config_keys

    assert accepted == env_config_keys("freeway")
    assert {"backend", "num_envs", "dtype", "kernel", "seed", "render_mode"} <= set(accepted)
    assert {"shield", "team_reward", "velocity_weight", "n_vehicles"} <= set(accepted)
    assert not (tmp_path / "run").exists()
