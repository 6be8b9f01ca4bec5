"""Metric functions on hand-made trajectories (MA-PETS paper eqs. 27-28)."""

import numpy as np
import pytest

from mapets_rl.metrics import agility, average_comfort, average_velocity, safety


def test_agility_and_safety_closed_form() -> None:
    # 2 agents, 4 steps. Agent 0 never collides: 1 m/step; agent 1 collides in step 2, so it
    # completed t_c = 1 step before the collision (distances 3, 5 of the 2 driven steps count,
    # later steps ignored).
    distances = np.array([[1.0, 3.0], [1.0, 5.0], [1.0, 9.0], [1.0, 9.0]])
    collision_steps = np.array([4, 1])
    assert agility(distances, collision_steps) == pytest.approx((4 / 4 + 8 / 2) / 2)
    assert safety(collision_steps, horizon=4) == pytest.approx((4 / 4 + 1 / 4) / 2)


def test_no_collision_gives_safety_one_and_mean_distance() -> None:
    distances = np.full((10, 3), 1.3)
    assert agility(distances, np.full(3, 10)) == pytest.approx(1.3)
    assert safety(np.full(3, 10), 10) == 1.0


def test_crash_in_the_last_step_is_not_safe() -> None:
    # H = 8 steps, one of 8 CAVs collides in step 8: it completed t_c = 7 < H steps.
    horizon, distances = 8, np.full((8, 8), 1.0)
    collision_steps = np.array([horizon] * 7 + [horizon - 1])
    assert safety(collision_steps, horizon) == pytest.approx((7 + 7 / 8) / 8)
    assert safety(collision_steps, horizon) < 1.0
    assert agility(distances, collision_steps) == pytest.approx(1.0)  # 8 m over 8 driven steps


def test_crash_in_the_first_step_counts_its_distance() -> None:
    distances = np.array([[2.0, 4.0], [2.0, 0.0]])
    collision_steps = np.array([2, 0])  # agent 1 collides in step 1: t_c = 0
    assert safety(collision_steps, 2) == pytest.approx((1 + 0) / 2)
    assert agility(distances, collision_steps) == pytest.approx((2 + 4) / 2)


def test_freeway_averages() -> None:
    assert average_velocity([[20.0, 30.0], [25.0, 25.0]]) == 25.0
    assert average_comfort([[3, 2], [1, 0]]) == 1.5


@pytest.mark.parametrize(
    "call,match",
    [
        (lambda: agility(np.ones((3, 2)), np.array([1, 2, 3])), "distances must be"),
        (lambda: agility(np.ones((3, 2)), np.array([-1, 2])), "collision_steps"),
        (lambda: agility(np.ones((0, 2)), np.array([1, 2])), "at least one step"),
        (lambda: safety(np.array([1]), 0), "horizon"),
        (lambda: safety(np.array([1]), 2.5), "horizon"),
        (lambda: safety(np.array([-1]), 3), "collision_steps"),
        (lambda: agility(np.full((2, 1), np.nan), np.array([2])), "finite"),
    ],
)
def test_bad_metric_input(call, match: str) -> None:
    with pytest.raises(ValueError, match=match):
        call()
