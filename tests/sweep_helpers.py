"""A slow toy recipe for the sweep tests that kill a sweep mid-trial (imported by the sweep's
worker processes by import path, so it lives in a module of its own)."""

from __future__ import annotations

import os
import time

from tensordict import TensorDictBase
from toy_recipe import ToyLearner

SLOW_ENV = "MAPETS_RL_TEST_SLOW_TOY"
"""Seconds every training step of :class:`SlowToy` sleeps (unset: none)."""


class SlowToy(ToyLearner):
    """The toy learner, sleeping ``$MAPETS_RL_TEST_SLOW_TOY`` seconds per training step."""

    name = "slowtoy"

    def train_step(self, batch: TensorDictBase) -> dict[str, float]:
        time.sleep(float(os.environ.get(SLOW_ENV, "0") or 0))
        return super().train_step(batch)
