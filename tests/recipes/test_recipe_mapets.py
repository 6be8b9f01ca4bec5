"""MA-PETS recipe: end-to-end episodes, metrics, checkpoints, exact resume, config validation."""

from __future__ import annotations

import csv
import json
import textwrap

import pytest
import torch
import yaml

from mapets_rl.app.cli import main as cli_main
from mapets_rl.experiment import ConfigError, latest_checkpoint, load_checkpoint
from mapets_rl.recipes.mapets import MAPETS, MAPETSConfig

TINY = dict(
    env_config={"n_cavs": 3, "n_hvs": 2, "horizon": 20},
    preset="cpu",
    planner={"horizon": 3, "population": 8, "elites": 2, "iterations": 2, "particles": 5},
    model={"hidden": [16], "buffer_size": 64, "batch_size": 16, "epochs": 2},
    num_threads=1,
    progress=False,
)


def tiny(**overrides) -> MAPETSConfig:
    return MAPETSConfig(**{**TINY, **overrides})


@pytest.fixture(scope="module")
def two_episodes(tmp_path_factory):
    run_dir = tmp_path_factory.mktemp("mapets") / "run"
    exp = MAPETS(tiny(episodes=2, seed=3), run_dir)
    params_before = [p.detach().clone() for p in exp.model.parameters()]
    seen = []
    exp.train(on_episode_end=seen.append)
    return exp, run_dir, params_before, seen


def test_two_episodes_write_metrics_and_checkpoint(two_episodes):
    exp, run_dir, params_before, seen = two_episodes
    assert [m["episode"] for m in seen] == [1.0, 2.0]
    assert [m["random"] for m in seen] == [1.0, 0.0]  # episode 1 random, then the planner
    results = json.loads((run_dir / "results.json").read_text())
    assert results["recipe"] == "mapets"
    entries = results["train"]
    assert [e["metrics"]["episode"] for e in entries] == [1.0, 2.0]
    frames = [e["frames"] for e in entries]
    assert frames[0] == entries[0]["metrics"]["length"] and frames[1] > frames[0]
    for entry in entries:
        m = entry["metrics"]
        assert 0.0 <= m["safety"] <= 1.0 and m["agility"] >= 0.0
        assert 0 < m["transitions_stored"] <= 3 * 20
        assert m["transitions_shared"] >= 0 and torch.isfinite(torch.tensor(m["model_nll"]))
    # CSV logger (the default) wrote one row per episode
    with open(next(run_dir.glob("logs/*/scalars/train/safety.csv"))) as fh:
        assert len(list(csv.reader(fh))) == 2
    ckpt = latest_checkpoint(run_dir)
    assert ckpt is not None
    state = load_checkpoint(ckpt)  # weights_only=True
    assert state["recipe"] == "mapets" and state["components"]["counters"]["episode"] == 2
    # the ensembles trained
    changed = [
        not torch.equal(a, b) for a, b in zip(params_before, exp.model.parameters(), strict=True)
    ]
    assert all(changed)
    # every CAV's dataset holds its own stored transitions (+ what neighbours sent)
    stored = sum(m["transitions_stored"] for m in seen)
    assert int(exp.datasets.sizes.sum()) >= min(stored, 3 * 64)


def test_resume_continues_at_episode_3_like_an_uninterrupted_run(two_episodes, tmp_path):
    _, run_dir, _, _ = two_episodes
    resumed = MAPETS.from_run_dir(run_dir, overrides=["episodes=3"])
    assert resumed.episode == 2
    seen = []
    resumed.train(on_episode_end=seen.append)
    assert [m["episode"] for m in seen] == [3.0]
    entries = json.loads((run_dir / "results.json").read_text())["train"]
    assert [e["metrics"]["episode"] for e in entries] == [1.0, 2.0, 3.0]

    straight = MAPETS(tiny(episodes=3, seed=3), tmp_path / "straight")
    straight.train()
    ref = straight.results.train
    for key in ("agility", "safety", "reward", "transitions_shared", "model_nll"):
        assert entries[2]["metrics"][key] == pytest.approx(ref[2]["metrics"][key], rel=1e-5)
    for a, b in zip(resumed.model.parameters(), straight.model.parameters(), strict=True):
        torch.testing.assert_close(a, b)


