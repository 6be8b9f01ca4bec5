"""benchmarks/cooperation_control.py (issue 32's positive control): variants are named changes
that are refused before any work when unknown, a tiny end-to-end run scores every policy on
the same roads as keep lane, and a second call reuses the finished runs and evaluations."""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path
from types import ModuleType

import pytest

ROOT = Path(__file__).resolve().parents[2]
TINY = ["--seeds", "0", "--frames", "20", "--train-roads", "4", "--eval-roads", "2"]
"""20 frames: two batches of 4 roads x 4 steps, so a finished run has done more than asked."""


@pytest.fixture
def control(load_script: Callable[[str], ModuleType], monkeypatch) -> ModuleType:
    monkeypatch.syspath_prepend(str(ROOT / "benchmarks"))  # it imports freeway_headroom
    return load_script("benchmarks/cooperation_control.py")


@pytest.mark.parametrize(
    "variant",
    [
        "maddpg_boltzmann",
        "mappo_epsilon",
        "maddpg_short",
        "sac",
        "shapley_gamma99",
        "shapley_individual",
    ],
)
def test_an_unknown_variant_is_refused_before_any_work(
    control: ModuleType, variant: str, tmp_path: Path
) -> None:
    with pytest.raises(ValueError, match="--variants"):
        control.main(["--variants", variant, *TINY, "--out", str(tmp_path)])
    assert not any(tmp_path.iterdir())


def test_variants_are_one_change_at_a_time(control: ModuleType) -> None:
    args = control.argparse.Namespace(train_roads=4, n_vehicles=8, frames=16, anneal_frames=8)
    _, base = control.variant_overrides("maddpg", args)
    _, shielded = control.variant_overrides("maddpg_shield", args)
    assert sorted(set(shielded) - set(base)) == ["env_config.shield=true"]
    assert "env_config.team_reward=true" in base
    _, longer = control.variant_overrides("maddpg_gamma99", args)
    assert sorted(set(longer) - set(base)) == ["gamma=0.99", "n_steps=5"]
    assert "gamma=0.95" not in longer
    _, weighted = control.variant_overrides("maddpg_w1", args)
    assert sorted(set(weighted) - set(base)) == ["env_config.velocity_weight=1.0"]
    _, selfish = control.variant_overrides("maddpg_w1_individual", args)
    assert sorted(set(selfish) - set(weighted)) == ["env_config.team_reward=false"]
    assert "env_config.team_reward=true" not in selfish
    _, shared = control.variant_overrides("maddpg_w1_individual_shared", args)
    assert sorted(set(shared) - set(selfish)) == ["critic_share_params=true"]
    recipe, shapley = control.variant_overrides("shapley_w1", args)
    assert recipe == "shapley_ac"  # the same schedule, paid the rewards it reallocates
    assert sorted(set(shapley) - set(selfish)) == sorted(control.SHAPLEY_SCHEDULE)
    assert set(selfish) <= set(shapley)
    cls = control.load_recipe(recipe)  # every field of the Shapley arm is the recipe's
    config = cls.Config(env=control.ENV).with_overrides(shapley)
    assert (config.critic_cells, config.num_cells) == ([64, 64], [64, 64])
    _, member = control.variant_overrides("shapley_w1_member", args)
    assert sorted(set(member) - set(shapley)) == ["critic_member_heads=true"]
    assert cls.Config(env=control.ENV).with_overrides(member).critic_member_heads is True


def test_scripted_references_are_scored_with_the_variants_reward(control: ModuleType) -> None:
    assert control.env_settings("maddpg_epsilon_shield") == {"shield": True}
    assert control.env_settings("mappo_w1") == {"shield": False, "velocity_weight": 1.0}
    assert control.settings_label(control.env_settings("maddpg_shield_w1")) == ", shield, w=1.0"
    args = control.argparse.Namespace(eval_roads=2, n_vehicles=8)
    keep = control.ScriptedCAVPolicy
    plain = control.score(keep, control.env_settings("maddpg"), 0, args)
    weighted = control.score(keep, control.env_settings("maddpg_w1"), 0, args)
    # same roads and the same driving: only the velocity term of the reward grows, tenfold
    assert (plain["average_velocity"] == weighted["average_velocity"]).all()
    assert (weighted["system_reward"] > plain["system_reward"] + 1.0).all()


