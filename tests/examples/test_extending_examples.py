"""The scripts of ``examples/extending`` run as a researcher runs them (``python script.py``,
in a fresh process) and print what their docstrings promise."""

from __future__ import annotations

import ast
import re
import subprocess
import sys
from pathlib import Path

EXTENDING = Path(__file__).resolve().parents[2] / "examples" / "extending"
ARGS = {
    "toy_scenario.py": ["--steps", "5"],
    "toy_recipe.py": ["--frames", "40"],
    "exact_model_planning.py": ["--steps", "10"],
    "traffic_scenario.py": ["--episodes", "2", "--horizon", "20"],
    "highway_pettingzoo.py": ["--episodes", "2", "--frames", "20", "--duration", "5"],
}


def _run(script: str) -> str:
    proc = subprocess.run(
        [sys.executable, str(EXTENDING / script), *ARGS[script]],
        cwd=EXTENDING.parents[1],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert proc.returncode == 0, proc.stderr
    return proc.stdout


def _listed(out: str, label: str) -> list[float]:
    return ast.literal_eval(re.search(rf"^{label}:? (\[.*?\])", out, re.M).group(1))


def test_every_script_of_the_folder_is_run_here() -> None:
    assert sorted(p.name for p in EXTENDING.glob("*.py")) == sorted(ARGS)


def test_toy_scenario_rolls_out_with_a_communication_graph() -> None:
    out = _run("toy_scenario.py")
    links = _listed(out, "links within 1.0 per step")
    assert len(links) == 5 and all(0 <= n <= 3 for n in links)  # 3 agents: at most 3 links
    assert len(_listed(out, "return per agent")) == 3


def test_toy_recipe_trains_and_improves() -> None:
    out = _run("toy_recipe.py")
    before = float(re.search(r"^before training: return (\S+)$", out, re.M).group(1))
    evals = re.findall(r"^frames (\d+): return (\S+)$", out, re.M)
    assert [int(frames) for frames, _ in evals] == [20, 40]
    assert float(evals[-1][1]) > before  # it learns to drive x to 0


def test_exact_model_planning_steers_the_point_masses_home() -> None:
    out = _run("exact_model_planning.py")
    actions = [
        _listed(line, r"step \d+: position \[.*?\] action") for line in out.splitlines()[:-1]
    ]
    assert len(actions) == 10 and all(-2.0 <= a <= 2.0 for step in actions for a in step)
    # agent 0 (at +2) is pushed left, agent 1 (at -1, moving away) is pushed back right
    assert actions[0][0] < 0 < actions[0][1]
    start, final = [2.0, -1.0], _listed(out, "final position")
    assert all(abs(x) < 0.6 * abs(x0) for x, x0 in zip(final, start, strict=True))


def test_traffic_scenario_trains_mapets_with_its_reward_and_loss() -> None:
    out = _run("traffic_scenario.py")
    rows = re.findall(
        r"^episode (\d+): safety (\S+) agility (\S+) m/step transitions_shared (\d+) "
        r"model_mse (\S+)$",
        out,
        re.M,
    )
    assert [int(r[0]) for r in rows] == [1, 2]
    for _, safety, agility, shared, mse in rows:
        assert 0.0 <= float(safety) <= 1.0 and 0.0 < float(agility) < 1.39  # 13.89 m/s x 0.1 s
        assert int(shared) >= 0 and 0.0 < float(mse) < 10.0  # the MSE loss trained the models


def test_highway_pettingzoo_trains_mapets_and_mappo_on_a_stock_highway_env() -> None:
    """highway-v0 (3 controlled vehicles) through ``wrap_pettingzoo``: MA-PETS plans with the
    example's reward and shares data within 200 m (positions from the callable); MAPPO trains;
    both report the adapter's ``last_episode_metrics`` (speed, collisions)."""
    out = _run("highway_pettingzoo.py")
    mapets = re.findall(
        r"^mapets episode (\d+): return (\S+) speed (\S+) m/s collisions (\d+) "
        r"transitions_shared (\d+)$",
        out,
        re.M,
    )
    assert [int(r[0]) for r in mapets] == [1, 2]
    for _, ret, speed, collisions, shared in mapets:
        assert -3.0 <= float(ret) <= 15.0  # 3 vehicles x 5 steps x [-1, 1]
        assert 0.0 < float(speed) <= 40.0 and 0 <= int(collisions) <= 3
        assert int(shared) > 0  # the vehicles are within 200 m of one another
    mappo = re.findall(
        r"^mappo frames (\d+): return (\S+) speed (\S+) m/s collisions (\d+)$", out, re.M
    )
    assert [int(r[0]) for r in mappo] == [20]
    assert 0.0 < float(mappo[0][2]) <= 40.0