def test_bf16_planner_resumes_like_an_uninterrupted_run(tmp_path):
    """The bf16 planner (``dtype="auto"`` on AVX512-BF16 CPUs) plans with the weights trained
    in this process exactly as with the same weights loaded from a checkpoint."""
    planner = {**TINY["planner"], "dtype": "bf16"}
    first = MAPETS(tiny(episodes=2, seed=3, planner=planner), tmp_path / "run")
    first.train()
    resumed = MAPETS.from_run_dir(tmp_path / "run", overrides=["episodes=3"])
    resumed.train()
    straight = MAPETS(tiny(episodes=3, seed=3, planner=planner), tmp_path / "straight")
    straight.train()
    got, ref = (r.results.train[2]["metrics"] for r in (resumed, straight))
    timings = {k for k in ref if k.endswith("_time")}
    assert timings and {k: v for k, v in got.items() if k not in timings} == {
        k: v for k, v in ref.items() if k not in timings
    }


def test_d0_shares_nothing_and_d_inf_shares(tmp_path):
    exp = MAPETS(tiny(episodes=1, comm={"comm_range": 0.0}), tmp_path / "d0")
    (metrics,) = [e["metrics"] for e in exp.train()]
    assert metrics["transitions_shared"] == 0
    sizes = exp.datasets.sizes
    assert int(sizes.sum()) == metrics["transitions_stored"]
    exp = MAPETS(tiny(episodes=1, comm={"comm_range": float("inf")}), tmp_path / "dinf")
    (metrics,) = [e["metrics"] for e in exp.train()]
    # CAVs still driving at the end send their episode to the other two
    assert metrics["transitions_shared"] > 0


def test_cli_train_mapets(tmp_path, capsys):
    run_dir = tmp_path / "cli"
    args = [
        "train",
        "mapets",
        "--env",
        "figure-eight",
        "--run-dir",
        str(run_dir),
        "episodes=1",
        "random_episodes=1",
        "preset=cpu",
        "model.hidden=[8]",
        "planner.horizon=2",
        "planner.population=4",
        "planner.elites=1",
        "planner.iterations=1",
        "env_config.n_cavs=2",
        "env_config.n_hvs=1",
        "env_config.horizon=5",
        "progress=false",
        "num_threads=1",
    ]
    assert cli_main(args) == 0
    out = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert out["metrics"]["episode"] == 1.0 and 0 <= out["metrics"]["safety"] <= 1
    config = MAPETSConfig.from_yaml(run_dir / "config.yaml")
    assert config.model.hidden == [8] and config.planner.population == 4
    assert config.planner.particles == 5


def test_presets_resolve_and_explicit_fields_win():
    paper = MAPETSConfig()
    plan, model = paper.planner, paper.model
    assert (
        plan.horizon,
        plan.population,
        plan.elites,
        plan.iterations,
        plan.particles,
        model.ensemble_size,
        model.hidden,
    ) == (25, 400, 40, 5, 20, 5, [300, 300, 300])
    assert (model.buffer_size, model.batch_size, model.epochs, model.lr) == (2048, 128, 5, 1e-3)
    assert paper.episodes == 15 and paper.comm.comm_range == 100.0 and paper.random_episodes == 1
    cpu = MAPETSConfig(preset="cpu", planner={"horizon": 15})
    assert (cpu.planner.horizon, cpu.planner.population, cpu.model.hidden, cpu.model.epochs) == (
        15,
        8,
        [64, 64, 64],
        30,
    )
    assert cpu.planner.compile and not paper.planner.compile
    assert cpu.with_overrides(["model.lr=3e-4"]).planner.horizon == 15


@pytest.mark.parametrize("value", ["cpu", '"cpu"', "'cpu'"])
def test_a_preset_override_resizes_however_its_value_is_quoted(value: str) -> None:
    """``mapets-rl sweep --config`` passes a file's fields as JSON (``preset="cpu"``); a quoted
    preset must resize the planner and the model as the bare one does, not leave the paper's."""
    config = MAPETSConfig().with_overrides([f"preset={value}"])
    assert config.preset == "cpu"
    assert (config.planner.population, config.model.hidden) == (8, [64, 64, 64])


