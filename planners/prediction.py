"""Predictions of the other cars for the sequential planner (iLQR); see docs/agents.md.

The paper's iLQR predicts every opponent at constant speed and constant lateral offset
(:func:`planners.ilqr.predict_constant_velocity`). A car that brakes for a chicane, or
accelerates out of one, is then predicted far from where it will be within a 5 s horizon.
Two other kinds of prediction live here:

* a *behaviour model* rolled forward (:class:`PolicyRollout`): each modelled car is driven
  by a policy through the environment's own physics (:func:`racing_env.physics.drive`),
  one step of ``game.dt`` at a time. ``"lane-keeping"`` drives the others by the scripted
  lane keeper's law;
* a *planner in the other cars' place* (:class:`PlannerPrediction`): the others' plans as
  a planner with the game's costs would make them. ``"ilqr"``: each other car's own iLQR
  plan against the constant-velocity prediction of the rest (one level of reasoning above
  the paper's prediction), or with ``levels=k`` against everyone's plans one level down
  (level-k thinking); ``"ilqgame-fb"`` / ``"ilqgame-ol"``: the others' trajectories
  of the feedback / open-loop Nash equilibrium of the whole game. The ego then plans its
  best response to those trajectories, which separates the equilibrium as a *prediction*
  from the equilibrium as a *policy* (the iLQGame agents).

Each prediction has the name of its method (:data:`planners.methods.PREDICTIONS`: the same
strings as the agents'; ``CONSTANT_VELOCITY``, ``ILQR``, ... here are those of
:mod:`planners.methods`). A prediction named after an agent is exact against that agent when
it drives as predicted: the lane keeper (which ignores the others), or an ``ilqr`` agent with the same
weights and solver options (same start state, same warm start, same solve). Against any
other driver it is a model error like the constant-velocity one, only a different one.
"""

from __future__ import annotations

from typing import Any, Callable, Mapping

import jax
import numpy as np

from planners import ilq, ilqr, rival_game
from planners.methods import (
    CONSTANT_VELOCITY,
    FEEDBACK,
    FEEDBACK_GAME,
    GAME_MODES,
    ILQR,
    LANE_KEEPING,
    OPEN_LOOP_GAME,
    PLANNERS,
    PREDICTIONS,
)
from planners.scripted import LaneKeeping
from racing_env.dynamics import STATE_DIM
from racing_env.physics import drive

Driver = Callable[[np.ndarray], np.ndarray]
"""A driving policy: joint state ``(N, 6)`` -> the car's normalised jerk action ``(2,)``."""

Predictor = Callable[[Any, np.ndarray, "np.ndarray | None"], "tuple[np.ndarray, np.ndarray | None]"]
"""``(game, x0 (N, 6), U0 (T, N, 2) or None) -> (xs (T+1, N, 6), us (T, N, 2) or None)``: the
predicted joint trajectory from ``x0`` and, for a planner's prediction, the others' planned
jerks [m/s^3] (``U0``: those of the previous prediction shifted to now, its warm start)."""

__all__ = ["CONSTANT_VELOCITY", "Driver", "FEEDBACK_GAME", "ILQR", "LANE_KEEPING", "OPEN_LOOP_GAME", "PREDICTIONS",
           "PlannerPrediction", "PolicyRollout", "Predictor", "check_levels", "check_prediction",
           "make_predictor"]


def check_prediction(name: str) -> None:
    """Refuse a prediction name that is not one of :data:`PREDICTIONS`."""
    if name not in PREDICTIONS:
        raise ValueError(f"unknown prediction {name!r}; choose one of {list(PREDICTIONS)}")


def check_levels(name: str, levels: int) -> None:
    """Refuse ``levels`` of reasoning other than a positive integer, or other than 1 for a
    prediction that has no levels (all but ``"ilqr"``)."""
    if isinstance(levels, bool) or int(levels) != levels or levels < 1:
        raise ValueError(f"levels must be a positive integer, got {levels!r}")
    if levels != 1 and name != ILQR:
        raise ValueError(f"levels apply to the {ILQR!r} prediction only, not to {name!r}")


