"""Behaviour-model predictions of the other cars, for the sequential planner (iLQR).

The paper's iLQR predicts every opponent at constant speed and constant lateral offset
(:func:`planners.ilqr.predict_constant_velocity`). A car that brakes for a chicane, or
accelerates out of one, is then predicted tens of metres from where it will be within the
5 s horizon. Here a *model* of how the opponents drive is rolled forward instead: each
modelled car is driven by a policy through the environment's own physics
(:func:`racing_env.physics.drive`), one step of ``game.dt`` at a time.

Against a car that does drive by that policy and ignores the others (the scripted lane
keeper), the prediction is exact; against any other driver it is a model error like the
constant-velocity one, only a different one.
"""

from __future__ import annotations

from typing import Callable, Mapping

import jax
import numpy as np

from planners.scripted import LaneKeeping
from racing_env.dynamics import STATE_DIM
from racing_env.physics import drive

Driver = Callable[[np.ndarray], np.ndarray]
"""A driving policy: joint state ``(N, 6)`` -> the car's normalised jerk action ``(2,)``."""

CONSTANT_VELOCITY = "constant-velocity"
LANE_KEEPING = "lane-keeping"
PREDICTIONS = (CONSTANT_VELOCITY, LANE_KEEPING)
"""The predictions an iLQR agent can plan against (its ``prediction`` option)."""

__all__ = ["CONSTANT_VELOCITY", "Driver", "LANE_KEEPING", "PREDICTIONS", "PolicyRollout", "check_prediction",
           "make_predictor"]


def check_prediction(name: str) -> None:
    """Refuse a prediction name that is not one of :data:`PREDICTIONS`."""
    if name not in PREDICTIONS:
        raise ValueError(f"unknown prediction {name!r}; choose one of {list(PREDICTIONS)}")


class PolicyRollout:
    """Predicts the joint trajectory by driving every modelled car with its policy.

    Args:
        game: the :class:`racing_env.RaceGame` raced (track, vehicles, ``dt``, ``horizon``).
        drivers: ``{car index: driver}``; the cars without a driver get zero jerk (for the
            planning car its row is replaced by its plan anyway).

    Calling it with a joint state ``x0 (N, 6)`` returns ``(horizon + 1, N, 6)``, row 0 being
    ``x0``. Every driver sees the predicted joint state of its step. The rollout knows
    nothing of the race's end (a finished car keeps driving) and takes about 20 us per
    step plus the drivers' own time (Intel Xeon: 1.4-1.8 ms for 50 steps of one lane
    keeper). The physics step is compiled at the first call.
    """

    def __init__(self, game, drivers: Mapping[int, Driver]) -> None:
        n = game.num_players
        bad = [j for j in drivers if not 0 <= int(j) < n]
        if bad:
            raise ValueError(f"driver car indices must be in [0, {n}), got {bad}")
        self.game = game
        self.drivers = {int(j): driver for j, driver in drivers.items()}
        self._step = None  # the jitted physics step, made at the first call

    def __call__(self, x0) -> np.ndarray:
        x = np.asarray(x0, dtype=np.float64)
        n = self.game.num_players
        if x.shape != (n, STATE_DIM):
            raise ValueError(f"x0 must have shape (N, 6) = ({n}, {STATE_DIM}), got {x.shape}")
        if self._step is None:
            game = self.game  # closed over: its arrays become constants of the compiled step
            self._step = jax.jit(lambda state, actions: drive(game, state, actions))
        out = np.empty((self.game.horizon + 1, n, STATE_DIM))
        out[0] = x
        actions = np.zeros((n, 2))
        for t in range(self.game.horizon):
            for j, driver in self.drivers.items():
                actions[j] = driver(x)
            x = np.asarray(self._step(x, actions))
            out[t + 1] = x
        return out


def _lane_keeper(game, car: int) -> Driver:
    controller = LaneKeeping(game.track, car, game.vehicles.car(car))
    return lambda x: controller(None, x)


def make_predictor(name: str, game, ego: int) -> Callable[[np.ndarray], np.ndarray] | None:
    """The prediction ``name`` (one of :data:`PREDICTIONS`) for car ``ego`` in ``game``.

    ``"constant-velocity"``: ``None`` (the planner's own default, the paper's prediction).
    ``"lane-keeping"``: a :class:`PolicyRollout` driving every other car by the scripted
    lane keeper's law (:class:`planners.scripted.LaneKeeping` with its defaults: the centre
    line at the car's ``v_max``, slowing for the curves ahead).
    """
    check_prediction(name)
    if name == CONSTANT_VELOCITY:
        return None
    others = [j for j in range(game.num_players) if j != ego]
    return PolicyRollout(game, {j: _lane_keeper(game, j) for j in others})