@pytest.mark.parametrize(
    ("field", "value"),
    [
        ("episodes", 0),
        ("comm.comm_range", -1.0),
        ("comm.p_fail", 1.5),
        ("preset", "gpu"),
        ("planner.elites", 500),
        ("planner.particles", 7),
        ("model.hidden", []),
        ("planner.propagation", "ts2"),
        ("model.lr", 0.0),
        ("model.batch_size", 0),
        ("model.epochs", 0),
        ("planner.alpha", 1.0),
        ("num_envs", 2),
        ("planner_reward.collision_reward", 5.0),
        ("planner_reward.collision_gap", -1.0),
        ("planner_reward.headway", 11.0),
    ],
)
def test_bad_config_raises_naming_the_field(field, value):
    section, _, leaf = field.rpartition(".")
    with pytest.raises(ValueError, match=field) as err:
        MAPETSConfig(**({section: {leaf: value}} if section else {field: value}))
    assert isinstance(err.value, ConfigError)


def test_discrete_env_is_rejected(tmp_path):
    with pytest.raises(ValueError, match="continuous actions"):
        MAPETS(
            tiny(env="freeway", env_config={"n_vehicles": 4, "cav_ratio": 0.5}),
            tmp_path / "freeway",
        )


def test_transitions_whose_neighbours_changed_stay_out_of_the_datasets(tmp_path):
    exp = MAPETS(tiny(episodes=1, comm={"comm_range": 0.0}, seed=5), tmp_path / "run")
    rollout = exp.run_episode(random_actions=True)
    changed = torch.zeros_like(rollout["next", "agents", "info", "neighbour_changed"])
    changed[:, 0] = True  # agent 0: every step had a new neighbour
    changed[0, 1] = True  # agent 1: the first step only
    rollout["next", "agents", "info", "neighbour_changed"] = changed
    driving = rollout["agents", "mask"] & ~rollout["next", "agents", "terminated"].squeeze(-1)
    stats = exp.store_and_share(rollout)
    sizes = exp.datasets.sizes
    assert sizes[0] == 0  # d = 0: nothing received either
    assert sizes[1] == int(driving[:, 1].sum()) - int(driving[0, 1])
    assert sizes[2] == int(driving[:, 2].sum())
    assert stats["transitions_filtered"] == int(driving[:, 0].sum()) + int(driving[0, 1])


@pytest.mark.parametrize("field", MAPETSConfig.retired_fields)
def test_config_has_no_frame_budget(field):
    with pytest.raises(ConfigError, match=f"unknown config key '{field}' for MAPETSConfig"):
        MAPETSConfig(**{field: 1})


def test_run_with_retired_frame_budget_keys_resumes_and_keeps_its_guard(tmp_path):
    run_dir = tmp_path / "run"
    exp = MAPETS(tiny(episodes=1), run_dir)
    assert exp.env.transform is exp.comm  # the communication transform drives the env
    exp.train()
    # config.yaml as MA-PETS wrote it while it inherited the frame budget
    path = run_dir / "config.yaml"
    old = {**yaml.safe_load(path.read_text()), "total_frames": 3000, "num_envs": 1}
    path.write_text(yaml.safe_dump(old, sort_keys=False))
    resumed = MAPETS.from_run_dir(run_dir, overrides=["episodes=2"])
    assert resumed.episode == 1
    assert "total_frames" not in yaml.safe_load(path.read_text())
    assert [m["episode"] for m in [e["metrics"] for e in resumed.train()]] == [1.0, 2.0]
    # resuming did not lift the guard against a second run in the same directory
    with pytest.raises(ValueError, match="already holds a run with checkpoints"):
        MAPETS(tiny(episodes=1), run_dir)