def test_a_tiny_control_scores_policies_on_the_roads_of_keep_lane(
    control: ModuleType, tmp_path: Path, monkeypatch
) -> None:
    argv = ["--variants", "maddpg_shield", *TINY, "--n-vehicles", "8", "--out", str(tmp_path)]
    summary = control.main(argv)
    assert summary["keep lane (scripted, shield)"]["gain_percent_per_seed"] == [0.0]
    run = summary["maddpg_shield"]
    assert len(run["gain_percent_per_seed"]) == 1
    low, high = run["gain_percent_ci95"]
    assert low <= run["gain_percent_mean"] <= high
    assert json.loads((tmp_path / "control.json").read_text())["maddpg_shield"] == run

    files = sorted(tmp_path.rglob("*"))
    stamps = {f: f.stat().st_mtime_ns for f in files if f.is_file() and "logs" not in f.parts}
    again = control.main(argv)
    assert again["maddpg_shield"] == run
    for path, stamp in stamps.items():
        if path.name not in ("control.md", "control.json", ".lock"):
            assert path.stat().st_mtime_ns == stamp, path  # nothing trained or scored again


@pytest.mark.parametrize("variant", ["maddpg_epsilon", "shapley_epsilon"])
def test_the_explored_row_scores_the_final_collection_policy(
    control: ModuleType, tmp_path: Path, variant: str
) -> None:
    # 20 frames of a 200k-frame annealing: epsilon is still about 1, so the collection policy
    # changes lanes at random where the greedy one does not
    argv = ["--variants", variant, *TINY, "--n-vehicles", "8", "--out", str(tmp_path)]
    summary = control.main([*argv, "--explored"])
    greedy = summary[variant]
    explored = summary[f"{variant} (its final epsilon-greedy)"]
    assert explored["system_reward"] != greedy["system_reward"]
    assert explored["average_comfort"] != greedy["average_comfort"]
    assert (tmp_path / "evals" / f"{variant}_seed0_2roads_explored.json").is_file()
    # keep lane with random moves at the variant's epsilon_end: lane changes keep lane never makes
    label = f"keep lane + random moves at {variant}'s epsilon_end (scripted)"
    noisy, keep = summary[label], summary["keep lane (scripted)"]
    moves = noisy["mainline_changes_near_merge"] + noisy["mainline_changes_elsewhere"]
    assert moves > 0 == keep["mainline_changes_near_merge"] + keep["mainline_changes_elsewhere"]
    again = control.main([*argv, "--explored"])
    assert again[f"{variant} (its final epsilon-greedy)"] == explored
    assert again[label] == noisy


def test_training_windows_bin_the_episodes_by_the_frame_they_ended(
    control: ModuleType, tmp_path: Path
) -> None:
    ended = [(10, 1.0, 0.0), (20, 2.0, 1.0), (30, 3.0, 2.0), (70, 4.0, 3.0)]
    lines = [
        json.dumps({"frames": f, "system_return": r, "length": 40.0, "ramp_stuck": stuck})
        for f, r, stuck in ended
    ]
    (tmp_path / "train_episodes.jsonl").write_text("\n".join(lines) + "\n")
    windows = control.training_windows(tmp_path, 20, 80)
    assert windows[:2] == [(1.5, 0.5), (3.0, 2.0)]
    assert all(v != v for v in windows[2])  # no episode ended in frames 41-60: NaN
    assert windows[3] == (4.0, 3.0)
    table = control.windows_table("v", {0: windows}, 20)
    assert "| 0 | 2 / 0.5 | 3 / 2.0 | nan / nan | 4 / 3.0 |" in table


def test_keep_lane_never_changes_mainline_lanes_and_the_merge_rule_yields_near_the_merge(
    control: ModuleType, tmp_path: Path
) -> None:
    args = control.argparse.Namespace(eval_roads=4, n_vehicles=30, out=str(tmp_path))
    scores = control.scripted(0, {"shield": False}, args)
    keep, rule = scores["keep lane"], scores["cooperative merge"]
    assert sum(keep["mainline_changes_near_merge"]) == sum(keep["mainline_changes_elsewhere"]) == 0
    assert sum(rule["mainline_changes_near_merge"]) > 0  # its yields
    assert sum(rule["ramp_stuck"]) < sum(keep["ramp_stuck"])


