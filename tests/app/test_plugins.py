"""The library never imports its applications: recipes and extra scenarios come from entry
points (``mapets_rl.recipes``, ``mapets_rl.scenarios``), and ``mapets-rl --help`` imports
neither recipes nor torch."""

from __future__ import annotations

import importlib
import inspect
import json
import subprocess
import sys
from importlib import metadata
from pathlib import Path

import pytest

from mapets_rl.app.plugins import RECIPE_GROUP, available_recipes, entry_points, load_recipe
from mapets_rl.envs.registry import SCENARIO_GROUP
from mapets_rl.experiment import Experiment, available_envs, build_env, read_results, register_env
from tests.cli_run import run_cli
from tests.test_architecture import project_imports

ROOT = Path(__file__).resolve().parents[2]


# ------------------------------------------------------------------------ import direction
def test_the_library_never_imports_recipes() -> None:
    offenders = [
        f"{path.relative_to(ROOT)}: {name}"
        for path in sorted((ROOT / "mapets_rl").rglob("*.py"))
        for _line, name in project_imports(path)
        if name == "recipes" or name.startswith("recipes.")
    ]
    assert offenders == []


def test_help_imports_neither_recipes_nor_torch() -> None:
    code = (
        "import sys\n"
        "from mapets_rl.app.cli import main\n"
        "for argv in (['--help'], ['train', '--help']):\n"
        "    try:\n"
        "        main(argv)\n"
        "    except SystemExit:\n"
        "        pass\n"
        "loaded = sorted(m for m in sys.modules if m.split('.')[0] in ('recipes', 'torch'))\n"
        "print('LOADED', loaded)\n"
    )
    proc = subprocess.run(
        [sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=120
    )
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.splitlines()[-1] == "LOADED []"


# ------------------------------------------------------------------------------ recipes
def _recipe_classes() -> dict[str, str]:
    """``{Experiment.name: "recipes.<module>:<Class>"}`` of every recipe defined in recipes/."""
    found = {}
    for path in sorted((ROOT / "recipes").glob("*.py")):
        if path.name.startswith("_"):
            continue
        module = importlib.import_module(f"recipes.{path.stem}")
        for cls_name, cls in inspect.getmembers(module, inspect.isclass):
            if issubclass(cls, Experiment) and cls.__module__ == module.__name__:
                found[cls.name] = f"{module.__name__}:{cls_name}"
    return found


def test_pyproject_declares_exactly_the_recipes_of_the_recipes_package() -> None:
    tomllib = pytest.importorskip("tomllib")  # Python >= 3.11
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    declared = project["entry-points"][RECIPE_GROUP]
    assert declared == _recipe_classes()
    assert set(declared) == {
        "coma",
        "dqn",
        "firl",
        "m3ddpg",
        "maddpg",
        "mapets",
        "mappo",
        "sac",
        "shapley_ac",
        "svmix",
    }
    for name, value in declared.items():
        assert metadata.EntryPoint(name=name, value=value, group=RECIPE_GROUP).load().name == name


def test_recipes_are_loaded_from_entry_points(add_entry_point) -> None:
    add_entry_point(RECIPE_GROUP, "toy", "toy_recipe:ToyLearner")
    import toy_recipe

    assert "toy" in available_recipes()
    assert load_recipe("toy") is toy_recipe.ToyLearner


def test_unknown_recipe_names_the_installed_ones(add_entry_point, capsys) -> None:
    add_entry_point(RECIPE_GROUP, "zz_first", "toy_recipe:ToyLearner")
    add_entry_point(RECIPE_GROUP, "zz_second", "toy_recipe:ToyLearner")
    with pytest.raises(
        ValueError,
        match=r"unknown recipe 'nope' \(choose from: .*zz_first, "
        r"zz_second\)",
    ):
        load_recipe("nope")
    code, _, err = run_cli(["train", "nope", "--env", "figure-eight"], capsys)
    assert code == 2 and err.count("\n") == 1
    assert err.startswith("mapets-rl: error: unknown recipe 'nope' (choose from: ")
    assert "zz_first, zz_second" in err


def test_no_installed_recipe_says_to_reinstall(monkeypatch, capsys) -> None:
    monkeypatch.setattr(metadata, "entry_points", lambda **params: metadata.EntryPoints([]))
    code, _, err = run_cli(["train", "mappo", "--env", "figure-eight"], capsys)
    assert code == 2 and err.count("\n") == 1
    assert "no recipes are registered" in err and "pip install -e ." in err


def test_unimportable_recipe_is_one_line(add_entry_point, capsys) -> None:
    add_entry_point(RECIPE_GROUP, "ghost", "no_such_module_here:Ghost")
    code, _, err = run_cli(["train", "ghost", "--env", "figure-eight"], capsys)
    assert code == 2 and err.count("\n") == 1
    assert "recipe 'ghost' (no_such_module_here:Ghost) cannot be imported" in err


def test_a_recipe_seen_twice_counts_once_and_a_clash_is_refused(add_entry_point) -> None:
    add_entry_point(RECIPE_GROUP, "toy", "toy_recipe:ToyLearner")
    add_entry_point(RECIPE_GROUP, "toy", "toy_recipe:ToyLearner")
    assert available_recipes().count("toy") == 1
    add_entry_point(RECIPE_GROUP, "toy", "toy_recipe:ToyConfig")
    with pytest.raises(
        ValueError,
        match="'toy' is declared twice, as 'toy_recipe:ToyLearner' and 'toy_recipe:ToyConfig'",
    ):
        entry_points(RECIPE_GROUP)


def test_train_recipe_help_lists_its_fields(toy_recipe, capsys) -> None:
    code, out, _ = run_cli(["train", "toy", "--help"], capsys)
    assert code == 0 and out.startswith("usage: mapets-rl train toy --env SCENARIO")
    assert "  lr: float = 0.05\n      step size of the policy regression (> 0).\n" in out
    assert "  env_config: dict[str, Any] = {}\n" in out
    # a unit declared by the field's metadata, and one inherited from ExperimentConfig
    assert "  batch_size: int = 16 [observations]\n" in out
    assert "  total_frames: int = 60 [frames]\n      environment steps to train for" in out
    # the scenarios with the recipe's actions (the toy env's are continuous)
    scenarios = out.split("scenarios (continuous or discrete actions; --env SCENARIO):\n")[1]
    assert "  toy (3 agents, obs 2, continuous actions)" in scenarios.split("\n\n")[0].splitlines()


def test_train_mapets_help_lists_sections_units_and_scenarios(capsys) -> None:
    code, out, _ = run_cli(["train", "mapets", "--help"], capsys)
    assert code == 0
    lines = out.splitlines()
    assert "  planner.horizon: int = 25 [steps]" in lines
    assert lines[lines.index("  planner.horizon: int = 25 [steps]") + 1].startswith(
        "      MPC horizon w"
    )
    assert "  comm.comm_range: float = 100.0 [m]" in lines
    assert "  model.hidden: list[int] = [300, 300, 300]" in lines  # the paper preset's
    assert "  planner_reward.collision_gap: float = 2.0 [m]" in lines
    assert "  episodes: int = 15 [episodes]" in lines
    supported, unsupported = out.split("not supported:\n")
    assert "figure-eight (8 agents, obs 10, continuous actions)" in supported
    assert "freeway (30 agents, obs 22, discrete actions)" in unsupported.split("\n\n")[0]


# ---------------------------------------------------------------------------- scenarios
@pytest.fixture
def plugin_scenario(add_entry_point) -> str:
    """``ToyAgentsEnv`` installed as scenario ``toy-plugin`` (not registered in-process)."""
    add_entry_point(SCENARIO_GROUP, "toy-plugin", "toy_scenario:ToyAgentsEnv")
    return "toy-plugin"


def test_installed_scenario_is_available_and_built(plugin_scenario: str, toy_scenario) -> None:
    assert plugin_scenario in available_envs()
    assert {"figure-eight", "freeway", "toy"} <= set(available_envs())
    env = build_env(plugin_scenario, {"n_agents": 2, "horizon": 4})
    assert env.full_observation_spec["agents", "observation"].shape == (2, 2)
    with pytest.raises(ValueError, match="'toy-plugin' is an installed scenario"):
        register_env(plugin_scenario, lambda: None)


def test_installed_scenario_trains_and_resumes_from_the_cli(
    plugin_scenario: str, toy_recipe, tmp_path: Path, capsys
) -> None:
    run = tmp_path / "run"
    code, out, err = run_cli(
        [
            "train",
            "toy",
            "--env",
            plugin_scenario,
            "--run-dir",
            str(run),
            "total_frames=20",
            "env_config.n_agents=2",
        ],
        capsys,
    )
    assert code == 0, err
    code, out, err = run_cli(["resume", str(run), "total_frames=40"], capsys)
    assert code == 0, err
    assert json.loads(out.splitlines()[-1])["frames"] == 40
    results = read_results(run)
    assert results["env"] == plugin_scenario
    assert [e["frames"] for e in results["evaluations"]] == [20, 40]


def test_builtin_scenarios_win_over_an_installed_one_of_the_same_name(add_entry_point) -> None:
    add_entry_point(SCENARIO_GROUP, "figure-eight", "no_such_module_here:make")
    env = build_env("figure-eight", {"n_cavs": 2, "n_hvs": 1, "horizon": 5})
    assert env.full_observation_spec["agents", "observation"].shape[0] == 2


# --------------------------------------------------- the README's traffic-scenario recipe
def test_readme_traffic_scenario_has_positions_where_mapets_reads_them() -> None:
    """A MultiAgentTrafficEnv subclass wrapped with ``wrap_pettingzoo`` writes the CAVs'
    positions under ``("agents", "position")`` (the stock PettingZooWrapper does not: MA-PETS'
    CommunicationRange failed with KeyError 'position')."""
    from torchrl.envs.utils import check_env_specs
    from traffic_scenario import StopAndGoParallelEnv, make_stop_and_go

    from mapets_rl.envs import wrap_pettingzoo

    env = make_stop_and_go(n_cavs=2, n_hvs=2, horizon=5)
    check_env_specs(env)
    td = env.rollout(3)
    position = td["next", "agents", "position"]
    assert position.shape == (3, 2, 2) and bool((position[1:, :, 0] > position[:-1, :, 0]).all())
    with pytest.raises(ValueError, match="parallel_env must be a pettingzoo.ParallelEnv"):
        wrap_pettingzoo(StopAndGoParallelEnv(horizon=5).env)


TINY_MAPETS = [
    "episodes=2",
    "env_config.horizon=15",
    "env_config.n_cavs=2",
    "env_config.n_hvs=2",
    "planner.horizon=4",
    "planner.population=8",
    "planner.elites=2",
    "planner.iterations=1",
    "model.epochs=2",
    "model.hidden=[16,16]",
    "progress=false",
]


def test_plugin_traffic_scenario_and_mapets_recipe_from_the_cli(
    add_entry_point, tmp_path: Path, capsys
) -> None:
    """The example's scenario and MA-PETS recipe, installed as entry points, train, resume
    and evaluate through ``mapets-rl`` (nothing registered in-process)."""
    add_entry_point(SCENARIO_GROUP, "stop-and-go", "traffic_scenario:make_stop_and_go")
    add_entry_point(RECIPE_GROUP, "mapets-stop-and-go", "traffic_scenario:StopAndGoMAPETS")
    run = tmp_path / "run"
    argv = ["train", "mapets-stop-and-go", "--env", "stop-and-go", "--run-dir", str(run)]
    code, out, err = run_cli([*argv, *TINY_MAPETS], capsys)
    assert code == 0, err
    assert json.loads(out.splitlines()[-1])["frames"] == 30
    code, out, err = run_cli(["resume", str(run), "episodes=3"], capsys)
    assert code == 0, err
    assert json.loads(out.splitlines()[-1])["frames"] == 45
    code, out, err = run_cli(["evaluate", str(run), "--episodes", "1"], capsys)
    assert code == 0, err
    printed = json.loads(out.splitlines()[-1])
    metrics = printed["metrics"]
    assert 0.0 <= metrics["safety"] <= 1.0 and metrics["length"] == 15
    assert printed["units"]["agility"] == "m/step" and printed["units"]["length"] == "steps"
    results = read_results(run)
    assert results["env"] == "stop-and-go" and results["recipe"] == "mapets-stop-and-go"
    assert [e["metrics"]["episode"] for e in results["train"]] == [1.0, 2.0, 3.0]