def test_dotted_overrides_reach_the_nested_sections():
    config = tiny().with_overrides(
        ["planner.horizon=25", "model.hidden=[32,32]", "comm.comm_range=inf", "planner.alpha=0.2"]
    )
    assert config.planner.horizon == 25 and config.planner.alpha == 0.2
    assert config.model.hidden == [32, 32] and config.comm.comm_range == float("inf")
    assert config.planner.population == 8  # the other fields are kept
    # preset=paper re-fills the fields that still hold the cpu preset's values only
    paper = MAPETSConfig(preset="cpu", planner={"horizon": 15}).with_overrides(["preset=paper"])
    assert (paper.planner.horizon, paper.planner.population, paper.model.hidden) == (
        15,
        400,
        [300, 300, 300],
    )


def test_yaml_round_trip_keeps_the_nested_sections(tmp_path):
    config = tiny(comm={"comm_range": float("inf"), "p_fail": 0.25})
    path = tmp_path / "config.yaml"
    config.to_yaml(path)
    on_disk = yaml.safe_load(path.read_text())
    assert on_disk["planner"]["horizon"] == 3 and on_disk["model"]["hidden"] == [16]
    assert on_disk["comm"] == {"comm_range": float("inf"), "p_fail": 0.25, "share_plans": False}
    assert "horizon" not in on_disk and "comm_range" not in on_disk
    assert MAPETSConfig.from_yaml(path) == config


@pytest.mark.parametrize(
    "override", ["planner.bogus=1", "model.widths=[8]", "comm.range=5", "planner.horizon.x=1"]
)
def test_an_unknown_nested_key_is_a_one_line_error_naming_it(override):
    key = override.partition("=")[0]
    with pytest.raises(ConfigError) as err:
        tiny().with_overrides([override])
    assert "\n" not in str(err.value)
    assert key.rsplit(".", 1)[0] in str(err.value)
    if key.count(".") == 1:
        assert f"unknown config key '{key}'" in str(err.value)
    with pytest.raises(ConfigError, match="unknown config key 'planner.bogus'"):
        MAPETSConfig(planner={"bogus": 1})


@pytest.mark.parametrize(
    ("section", "field", "value", "allowed"),
    [
        ("planner", "epsilon", float("nan"), "a finite number"),
        ("model", "lr", float("nan"), "a finite number"),
        ("model", "logvar_bound_coef", float("inf"), "a finite number"),
        ("comm", "comm_range", float("nan"), r"a number \(inf allowed\), not NaN"),
        ("comm", "p_fail", float("nan"), "a finite number"),
    ],
)
def test_nan_in_a_nested_field_is_rejected(section, field, value, allowed):
    with pytest.raises(ConfigError, match=rf"^{section}\.{field} must be {allowed}"):
        MAPETSConfig(**{section: {field: value}})
    with pytest.raises(ConfigError, match=rf"{section}\.{field} must be {allowed}"):
        tiny().with_overrides([f"{section}.{field}={value}"])


def test_run_with_flat_field_names_resumes_with_nested_sections(tmp_path, caplog):
    run_dir = tmp_path / "run"
    MAPETS(tiny(episodes=1, comm={"comm_range": 50.0}), run_dir).train()
    path = run_dir / "config.yaml"
    nested = yaml.safe_load(path.read_text())
    # config.yaml as MA-PETS wrote it before the sections: flat planner/model/comm names
    flat = {k: v for k, v in nested.items() if k not in ("planner", "model", "comm")}
    flat.update(nested["planner"], **nested["model"], **nested["comm"])
    flat["cem_momentum"] = flat.pop("alpha")
    newer_planner = ("noise_beta", "keep_elites", "shift_elites", "population_decay", "compile")
    newer_planner += ("optimizer",)
    newer_model = ("holdout", "patience", "min_improvement")
    for newer in ("dtype", "anchor_candidates", "keep_best", "cuda_graph", *newer_planner):
        del flat[newer]  # flat config.yaml files predate these planner fields
    for newer in newer_model:
        del flat[newer]  # ... and these model fields
    del flat["share_plans"]  # ... and plan sharing
    path.write_text(yaml.safe_dump(flat, sort_keys=False))
    with caplog.at_level("WARNING", logger="mapets_rl"):
        resumed = MAPETS.from_run_dir(run_dir, overrides=["episodes=2"])
    warnings = [r.getMessage() for r in caplog.records if "flat MA-PETS field names" in r.message]
    assert len(warnings) == 1 and "\n" not in warnings[0]
    assert "cem_momentum" in warnings[0] and "planner.alpha" in warnings[0]
    assert resumed.episode == 1
    assert resumed.config.planner.horizon == 3 and resumed.config.model.hidden == [16]
    assert resumed.config.comm.comm_range == 50.0
    assert yaml.safe_load(path.read_text())["planner"] == nested["planner"]  # rewritten nested
    assert [m["episode"] for m in [e["metrics"] for e in resumed.train()]] == [1.0, 2.0]


