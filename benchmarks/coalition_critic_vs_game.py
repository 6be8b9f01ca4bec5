"""A trained coalition critic's Shapley values against the coalition games computed by
simulation (issue 32).

For every Shapley AC run given (``--runs``, trained on the batched freeway, at most 10 CAVs so
that all ``2**n`` coalitions can be simulated), states are drawn by driving ``--roads`` roads
with the run's greedy policy (grand coalition, as in evaluation) for each number of steps in
``--steps``. At each state ``s``, with ``a`` the greedy joint action there:

- the **critic's game** ``v_critic(C) = v(s, a, C)`` for all coalitions, and its exact Shapley
  value ``phi_critic`` (what the actor's gradient reads);
- the **member game** (:func:`~mapets_rl.shapley.simulated.simulated_member_game`): what
  ``v(s, a, C)`` should converge to: after ``a``, every CAV plays the greedy policy on its
  coalition view and ``v(C)`` is the members' return discounted by the run's ``gamma``.
  Against it: the correlation of the 255 non-empty coalition values, the critic's
  grand-coalition value ``v(N)`` over the simulated one, and the correlation of the Shapley
  values;
- the **credit game** (:func:`~mapets_rl.shapley.simulated.simulated_game`): the members of
  ``C`` play the greedy policy and the other CAVs keep their lane; ``v(C)`` is the system
  return (discounted by ``gamma``). Its Shapley value is the credit each CAV's learned driving
  earns over keeping its lane. Against it: the correlation with ``phi_critic``, and how
  additive the game is (``v(N) - v(0)`` over the sum of single-CAV gains).

Also: the share of agent-steps at these states where a CAV's greedy action under the
evaluation view (grand coalition) differs from its action under a training view (a coalition
drawn as the run draws them while collecting).

Correlations are Pearson's, per state over CAVs (or coalitions) and summarised by the median
over states (states where either side is constant are left out), and pooled over all
(state, CAV) pairs. Writes ``OUT/states.jsonl`` (one row per state), ``OUT/table.md`` and
``OUT/critic_vs_game.png`` (phi_critic against the two simulated Shapley values).

    PYTHONPATH=. python benchmarks/coalition_critic_vs_game.py --runs RUN [RUN ...] \\
        [--roads 8] [--steps 0 5 10 15 20] [--seed 1000] --out OUT
"""

from __future__ import annotations

import argparse
import json
import statistics
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402
from tensordict import TensorDict  # noqa: E402
from torchrl.envs.utils import ExplorationType, set_exploration_type  # noqa: E402

from mapets_rl.envs import make_env  # noqa: E402
from mapets_rl.envs.torch_freeway.simulator import BatchedFreeway  # noqa: E402
from mapets_rl.experiment import atomic_savefig, atomic_write_text  # noqa: E402
from mapets_rl.machine import machine_line  # noqa: E402
from mapets_rl.modules import OBS  # noqa: E402
from mapets_rl.recipes.shapley_ac import COALITION, ShapleyAC  # noqa: E402
from mapets_rl.shapley import exact_shapley  # noqa: E402
from mapets_rl.shapley.simulated import simulated_game, simulated_member_game  # noqa: E402

MAX_CAVS = 10


def pearson(x: np.ndarray, y: np.ndarray) -> float | None:
    """Pearson's r, None where either side is (nearly) constant."""
    if x.std() < 1e-9 or y.std() < 1e-9:
        return None
    return float(np.corrcoef(x, y)[0, 1])


class GreedyCoalitionPolicy:
    """A Shapley AC run's actors as ``policy(observation [K, I, obs], members [K, I]) ->
    actions [K, I]``: every CAV's argmax on its coalition view ``s^C``."""

    def __init__(self, exp: ShapleyAC) -> None:
        self.exp = exp

    def __call__(self, observation: torch.Tensor, members: torch.Tensor) -> torch.Tensor:
        td = TensorDict(
            {OBS: observation.float(), COALITION: members}, batch_size=observation.shape[:-2]
        )
        with torch.no_grad(), self.exp.loss.actor_network_params.to_module(self.exp.actor):
            return self.exp.actor(td).get(("agents", "logits")).argmax(-1)


