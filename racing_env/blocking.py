"""Blocking moves, counted from a race's states: the defence the steward's rules allow.

A car **defends** while another racing car is behind it within the steward's
:attr:`~racing_env.steward.Steward.defend_gap` (20 m by default). A **defending move** is a
run of consecutive steps in which the car ahead moves across the track towards the side the
car behind is on (its lateral speed relative to the track, ``v sin(chi)`` [m/s], towards the
other car's offset, above the steward's ``across_speed``, 0.5 m/s by default): the move that
closes the door. A defending move is a **block** when the car behind is still behind
``hold`` seconds after the move ends (or when the race ends for either of them, if sooner):
the move kept it there. Contact is not required and not judged here; the steward judges the
moves that end in contact (docs/rules.md).

Shapes: joint states ``xs (T + 1, N, 6)`` (``racing_env.dynamics`` order: ``s`` cumulative
race distance [m], ``v``, ``n`` [m], ``chi`` [rad], ...), ``racing (T + 1, N)`` bool (each car
still in the race at each step).
"""

from __future__ import annotations

import itertools
from typing import NamedTuple

import numpy as np

from racing_env.dynamics import CHI, N_LAT, S, V
from racing_env.steward import ACROSS_SPEED, DEFEND_GAP  # the steward's full-size defaults

HOLD = 3.0
"""[s] how long after a defending move the car behind must still be behind for a block."""


class Blocking(NamedTuple):
    """Each car's defence in a race; every field has shape ``(N,)`` (int).

    Attributes:
        defending_moves: the car's moves across towards a car defending against it.
        blocks: those of its defending moves after which that car stayed behind for ``hold``.
        blocked: the blocks other cars made against this car.
    """

    defending_moves: np.ndarray
    blocks: np.ndarray
    blocked: np.ndarray


def _runs(flags: np.ndarray) -> list[tuple[int, int]]:
    """The ``(start, end)`` step indices (end exclusive) of the runs of True in ``flags (T,)``."""
    edges = np.diff(np.concatenate([[0], flags.astype(np.int8), [0]]))
    return list(zip(np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)))


def count_blocks(xs: np.ndarray, racing: np.ndarray | None = None, *, dt: float = 0.1,
                 defend_gap: float = DEFEND_GAP, across_speed: float = ACROSS_SPEED,
                 hold: float = HOLD) -> Blocking:
    """Each car's defending moves and blocks (module docstring) in the race ``xs (T + 1, N, 6)``.

    Args:
        xs: joint states at every step.
        racing: ``(T + 1, N)`` bool, each car still racing; a step counts only while both
            cars of a pair race. None: all cars race throughout.
        dt: [s] the time step.
        defend_gap: [m] the distance behind within which a car defends (> 0).
        across_speed: [m/s] the lateral speed that counts as a move across (>= 0).
        hold: [s] how long the car behind must stay behind for a block (>= 0).
    """
    xs = np.asarray(xs, dtype=float)
    if xs.ndim != 3 or xs.shape[2] <= CHI:
        raise ValueError(f"xs must have shape (T + 1, N, 6), got {xs.shape}")
    if not (defend_gap > 0 and across_speed >= 0 and hold >= 0 and dt > 0):
        raise ValueError(f"need defend_gap > 0, across_speed >= 0, hold >= 0 and dt > 0, got defend_gap={defend_gap}, "
                         f"across_speed={across_speed}, hold={hold}, dt={dt}")
    steps, num = xs.shape[:2]
    racing = np.ones((steps, num), dtype=bool) if racing is None else np.asarray(racing, dtype=bool)
    s, n = xs[:, :, S], xs[:, :, N_LAT]
    lateral = xs[:, :, V] * np.sin(xs[:, :, CHI])  # [m/s] across the track, to the left > 0
    hold_steps = int(round(hold / dt))
    moves, blocks, blocked = (np.zeros(num, dtype=int) for _ in range(3))
    for i, j in itertools.permutations(range(num), 2):  # i defends against j behind it
        both = racing[:, i] & racing[:, j]
        gap = s[:, i] - s[:, j]
        towards = lateral[:, i] * np.sign(n[:, j] - n[:, i])
        defending = both & (gap > 0.0) & (gap <= defend_gap) & (towards > across_speed)
        for _, end in _runs(defending):
            moves[i] += 1
            last = min(end - 1 + hold_steps, steps - 1)
            still = both[end - 1:last + 1]  # from the move's last step until the hold ends or a car stops racing
            stop = end - 1 + (int(np.argmin(still)) if not still.all() else len(still))
            if np.all(gap[end - 1:stop] > 0.0):
                blocks[i] += 1
                blocked[j] += 1
    return Blocking(defending_moves=moves, blocks=blocks, blocked=blocked)