def test_readme_loss_snippet_trains_mapets(tmp_path):
    """The README's "a model or loss" snippet, run as written: MA-PETS fits its ensembles with
    the snippet's loss (read from the "agents" keys through ``make_loss``)."""
    import re
    from pathlib import Path

    readme = (Path(__file__).resolve().parents[2] / "README.md").read_text()
    (block,) = [
        textwrap.dedent(b)
        for b in re.findall(r"```python\n(.*?)```", readme, re.S)
        if "def make_loss" in b
    ]
    namespace: dict = {}
    exec(compile(block, "README.md", "exec"), namespace)
    exp = namespace["MAPETSWithMSE"](tiny(episodes=2, seed=0), tmp_path / "run")
    assert type(exp.loss).__name__ == "EnsembleMeanLoss"
    before = [p.detach().clone() for p in exp.model.weights]
    (_, second) = [e["metrics"] for e in exp.train()]
    assert all(not torch.equal(a, b) for a, b in zip(before, exp.model.weights, strict=True))
    assert second["model_nll"] < second["model_nll_first_epoch"]  # the squared error fell


def test_a_scenario_without_a_planner_reward_needs_reward_fn(tmp_path, monkeypatch):
    """The figure-eight's reward is the figure-eight scenarios' own: a scenario registered
    without one (here the figure-eight itself under another name, so its observations would
    fit) is refused before the run directory exists unless ``reward_fn`` is given."""
    import functools

    from mapets_rl.envs import FigureEightPlannerReward, make_env, registry

    monkeypatch.setattr(registry, "_SCENARIOS", dict(registry._SCENARIOS))
    registry.register_env("my-loop", functools.partial(make_env, "figure-eight"))
    config = tiny(env="my-loop")
    run_dir = tmp_path / "run"
    with pytest.raises(ValueError, match="reward_fn is required for env 'my-loop'"):
        MAPETS(config, run_dir)
    assert not run_dir.exists()
    assert config.planner_reward is None
    reward = FigureEightPlannerReward().reward
    exp = MAPETS(config, run_dir, reward_fn=reward)
    assert exp.reward_fn is reward and exp.termination_fn is None
    exp.close()
    # the shell path: the reward named in the config, resolved by import
    shell = config.with_overrides(["reward_fn=tests.recipes.test_recipe_mapets:speed_reward"])
    exp = MAPETS(shell, tmp_path / "shell")
    assert exp.reward_fn is speed_reward and exp.termination_fn is None
    assert exp.planner.reward_fn is speed_reward
    exp.close()
    assert MAPETSConfig.from_yaml(tmp_path / "shell" / "config.yaml").reward_fn == (
        "tests.recipes.test_recipe_mapets:speed_reward"
    )
    scenario = registry.registered_scenario("figure-eight")
    assert scenario.planner_reward is FigureEightPlannerReward


def speed_reward(obs: torch.Tensor, action: torch.Tensor, next_obs: torch.Tensor) -> torch.Tensor:
    """A custom planner reward for the ``reward_fn`` config field: the predicted speed."""
    return next_obs[..., 0]


def test_planner_reward_is_the_scenarios_section_set_from_overrides(tmp_path):
    from mapets_rl.envs import FigureEightPlannerReward

    config = tiny().with_overrides(["planner_reward.headway=0.3"])
    assert config.planner_reward == FigureEightPlannerReward(headway=0.3)
    assert config.to_dict()["planner_reward"]["headway"] == 0.3
    exp = MAPETS(config, tmp_path / "run")
    assert exp.reward_fn == config.planner_reward.reward
    assert exp.termination_fn == config.planner_reward.collision
    exp.close()
    assert MAPETSConfig().planner_reward == FigureEightPlannerReward()


