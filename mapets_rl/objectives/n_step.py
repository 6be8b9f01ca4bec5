"""Per-agent n-step transitions for replay-buffer learners of the ``("agents", ...)`` group.

torchrl's ``MultiStep`` post-processor works on root reward/done keys; here every agent has its
own reward and its own termination (a crashed CAV stops while the others drive on), so the
n-step return is accumulated per agent and stops at that agent's end. The joint next state is
common to the row (a centralised critic reads every agent's observation), so all agents look
ahead the same number of steps: ``n``, fewer at the end of the collected batch or of an
episode. torchrl's TD(0) value estimator discounts the bootstrap by
``gamma ** steps_to_next_obs`` when the batch carries that key (set it with
``estimator.set_keys(steps_to_next_obs=STEPS_TO_NEXT_OBS)``).
"""

from __future__ import annotations

import torch
from tensordict import TensorDictBase

from mapets_rl.modules.keys import DONE, GROUP, REWARD, TERMINATED

STEPS_TO_NEXT_OBS = (GROUP, "steps_to_next_obs")
"""Steps between a transition's observation and its (n-step) next observation, [*, I, 1]."""


@torch.no_grad()
def n_step_transitions(batch: TensorDictBase, gamma: float, n_steps: int) -> TensorDictBase:
    """Turn a collected batch of consecutive steps into n-step transitions.

    Row ``t`` keeps its observation and action; its ``"next"`` becomes the ``"next"`` of step
    ``t + m - 1``, where ``m <= n_steps`` stops at the batch's end and after a step whose root
    ``("next", "done")`` is set (an episode boundary). Per agent, the reward becomes
    ``sum_{k < m_i} gamma^k r_{t+k}``, where ``m_i <= m`` also stops after the agent's own
    done, and ``done``/``terminated`` are those of that last included step.
    ``("agents", "steps_to_next_obs")`` holds ``m_i``.

    Args:
        batch: ``[*, T]`` consecutive steps (one collector batch; time last) with
            ``("next", "agents", "reward"|"done"|"terminated")`` ``[*, T, I, 1]`` and root
            ``("next", "done")`` ``[*, T, 1]``; every leading index (a road of a batched env)
            is its own sequence, all of them computed at once.
        gamma: discount in [0, 1].
        n_steps: look-ahead (>= 1; 1 returns the batch with ``steps_to_next_obs = 1``).

    Returns:
        A new ``[*, T]`` TensorDict of n-step transitions.
    """
    if n_steps < 1:
        raise ValueError(f"n_steps must be >= 1, got {n_steps}")
    if batch.ndim == 0:
        raise ValueError("batch must have a time batch dim (the last one)")
    lead = batch.shape[:-1]
    rows = batch.reshape(-1, batch.shape[-1])  # [N, T]: each row (road) its own sequence
    nxt = rows.get("next")
    reward, done_i, term_i = nxt.get(REWARD), nxt.get(DONE), nxt.get(TERMINATED)  # [N, T, I, 1]
    episode_end = nxt.get("done").reshape(rows.shape)  # [N, T]
    steps_total = rows.shape[1]
    time = torch.arange(steps_total, device=reward.device)

    ret, steps = reward.clone(), torch.ones_like(reward)
    done, term = done_i.clone(), term_i.clone()
    last = time.expand(rows.shape).clone()  # [N, T] the step whose "next" row t takes
    extend = ~episode_end  # [N, T] row t may look one step further
    for k in range(1, n_steps):
        ahead = time + k  # [T], the same for every row
        extend = extend & (ahead < steps_total)
        ahead = ahead.clamp(max=steps_total - 1)
        add = extend[..., None, None] & ~done  # [N, T, I, 1] agents still driving
        ret = torch.where(add, ret + gamma**k * reward.index_select(1, ahead), ret)
        steps = steps + add.to(steps.dtype)
        done = torch.where(add, done_i.index_select(1, ahead), done)
        term = torch.where(add, term_i.index_select(1, ahead), term)
        last = torch.where(extend, ahead, last)
        extend = extend & ~episode_end.index_select(1, ahead)

    out = rows.clone(False)
    road = torch.arange(rows.shape[0], device=last.device).unsqueeze(-1)  # [N, 1]
    out.set("next", nxt[road, last].clone())
    out.set(("next", *REWARD), ret)
    out.set(("next", *DONE), done)
    out.set(("next", *TERMINATED), term)
    out.set(STEPS_TO_NEXT_OBS, steps)
    return out.reshape(*lead, steps_total)