def training_view_disagreement(exp: ShapleyAC, observation: torch.Tensor) -> float:
    """Share of agent-steps (``observation [B, I, obs]``) whose greedy action under a coalition
    drawn as in collection differs from the one under the grand coalition."""
    policy = GreedyCoalitionPolicy(exp)
    grand = torch.ones(observation.shape[:-1], dtype=torch.bool)
    td = TensorDict({OBS: observation.float()}, batch_size=observation.shape[:-2])
    with set_exploration_type(ExplorationType.RANDOM):
        drawn = exp.coalition(td).get(COALITION)
    return float((policy(observation, grand) != policy(observation, drawn)).float().mean())


def state_rows(exp: ShapleyAC, run: str, args: argparse.Namespace) -> list[dict]:
    """One row per (road, step) state of run ``run``."""
    env_config = dict(exp.config.env_config)
    env_config.pop("num_envs", None)
    config = make_env(exp.config.env, **env_config).config
    n = int(config["n_cavs"])
    if not 1 <= n <= MAX_CAVS:
        raise SystemExit(f"{run}: {n} CAVs; the games need 2**n copies per state (n <= 10)")
    gamma = float(exp.config.gamma)
    policy = GreedyCoalitionPolicy(exp)
    critic = exp.critic
    rows = []
    for step in args.steps:
        sim = BatchedFreeway(config, exp.config.env == "freeway-merge", args.roads, seed=args.seed)
        grand = torch.ones(args.roads, n, dtype=torch.bool)
        for _ in range(step):
            sim.step(policy(sim.observe(), grand))
        observation = sim.observe()  # [B, I, obs]
        action = policy(observation, grand)  # [B, I]
        disagreement = training_view_disagreement(exp, observation)
        one_hot = torch.nn.functional.one_hot(action, critic.action_dim).float()
        with torch.no_grad(), exp.loss.critic_network_params.to_module(critic):
            critic_values = critic.all_coalition_values(observation.float(), one_hot).double()
        alive = sim.state["agents"].get("alive")
        for road in range(args.roads):
            if not bool(alive[road].all()):
                continue  # a crashed CAV has no actions to credit
            member = simulated_member_game(sim, road, policy, action[road], gamma=gamma)
            credit = simulated_game(sim, road, policy, gamma=gamma)
            v_critic = critic_values[road]
            phi = {
                "critic": exact_shapley(v_critic, n),
                "member": exact_shapley(member.double(), n),
                "credit": exact_shapley(credit.double(), n),
            }
            singles = torch.stack([credit[1 << i] for i in range(n)]).double() - credit[0]
            rows.append(
                {
                    "run": run,
                    "step": step,
                    "road": road,
                    "view_disagreement": disagreement,
                    "v_critic": v_critic.tolist(),
                    "v_member": member.double().tolist(),
                    "v_credit": credit.double().tolist(),
                    "phi": {k: v.tolist() for k, v in phi.items()},
                    "credit_gain": float(credit[-1] - credit[0]),
                    "credit_additive": float(singles.sum()),
                }
            )
    return rows


def summarise(rows: list[dict]) -> dict[str, float | int | None]:
    """The table's columns for the rows of one run."""

    def median(values: list[float | None]) -> float | None:
        kept = [v for v in values if v is not None]
        return statistics.median(kept) if kept else None

    v_critic, v_member = (np.asarray([r[k] for r in rows]) for k in ("v_critic", "v_member"))
    phi = {k: np.asarray([r["phi"][k] for r in rows]) for k in ("critic", "member", "credit")}
    ratio = [
        r["credit_gain"] / r["credit_additive"] for r in rows if abs(r["credit_additive"]) > 1e-6
    ]
    return {
        "states": len(rows),
        "v_corr": median([pearson(c[1:], m[1:]) for c, m in zip(v_critic, v_member, strict=True)]),
        "grand_ratio": float(np.median(v_critic[:, -1] / v_member[:, -1])),
        "phi_member_corr": median(
            [pearson(c, m) for c, m in zip(phi["critic"], phi["member"], strict=True)]
        ),
        "phi_member_pooled": pearson(phi["critic"].ravel(), phi["member"].ravel()),
        "phi_credit_corr": median(
            [pearson(c, m) for c, m in zip(phi["critic"], phi["credit"], strict=True)]
        ),
        "phi_credit_pooled": pearson(phi["critic"].ravel(), phi["credit"].ravel()),
        "credit_gain": float(np.mean([r["credit_gain"] for r in rows])),
        "credit_ratio": statistics.median(ratio) if ratio else None,
        "view_disagreement": float(np.mean([r["view_disagreement"] for r in rows])),
    }


