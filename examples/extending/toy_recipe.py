"""A custom recipe: a minimal :class:`mapets_rl.experiment.Experiment` on the toy scenario.

A recipe is a validated config dataclass plus an ``Experiment`` subclass that builds its
modules, collector and buffer in ``__init__`` and implements ``train_step(batch)`` and
``stateful_components()``; the base class gives it the run loop, ``key=value`` overrides,
config files, checkpoints with exact resume, results files, evaluation and ``compare``.

Make it known to the ``mapets-rl`` command with an entry point in your package's
``pyproject.toml`` (then ``pip install -e .``)::

    [project.entry-points."mapets_rl.recipes"]
    toy = "toy_recipe:ToyLearner"

Run it to train on the toy scenario for a few frames and print the evaluations:

    python examples/extending/toy_recipe.py [--frames 60] [--run-dir DIR]
"""

from __future__ import annotations

import argparse
import dataclasses
import tempfile

import torch
from tensordict.nn import TensorDictModule, TensorDictSequential
from torch import nn
from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer
from torchrl.modules import AdditiveGaussianModule

from mapets_rl.experiment import Experiment, ExperimentConfig, check


@dataclasses.dataclass
class ToyConfig(ExperimentConfig):
    """The shared fields of :class:`ExperimentConfig` with small defaults, plus the learner's
    own (``lr``, ``batch_size``, ``sigma``), checked in ``__post_init__``.

    ``mapets-rl train toy --help`` lists every field with the first sentence of its entry
    below (or of a base class's) and the ``unit`` of its ``dataclasses.field`` metadata.

    Attributes:
        lr: step size of the policy regression (> 0).
        batch_size: replayed observations per regression step (>= 1).
        sigma: standard deviation of the exploration noise added to the action.
    """

    env: str = "toy"
    lr: float = 0.05
    batch_size: int = dataclasses.field(default=16, metadata={"unit": "observations"})
    sigma: float = 0.3
    total_frames: int = 60
    frames_per_batch: int = 10
    eval_interval: int = 20
    checkpoint_interval: int = 20
    progress: bool = False
    logger: str = "none"

    def __post_init__(self) -> None:
        super().__post_init__()
        check(self.lr > 0, "lr", "> 0", self.lr)
        check(self.batch_size >= 1, "batch_size", ">= 1", self.batch_size)


class ToyLearner(Experiment):
    """A real small learner: a linear policy regressed (from replayed observations) onto the
    action that zeroes the position, with Gaussian exploration noise during collection."""

    name = "toy"
    Config = ToyConfig

    def __init__(self, config: ToyConfig, run_dir=None) -> None:
        super().__init__(config, run_dir)
        self.actor = TensorDictModule(
            nn.Linear(2, 1), [("agents", "observation")], [("agents", "action")]
        )
        noise = AdditiveGaussianModule(
            self.env.full_action_spec_unbatched[("agents", "action")],
            sigma_init=config.sigma,
            sigma_end=config.sigma,
            action_key=("agents", "action"),
        )
        self.collector = self.make_collector(TensorDictSequential(self.actor, noise))
        self.eval_policy = self.actor
        self.buffer = TensorDictReplayBuffer(
            storage=LazyTensorStorage(200), batch_size=config.batch_size
        )
        self.optim = torch.optim.Adam(self.actor.parameters(), lr=config.lr)

    def train_step(self, batch):
        self.buffer.extend(batch.reshape(-1).select(("agents", "observation")))
        sample = self.buffer.sample()
        obs = sample["agents", "observation"]
        target = (-obs[..., :1] / 0.5).clamp(-1, 1)
        loss = (self.actor.module(obs) - target).pow(2).mean()
        self.optim.zero_grad()
        loss.backward()
        self.optim.step()
        return {"loss": loss.item()}

    def stateful_components(self):
        return {"actor": self.actor, "optim": self.optim, "buffer": self.buffer}


def main() -> None:
    from toy_scenario import ToyAgentsEnv

    from mapets_rl.experiment import register_env

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=60, help="total frames (multiple of 10)")
    parser.add_argument("--run-dir", help="run directory (default: a temporary one)")
    args = parser.parse_args()
    register_env("toy", ToyAgentsEnv)
    with tempfile.TemporaryDirectory() as tmp:
        exp = ToyLearner(ToyConfig(total_frames=args.frames), args.run_dir or f"{tmp}/run")
        print(f"before training: return {exp.evaluate()['return']:.3f}")
        for entry in exp.train():
            print(f"frames {entry['frames']}: return {entry['metrics']['return']:.3f}")


if __name__ == "__main__":
    main()