class PolicyRollout:
    """Predicts the joint trajectory by driving every modelled car with its policy.

    Args:
        game: the :class:`racing_env.RaceGame` raced (track, vehicles, ``dt``, ``horizon``).
        drivers: ``{car index: driver}``; the cars without a driver get zero jerk (for the
            planning car its row is replaced by its plan anyway).

    Calling it with a joint state ``x0 (N, 6)`` returns ``(horizon + 1, N, 6)``, row 0 being
    ``x0``. Every driver sees the predicted joint state of its step. The rollout knows
    nothing of the race's end (a finished car keeps driving). The physics step is compiled
    at the first call; a step then costs little next to the drivers' own time
    (docs/performance.md).
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


def check_solver_options(prediction: str, **solver_options: Any) -> None:
    """Refuse :class:`planners.ilq.SolverOptions` fields that the solves of a planned
    ``prediction`` (``"ilqr"`` or a game) cannot take, in the mode they use; other
    predictions solve nothing and take any."""
    if prediction in PLANNERS:
        options = ilq.SolverOptions(**{**solver_options, "mode": GAME_MODES.get(prediction, FEEDBACK)})
        ilq.check_adaptive_regularization(options, 2 if prediction in GAME_MODES else 1)


class PlannerPrediction:
    """Predicts the other cars by the plans a planner in their place would make.

    Args:
        planner: ``"ilqr"`` (each other car ``j`` planned by :func:`planners.ilqr.solve_ilqr`
            as the ego, against a prediction of every other car, the predicting car
            included; see ``levels``), ``"ilqgame-fb"`` or ``"ilqgame-ol"`` (the whole game
            solved by :func:`planners.ilq.solve` in feedback / open-loop mode).
        ego: the predicting car (its row of the prediction is not a prediction: for
            ``"ilqr"`` its constant-velocity motion or its own plan of the level below, for
            the games its equilibrium plan).
        rivals: for the games, the rivals ``k`` of the predicting car in the game solved: in a
            race of more than ``k + 1`` cars its local game with its ``k`` nearest rivals
            (:mod:`planners.rival_game`), whose equilibrium predicts those rivals; every
            other car is predicted at constant speed and lateral offset.
        obstacles: for the games, the other cars the local game predicts as moving
            obstacles, nearest first (None: all).
        levels: for ``"ilqr"``, the levels of reasoning (level-k thinking). Level 0 is the
            constant-velocity prediction of every car; a car's level-``k`` plan is its iLQR
            best response to the level-``k - 1`` plans of all the others. The prediction is
            the others' level-``levels`` plans (``1``: each against constant velocity).
            Every level above the first also plans the predicting car. Where the levels
            settle, they settle on an open-loop Nash equilibrium: a profile of trajectories
            that are best responses to each other (docs/agents.md shows them approach it in
            the paper's scene).
        solver_options: :class:`planners.ilq.SolverOptions` fields of these solves
            (``max_iterations``, ``tolerance``, ...), e.g. those of the predicting agent.

    Calling it with ``(game, x0 (N, 6), U0)`` returns ``(xs (T+1, N, 6), us (T, N, 2))``;
    ``U0`` (or ``None``: zeros) is the warm start, row ``j`` for car ``j``'s own solve at
    the first level (each level above starts from the car's plan of the level below). A
    solve that does not converge contributes its last iterate, as an agent would drive it.
    The cost is that of the solves: ``levels * N - 1`` iLQR solves, or one game solve.
    """

    def __init__(self, planner: str, ego: int, levels: int = 1, rivals: int = 2, obstacles: int | None = None,
                 **solver_options: Any) -> None:
        if planner not in PLANNERS:
            raise ValueError(f"planner must be one of {list(PLANNERS)}, got {planner!r}")
        check_levels(planner, levels)
        self.rivals = rival_game.check_rivals(rivals)
        self.obstacles = rival_game.check_obstacles(obstacles)
        check_solver_options(planner, **solver_options)  # now, not at the first solve
        self.planner = planner
        self.ego = int(ego)
        self.levels = int(levels)
        self.solver_options = dict(solver_options)

    def __call__(self, game, x0, U0=None) -> tuple[np.ndarray, np.ndarray]:
        x0 = np.asarray(x0, dtype=np.float64)
        if self.planner in GAME_MODES:
            options = {**self.solver_options, "mode": GAME_MODES[self.planner]}
            if self.rivals >= game.num_players - 1:
                res = ilq.solve(game, x0, init=U0, **options)
                return np.asarray(res.xs), np.asarray(res.us)
            local = rival_game.local_game(game, x0, self.ego, self.rivals, U0, obstacles=self.obstacles)
            ilq.validate_problem(game)
            res = jax.device_get(ilq.solve(local.problem, local.x0, init=local.init, validate=False, **options))
            xs, us, _ = rival_game.to_field(local, res.xs, res.us, None, U0)
            return xs, us
        xs = np.array(ilqr.predict_constant_velocity(game, x0))  # level 0
        us = np.zeros((game.horizon, game.num_players, game.input_dim)) if U0 is None else np.array(U0)
        for level in range(1, self.levels + 1):
            # the predicting car's own top-level plan is the agent's to make, not a prediction
            cars = [j for j in range(game.num_players) if level < self.levels or j != self.ego]
            below = xs.copy()  # every car plans against the level below, not a half-updated one
            for j in cars:
                res = ilqr.solve_ilqr(game, x0, ego=j, U0=us[:, j], predicted=below, **self.solver_options)
                xs[:, j] = np.asarray(res.xs[:, j])
                us[:, j] = np.asarray(res.us[:, j])
        return xs, us


def _lane_keeper(game, car: int) -> Driver:
    controller = LaneKeeping(game.track, car, game.vehicles.car(car))
    return lambda x: controller(None, x)


def make_predictor(name: str, game, ego: int, levels: int = 1, rivals: int = 2, obstacles: int | None = None,
                   **solver_options: Any) -> Predictor | None:
    """The prediction ``name`` (one of :data:`PREDICTIONS`) for car ``ego`` in ``game``.

    ``"constant-velocity"``: ``None`` (the planner's own default, the paper's prediction).
    ``"lane-keeping"``: a :class:`PolicyRollout` driving every other car by the scripted
    lane keeper's law (:class:`planners.scripted.LaneKeeping` with its defaults: the centre
    line at the car's ``v_max``, slowing for the curves ahead); it drives in ``game``
    whatever game it is called with, and predicts no jerks. ``"ilqr"``, ``"ilqgame-fb"``,
    ``"ilqgame-ol"``: a :class:`PlannerPrediction` with ``solver_options`` (and ``levels``
    of reasoning for ``"ilqr"``, ``rivals`` and ``obstacles`` in the game for the games); it plans in the game it
    is called with (the predicting
    agent's beliefs of the others' weights).
    """
    check_prediction(name)
    check_levels(name, levels)
    if name == CONSTANT_VELOCITY:
        return None
    if name in PLANNERS:
        return PlannerPrediction(name, ego, levels=levels, rivals=rivals, obstacles=obstacles, **solver_options)
    others = [j for j in range(game.num_players) if j != ego]
    rollout = PolicyRollout(game, {j: _lane_keeper(game, j) for j in others})
    return lambda _game, x0, U0=None: (rollout(x0), None)