def test_a_cached_score_without_the_behaviour_counts_is_scored_again(
    control: ModuleType, tmp_path: Path
) -> None:
    args = control.argparse.Namespace(eval_roads=2, n_vehicles=8, out=str(tmp_path))
    fresh = control.scripted(0, {"shield": False}, args)
    (path,) = (tmp_path / "evals").iterdir()
    stale = {name: {"system_reward": [0.0, 0.0]} for name in fresh}
    path.write_text(json.dumps(stale))
    assert control.scripted(0, {"shield": False}, args) == fresh
    assert json.loads(path.read_text()) == fresh


def test_coma_is_the_on_policy_arm_with_mappos_schedule_of_batches(
    control: ModuleType, tmp_path: Path
) -> None:
    args = control.argparse.Namespace(train_roads=4, n_vehicles=8, frames=16, anneal_frames=8)
    recipe, coma = control.variant_overrides("coma_shield_short_w1", args)
    _, mappo = control.variant_overrides("mappo_shield_short_w1", args)
    assert recipe == "coma"
    assert set(coma) == set(mappo)  # the same env, reward and batches: the learner differs
    assert {"frames_per_batch=16", "minibatch_size=16", "gamma=0.99"} <= set(coma)
    argv = ["--variants", "coma_shield_short", *TINY, "--n-vehicles", "8", "--out", str(tmp_path)]
    run = control.main(argv)["coma_shield_short"]
    assert len(run["gain_percent_per_seed"]) == 1
    run_dir = tmp_path / "runs" / "coma_shield_short_seed0"
    assert json.loads((run_dir / "run.json").read_text())["recipe"] == "coma"
    config = control.load_recipe("coma").Config.from_yaml(run_dir / "config.yaml")
    assert config.env_config["shield"] is True and config.frames_per_batch == 16


def test_score_every_scores_the_greedy_policy_at_each_stage_of_one_uninterrupted_run(
    control: ModuleType, tmp_path: Path
) -> None:
    # one road, batches of 4 steps; the uninterrupted run checkpoints every 192 // 4 = 48
    # frames, as the stages do: one 40-step episode ends between two checkpoints
    argv = ["--variants", "maddpg_shield", *TINY, "--train-roads", "1", "--n-vehicles", "8"]
    argv += ["--frames", "192"]
    staged = control.main([*argv, "--score-every", "48", "--out", str(tmp_path / "staged")])
    plain = control.main([*argv, "--out", str(tmp_path / "plain")])
    # training in stages resumes bit-exactly: the same training episodes, final policy, scores
    assert staged["maddpg_shield"] == plain["maddpg_shield"]
    episodes = [
        tmp_path / out / "runs" / "maddpg_shield_seed0" / "train_episodes.jsonl"
        for out in ("staged", "plain")
    ]
    assert episodes[0].read_text() == episodes[1].read_text() != ""
    by_stage = staged["maddpg_shield greedy gain by stage"]["0"]
    assert list(by_stage) == ["48", "96", "144", "192"]
    assert by_stage["192"] == staged["maddpg_shield"]["gain_percent_per_seed"][0]
    evals = tmp_path / "staged" / "evals"
    assert {p.name for p in evals.glob("maddpg_shield_seed0_2roads_at*.json")} == {
        "maddpg_shield_seed0_2roads_at48.json",
        "maddpg_shield_seed0_2roads_at96.json",
        "maddpg_shield_seed0_2roads_at144.json",
    }
    run_dir = tmp_path / "staged" / "runs" / "maddpg_shield_seed0"
    assert len(list((run_dir / "checkpoints").glob("*.pt"))) == 1
    # a run that has gone past a stage cannot be scored there: marked, not scored from later
    again = control.main([*argv, "--score-every", "24", "--out", str(tmp_path / "staged")])
    finer = again["maddpg_shield greedy gain by stage"]["0"]
    assert finer == {
        "24": None,
        "48": by_stage["48"],
        "72": None,
        "96": by_stage["96"],
        "120": None,
        "144": by_stage["144"],
        "168": None,
        "192": by_stage["192"],
    }
    table = (tmp_path / "staged" / "control.md").read_text()
    assert "| seed | 24 | 48 | 72 | 96 | 120 | 144 | 168 | 192 |" in table
    assert f"| 0 | - | {by_stage['48']:+.1f}% | - |" in table


def test_stage_labels_name_millions_and_thousands(control: ModuleType) -> None:
    labels = [control.frames_label(f) for f in (1_000_000, 2_000_000, 975_000, 75_000, 192)]
    assert labels == ["1M", "2M", "975k", "75k", "192"]
