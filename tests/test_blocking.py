"""Blocking moves counted from hand-built races: each case's count follows from the definition."""

import numpy as np
import pytest

from racing_env.blocking import count_blocks
from racing_env.dynamics import CHI, N_LAT, S, V

DT = 0.1


def _duel(steps: int, gap: float, lateral_a: np.ndarray, n_b: float = 1.0, passes_at: int | None = None) -> np.ndarray:
    """Two cars at 20 m/s, car 0 ``gap`` metres ahead of car 1 (car 1 at offset ``n_b``);
    car 0's heading gives it the lateral speeds ``lateral_a (steps + 1,)`` [m/s]; from step
    ``passes_at`` car 1 is 5 m ahead instead."""
    xs = np.zeros((steps + 1, 2, 6))
    t = np.arange(steps + 1) * DT
    xs[:, :, V] = 20.0
    xs[:, 1, S] = 20.0 * t
    xs[:, 0, S] = xs[:, 1, S] + gap
    if passes_at is not None:
        xs[passes_at:, 0, S] = xs[passes_at:, 1, S] - 5.0
    xs[:, 0, CHI] = np.arcsin(lateral_a / 20.0)
    xs[:, 1, N_LAT] = n_b
    return xs


def test_a_move_towards_the_car_behind_that_keeps_it_behind_is_a_block():
    lateral = np.zeros(61)
    lateral[10:15] = 1.0  # one move of 0.5 s to the left, where car 1 is
    lateral[30:33] = 1.0  # and a second one
    got = count_blocks(_duel(60, 10.0, lateral), dt=DT)
    assert got.defending_moves.tolist() == [2, 0]
    assert got.blocks.tolist() == [2, 0]
    assert got.blocked.tolist() == [0, 2]


def test_moves_away_slow_moves_and_moves_out_of_range_are_not_defending():
    away = np.zeros(61)
    away[10:15] = -1.0  # away from car 1 (on its left)
    slow = np.zeros(61)
    slow[10:15] = 0.4  # under across_speed
    for xs in (_duel(60, 10.0, away), _duel(60, 10.0, slow), _duel(60, 25.0, np.where(away < 0, 1.0, 0.0))):
        got = count_blocks(xs, dt=DT)
        assert got.defending_moves.tolist() == [0, 0]


def test_a_move_after_which_the_car_behind_passes_within_the_hold_is_no_block():
    lateral = np.zeros(61)
    lateral[10:15] = 1.0
    passed = count_blocks(_duel(60, 10.0, lateral, passes_at=30), dt=DT)  # 1.6 s after the move's last step
    assert passed.defending_moves.tolist() == [1, 0]
    assert passed.blocks.tolist() == [0, 0]
    held = count_blocks(_duel(60, 10.0, lateral, passes_at=30), dt=DT, hold=1.0)
    assert held.blocks.tolist() == [1, 0]


def test_a_race_that_ends_within_the_hold_keeps_the_block_and_steps_out_of_the_race_do_not_count():
    lateral = np.zeros(61)
    lateral[55:58] = 1.0
    assert count_blocks(_duel(60, 10.0, lateral), dt=DT).blocks.tolist() == [1, 0]
    racing = np.ones((61, 2), dtype=bool)
    racing[50:, 1] = False  # car 1 retired before the move
    assert count_blocks(_duel(60, 10.0, lateral), racing, dt=DT).defending_moves.tolist() == [0, 0]


def test_bad_arguments_are_refused():
    with pytest.raises(ValueError, match="shape"):
        count_blocks(np.zeros((5, 2)))
    with pytest.raises(ValueError, match="defend_gap"):
        count_blocks(np.zeros((5, 2, 6)), defend_gap=0.0)