def fmt(value: float | int | None, digits: int = 2) -> str:
    return "-" if value is None else f"{value:.{digits}f}"


def write_outputs(rows: list[dict], runs: list[str], out: Path) -> str:
    header = (
        "| run | states | corr v_critic, v_member (median) | v_critic(N) / v_member(N) | "
        "corr phi_critic, phi_member (median / pooled) | corr phi_critic, phi_credit "
        "(median / pooled) | credit gain v(N)-v(0) | gain / additive (median) | "
        "eval vs training view |\n|---|---|---|---|---|---|---|---|---|"
    )
    lines = [header]
    fig, axes = plt.subplots(1, 2, figsize=(10, 4.6))
    null_runs: list[str] = []
    for run in runs:
        mine = [r for r in rows if r["run"] == run]
        if not mine:
            continue
        s = summarise(mine)
        lines.append(
            f"| {Path(run).name} | {s['states']} | {fmt(s['v_corr'])} | {fmt(s['grand_ratio'])} "
            f"| {fmt(s['phi_member_corr'])} / {fmt(s['phi_member_pooled'])} | "
            f"{fmt(s['phi_credit_corr'])} / {fmt(s['phi_credit_pooled'])} | "
            f"{s['credit_gain']:+.1f} | {fmt(s['credit_ratio'])} | "
            f"{100 * s['view_disagreement']:.1f}% |"
        )
        critic = np.concatenate([r["phi"]["critic"] for r in mine])
        for ax, other in zip(axes, ("member", "credit"), strict=True):
            simulated = np.concatenate([r["phi"][other] for r in mine])
            if other == "credit" and np.ptp(simulated) < 1e-6:
                null_runs.append(Path(run).name)  # a null game: the policy keeps its lane
                continue
            ax.scatter(simulated, critic, s=6, alpha=0.5, label=Path(run).name)
    top = axes[0].get_xlim()[1]
    axes[0].plot([0, top], [0, top], "k--", lw=0.8, label="critic = simulated")
    if null_runs:
        axes[1].text(
            0.5,
            0.5,
            "null game (the greedy policy keeps its lane):\n" + ", ".join(null_runs),
            ha="center",
            va="center",
            transform=axes[1].transAxes,
            fontsize=8,
        )
    for ax, title in zip(
        axes,
        ("member game (what the critic should learn)", "credit game (drive vs keep lane)"),
        strict=True,
    ):
        ax.set_xlabel(f"simulated Shapley value,\n{title}")
        ax.set_ylabel("critic's Shapley value")
        if ax.get_legend_handles_labels()[0]:
            ax.legend(fontsize=7)
    fig.tight_layout()
    atomic_savefig(fig, out / "critic_vs_game.png", dpi=120)
    plt.close(fig)
    table = "\n".join(lines) + "\n"
    atomic_write_text(out / "table.md", table)
    return table


def main(argv: list[str] | None = None) -> str:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--runs", nargs="+", required=True, help="Shapley AC run directories")
    parser.add_argument("--roads", type=int, default=8)
    parser.add_argument("--steps", nargs="+", type=int, default=[0, 5, 10, 15, 20])
    parser.add_argument("--seed", type=int, default=1000, help="seed of the states' roads")
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args(argv)
    if args.roads < 1 or any(not 0 <= s < 40 for s in args.steps):
        parser.error("--roads must be >= 1 and --steps in [0, 39]")
    print(f"# {machine_line()}")
    args.out.mkdir(parents=True, exist_ok=True)
    path = args.out / "states.jsonl"
    done = [json.loads(line) for line in path.read_text().splitlines()] if path.exists() else []
    finished = {r["run"] for r in done}
    for run in args.runs:
        if run in finished:
            continue
        exp = ShapleyAC.from_run_dir(run)
        exp.close()
        rows = state_rows(exp, run, args)
        with path.open("a") as f:
            f.writelines(json.dumps(r) + "\n" for r in rows)
        done.extend(rows)
    table = write_outputs(done, args.runs, args.out)
    print(table)
    return table


if __name__ == "__main__":
    from mapets_rl import quiet_dependencies

    quiet_dependencies()
    main()