def test_a_new_env_starts_from_its_own_planner_reward_section():
    from mapets_rl.envs import FigureEightPlannerReward

    # how the CLI and sweeps build a config: the default one with env=... applied
    assert MAPETSConfig().with_overrides(["env=freeway"]).planner_reward is None
    freeway = MAPETSConfig(env="freeway")
    assert freeway.with_overrides(["env=figure-eight"]).planner_reward == (
        FigureEightPlannerReward()
    )
    shifted = freeway.with_overrides(["env=figure-eight", "planner_reward.headway=0.3"])
    assert shifted.planner_reward == FigureEightPlannerReward(headway=0.3)
    # the same section on both figure-eights: the settings are kept
    short = MAPETSConfig(planner_reward={"headway": 0.3})
    assert short.with_overrides(["env=figure-eight-multilane"]).planner_reward.headway == 0.3


def test_old_flat_planner_reward_keys_load_into_the_section(tmp_path):
    path = tmp_path / "config.yaml"
    path.write_text("env: figure-eight\nheadway: 0.25\ncollision_gap: 3.0\n")
    config = MAPETSConfig.from_yaml(path)
    assert (config.planner_reward.headway, config.planner_reward.collision_gap) == (0.25, 3.0)
    assert config.planner_reward.lane_change_time == 1.0  # the others keep their defaults
    freeway = tmp_path / "freeway.yaml"
    freeway.write_text(
        "env: freeway\nheadway: 0.5\nreward_fn: tests.recipes.test_recipe_mapets:speed_reward\n"
    )
    assert MAPETSConfig.from_yaml(freeway).planner_reward is None


def test_brake_when_lost_overrules_the_planner_in_the_recipes_policy(tmp_path):
    """``planner_reward.brake_when_lost=true``: the CAV 1.5 m behind a stopped leader brakes
    whatever the planner chose (its last module turns a full-throttle action into 0 there);
    the others keep the planner's actions (the same generator state gives the same plan)."""
    config = tiny(seed=0).with_overrides(["planner_reward.brake_when_lost=true"])
    exp = MAPETS(config, tmp_path / "run")
    plain = MAPETS(tiny(seed=0), tmp_path / "plain")
    td = exp.env.reset()
    obs = td["agents", "observation"].clone()
    obs[0, [0, 3, 5]] = torch.tensor([5.0, 0.0, 1.5])
    td["agents", "observation"] = obs
    for e in (exp, plain):
        e.plan_generator.manual_seed(1)
    action = exp.policy(td.clone())["agents", "action"]
    reference = plain.policy(td.clone())["agents", "action"]
    assert action[0].tolist() == [0.0]
    torch.testing.assert_close(action[1:], reference[1:])
    throttle = td.clone().set(("agents", "action"), torch.full_like(reference, 13.0))
    overruled = exp.policy.module[-1](throttle)["agents", "action"]
    assert overruled[0].tolist() == [0.0] and (overruled[1:] == 13.0).all()
    exp.close()
    plain.close()


def test_a_sharing_cav_overruled_by_the_lost_brake_broadcasts_it(tmp_path):
    """With ``comm.share_plans`` the lost-state brake runs inside the plan-sharing planner
    (so that the broadcast plan is the braking one, ``tests/planning/test_shared_plans.py``):
    the CAV 1.5 m behind a stopped leader brakes."""
    config = tiny(seed=0, comm={"comm_range": 100.0, "share_plans": True}).with_overrides(
        ["planner_reward.brake_when_lost=true"]
    )
    exp = MAPETS(config, tmp_path / "run")
    assert exp.policy is exp.plan_sharing and exp.plan_sharing.fallback is not None
    td = exp.env.reset()
    obs = td["agents", "observation"].clone()
    obs[0, [0, 3, 5]] = torch.tensor([5.0, 0.0, 1.5])
    td["agents", "observation"] = obs
    action = exp.policy(td)["agents", "action"]
    assert action[0].tolist() == [0.0]
    exp.close()
