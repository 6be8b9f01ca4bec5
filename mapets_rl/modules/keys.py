"""TensorDict keys of the multi-agent ``"agents"`` group that the recipes' modules and losses
read and write (every scenario of :mod:`mapets_rl.envs` uses this layout)."""

from __future__ import annotations

GROUP = "agents"
OBS = (GROUP, "observation")
"""Per-agent observation [*, I, obs]."""
ACTION = (GROUP, "action")
"""Per-agent action [*, I, act] (continuous) or one-hot [*, I, n]."""
REWARD = (GROUP, "reward")
DONE = (GROUP, "done")
TERMINATED = (GROUP, "terminated")
MASK = (GROUP, "mask")
"""[*, I] bool, False once a CAV has crashed."""

LOSS_KEYS = {"reward": REWARD, "done": DONE, "terminated": TERMINATED}
"""Per-agent reward / done / terminated keys for ``loss.set_keys(**LOSS_KEYS)``."""
TRANSITION_KEYS = (
    OBS,
    ACTION,
    ("next", *OBS),
    ("next", *REWARD),
    ("next", *DONE),
    ("next", *TERMINATED),
)
"""What a one-step TD learner replays of a collected step ``(o, a, r, o', done, terminated)``:
the rest of the step (infos, positions, normalised observations, which the networks recompute)
stays out of the replay buffer."""

OBS_NORM = (GROUP, "observation_normalized")
"""Standardised observation [*, I, obs] written by :func:`~mapets_rl.modules.make_obs_norm`."""
OBS_ACTION = (GROUP, "obs_action")
"""Observation and action concatenated, [*, I, obs + act] (input of Q(o, a) critics)."""
Q_VALUE = (GROUP, "state_action_value")
"""Q(o, a) per agent [*, I, 1]."""
ACTION_VALUE = (GROUP, "action_value")
"""Q(o, .) over the discrete actions per agent [*, I, n]."""
VALUE = (GROUP, "state_value")
"""V(o) per agent [*, I, 1]."""
LOG_PROB = (GROUP, "action_log_prob")
"""Log-probability of the sampled action per agent [*, I]."""
