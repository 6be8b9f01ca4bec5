"""The evaluation protocol: a policy and its references on the same evaluation roads, disjoint
from training; the gains; the run's result file; the ``mapets-rl`` commands a study runs
(``train --config NAME``, ``configs``, ``evaluate --roads --references``)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch
import yaml

from mapets_rl.app.sweep import fold_into_fields
from mapets_rl.envs import make_env
from mapets_rl.experiment.protocol import (
    PROTOCOL_FILE,
    ROAD_EVAL_SEED_OFFSET,
    check_roads,
    evaluate_protocol,
    read_protocol,
    score_roads,
)
from mapets_rl.experiment.runner import BOUNDARY_SEED_STRIDE
from mapets_rl.recipes.maddpg import MADDPG, MADDPGConfig
from tests.cli_run import run_cli

ENV_CONFIG = {"backend": "torch", "num_envs": 2, "n_vehicles": 6, "cav_ratio": 1.0,
              "shield": True, "velocity_weight": 1.0}  # fmt: skip
TINY = [
    "env_config.num_envs=2",
    "env_config.n_vehicles=6",
    "frames_per_batch=20",
    "total_frames=40",
    "batch_size=8",
    "init_random_frames=0",
    "update_interval=20",
    "eval_interval=0",
    "checkpoint_interval=0",
    "logger=none",
    "progress=false",
]


def _config(team_reward: bool, seed: int = 3) -> MADDPGConfig:
    return MADDPGConfig(env="freeway-merge", env_config={**ENV_CONFIG, "team_reward": team_reward},
                        seed=seed, progress=False, logger="none")  # fmt: skip


def _keep_lane(env):
    from mapets_rl.envs.references import make_reference

    return make_reference("freeway-merge", "keep-lane", env)


def test_references_drive_the_evaluation_roads_a_hand_rollout_drives() -> None:
    """Keep lane through the protocol equals a hand rollout of Keep Lane on the same roads
    (seed + ROAD_EVAL_SEED_OFFSET), to the bit, under the team reward as under the individual
    one (the system reward is the sum of the CAVs' own rewards)."""
    roads = 3
    scores = score_roads(_config(team_reward=True), _keep_lane, roads)
    env = make_env("freeway-merge", backend="torch", num_envs=roads, n_vehicles=6, cav_ratio=1.0,
                   shield=True, velocity_weight=1.0)  # fmt: skip
    env.set_seed(3 + ROAD_EVAL_SEED_OFFSET)
    td = env.reset()
    system = torch.zeros(roads, dtype=torch.float64)
    keep_lane = torch.nn.functional.one_hot(torch.zeros(roads, 6, dtype=torch.long), 4)
    for _ in range(int(env.config["horizon"])):
        td.set(("agents", "action"), keep_lane)
        td = env.step(td)
        system += td.get(("next", "agents", "reward")).double().sum((-2, -1))
        td = td.get("next")
    env.close()
    assert scores.system_reward.tolist() == system.tolist()
    again = score_roads(_config(team_reward=False), _keep_lane, roads)
    assert again.system_reward.tolist() == scores.system_reward.tolist()
    assert again.metrics == scores.metrics
    assert {"ramp_stuck", "collisions", "shielded"} <= set(scores.metrics)


def test_the_evaluation_roads_are_none_of_the_training_seeds() -> None:
    for seed in (0, 1, 7, 123_456):
        assert all(
            seed + ROAD_EVAL_SEED_OFFSET != seed + BOUNDARY_SEED_STRIDE * k for k in range(10**4)
        )


@pytest.mark.parametrize("roads", [0, -1, True, 2.5, 10**6])
def test_bad_road_counts_are_refused(roads) -> None:
    with pytest.raises(ValueError, match="roads must be an integer in"):
        check_roads(roads)


def test_a_run_and_its_references_are_scored_and_written(tmp_path: Path) -> None:
    config = _config(team_reward=False).with_overrides(TINY)
    exp = MADDPG(config, tmp_path / "run")
    exp.train()
    exp = MADDPG.from_run_dir(tmp_path / "run")
    result = evaluate_protocol(exp, 4, ["keep-lane", "cooperative-merge"])
    exp.close()
    assert read_protocol(tmp_path / "run") == json.loads(json.dumps(result))
    keep = result["references"]["keep-lane"]["system_reward_mean"]
    mine = result["policy"]["system_reward_mean"]
    assert result["gain_percent"]["keep-lane"] == pytest.approx(100 * (mine / keep - 1))
    assert result["roads"] == 4 and result["eval_seed"] == config.seed + ROAD_EVAL_SEED_OFFSET
    assert len(result["policy"]["system_reward"]) == 4
    with pytest.raises(ValueError, match="'nosuch' is not a reference policy"):
        evaluate_protocol(exp, 4, ["nosuch"])


def test_a_study_runs_with_the_library_commands(tmp_path: Path, capsys) -> None:
    """``configs`` lists the published arms; ``train --config NAME`` trains one;
    ``evaluate RUN --roads B --references ...`` prints the gain over each reference and the
    behaviour metrics, and writes them into the run."""
    code, out, _ = run_cli(["configs"], capsys)
    assert code == 0 and "freeway-merge/maddpg-individual" in out
    run = tmp_path / "run"
    code, out, err = run_cli(
        ["train", "--config", "freeway-merge/maddpg-individual", *TINY, "--run-dir", str(run)],
        capsys,
    )
    assert code == 0, err
    code, out, err = run_cli(
        ["evaluate", str(run), "--roads", "3", "--references", "keep-lane", "cooperative-merge"],
        capsys,
    )
    assert code == 0, err
    printed = json.loads(out.strip().splitlines()[-1])
    assert set(printed["gain_percent"]) == {"keep-lane", "cooperative-merge"}
    assert {"ramp_stuck", "collisions", "shielded"} <= set(printed["metrics"])
    assert (run / PROTOCOL_FILE).is_file()
    for argv, needle in (
        (["evaluate", str(run), "--roads", "0"], "--roads must be an integer"),
        (["evaluate", str(run), "--references", "keep-lane"], "--references needs --roads"),
        (["evaluate", str(run), "--roads", "2", "--references", "x"], "choose from: keep-lane"),
        (["train", "--config", "nosuch/config"], "neither a file nor a published"),
        (["train", "mappo", "--config", "freeway-merge/maddpg-individual"], "differs from"),
    ):
        code, _, err = run_cli(argv, capsys)
        assert code == 2 and needle in err, (argv, err)


def test_compare_aggregates_the_protocol_over_seeds(tmp_path: Path, capsys) -> None:
    """Two seeds scored by the protocol: ``compare`` writes each seed's gain, their mean with
    its interval, the training return and the behaviour metrics (protocol.md / .json)."""
    runs = []
    for seed in (0, 1):
        run = tmp_path / f"run{seed}"
        argv = ["train", "--config", "freeway-merge/maddpg-individual", *TINY, "--seed", str(seed),
                "--run-dir", str(run)]  # fmt: skip
        assert run_cli(argv, capsys)[0] == 0
        assert run_cli(["evaluate", str(run), "--roads", "2"], capsys)[0] == 0
        runs.append(str(run))
    code, out, err = run_cli(["compare", *runs, "--out", str(tmp_path / "cmp")], capsys)
    assert code == 0, err
    summary = json.loads((tmp_path / "cmp" / "protocol.json").read_text())
    group = summary["groups"]["maddpg"]
    per_seed = [read_protocol(r)["gain_percent"]["cooperative-merge"] for r in runs]
    assert group["gain_percent"]["cooperative-merge"]["per_seed"] == per_seed
    assert group["gain_percent"]["cooperative-merge"]["mean"] == pytest.approx(sum(per_seed) / 2)
    assert set(summary["references"]) == {"keep-lane", "greedy-overtaking", "cooperative-merge"}
    assert "vs cooperative-merge" in out and "ramp_stuck" in out


def test_a_published_configs_seeds_are_swept(tmp_path: Path, capsys) -> None:
    """``sweep --config NAME --seeds ...`` takes recipe and scenario from the configuration; an
    override inside one of its mappings (``env_config.num_envs``) is folded into it, so every
    trial (resumed or not) applies its overrides in one go."""
    out = tmp_path / "sweep"
    argv = ["sweep", "--config", "freeway-merge/maddpg-individual", "--seeds", "0", *TINY,
            "--out", str(out)]  # fmt: skip
    code, _, err = run_cli(argv, capsys)
    assert code == 0, err
    (trial,) = (out / "trials").iterdir()
    config = yaml.safe_load((trial / "config.yaml").read_text())
    assert config["env"] == "freeway-merge" and config["env_config"]["num_envs"] == 2
    assert config["env_config"]["shield"] is True and config["exploration"] == "epsilon"


def test_overrides_fold_into_a_config_files_mappings() -> None:
    fields = {"env": "freeway-merge", "env_config": {"num_envs": 256, "shield": True}, "gamma": 0.9}
    head, rest = fold_into_fields(
        fields, ["env=freeway-merge", "env_config.num_envs=2", "gamma=0.5", "planner.horizon=3"]
    )
    assert head == ['env_config={"num_envs": 2, "shield": true}']
    assert rest == ["env=freeway-merge", "gamma=0.5", "planner.horizon=3"]
    assert fields["env_config"]["num_envs"] == 256  # the file's fields are not changed


def test_in_training_evaluations_follow_the_protocol(tmp_path: Path) -> None:
    """``eval_roads`` makes every evaluation the protocol: the gains and behaviour metrics are
    in the results, the references scored once per run."""
    tiny = [o for o in TINY if not o.startswith("eval_interval=")]
    config = _config(team_reward=False).with_overrides(
        [*tiny, "eval_interval=20", "eval_roads=2", "eval_references=[keep-lane]"]
    )
    exp = MADDPG(config, tmp_path / "run")
    exp.train()
    evaluations = json.loads((tmp_path / "run" / "results.json").read_text())["evaluations"]
    assert len(evaluations) == 2
    for entry in evaluations:
        assert {"system_return", "gain_vs_keep_lane", "ramp_stuck"} <= set(entry["metrics"])
    assert list(exp._reference_scores) == ["keep-lane"]


@pytest.mark.parametrize(
    ("overrides", "needle"),
    [
        (["eval_roads=-1"], r"eval_roads must be in \[0, 65536\]"),
        (["eval_references=[keep-lane]"], "eval_references must be empty unless eval_roads"),
        (["eval_roads=2", "eval_references=[nosuch]"], "'nosuch' is not a reference policy"),
        (["env=figure-eight", "env_config={}", "eval_roads=2"], "no batched backend"),
    ],
)
def test_protocol_settings_are_checked(overrides: list[str], needle: str) -> None:
    from mapets_rl.config import ConfigError

    with pytest.raises(ConfigError, match=needle):
        _config(team_reward=False).with_overrides(overrides)


def test_a_run_made_before_the_protocol_fields_still_loads(tmp_path: Path) -> None:
    exp = MADDPG(_config(team_reward=False).with_overrides(TINY), tmp_path / "run")
    exp.train()
    path = tmp_path / "run" / "config.yaml"
    data = yaml.safe_load(path.read_text())
    del data["eval_roads"], data["eval_references"]
    path.write_text(yaml.safe_dump(data))
    again = MADDPG.from_run_dir(tmp_path / "run")
    assert again.config.eval_roads == 0 and again.config.eval_references == []
    again.close()


def test_on_one_road_the_references_play_the_runs_own_evaluation_episodes(tmp_path: Path) -> None:
    """A scenario without a batched backend (the figure-eight): the protocol plays the run's
    evaluation episodes, the reference in place of the trained policy, which is put back."""
    from mapets_rl.envs.references import make_reference
    from mapets_rl.experiment.reference import evaluate_scripted
    from mapets_rl.recipes.sac import SAC, SACConfig

    config = SACConfig(
        env="figure-eight",
        env_config={"n_cavs": 3, "n_hvs": 2, "horizon": 10},
        total_frames=20,
        frames_per_batch=10,
        batch_size=8,
        init_random_frames=0,
        eval_interval=0,
        checkpoint_interval=0,
        progress=False,
        logger="none",
    )
    exp = SAC(config, tmp_path / "run")
    trained = exp.eval_policy
    result = evaluate_protocol(exp, 2, ["idm"])
    assert exp.eval_policy is trained and result["batched"] is False
    idm = evaluate_scripted(
        config.with_overrides(["eval_episodes=2"]),
        lambda env: make_reference("figure-eight", "idm", env),
    )
    # SAC reports no system return: the mean CAV return, on the same episodes
    assert result["references"]["idm"]["system_reward_mean"] == pytest.approx(idm["return"])
    exp.close()
