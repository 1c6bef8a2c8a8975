"""Sequential baseline of the paper: iLQR against predictions of the opponents.

The ego car (player ``ego`` of a :class:`racing_env.RaceGame`) predicts every opponent
``j`` from its current state at constant speed and constant lateral offset::

    s_j(t) = s_j0 + V_j0 * t * dt,   V_j = V_j0,   n_j = n_j0,   chi_j = ax_j = ay_j = 0,

and then solves the single-player problem (for a car with drag, its dynamics take the
slipstream of the predicted cars at each stage) whose stage cost is the game's stage cost of the
ego evaluated at the joint state ``[ego state; predicted opponents at stage t]`` (collision,
track, acceleration limits, jerk) and whose terminal cost is the ego's terminal cost (the
opponents' progress enters as a constant). That prediction is the paper's; others can be
passed in (``predicted``, e.g. from :mod:`planners.prediction`, which rolls a model of the
opponents' driving forward). It is :func:`planners.ilq.solve` with ``N = 1`` and a
time-varying problem (the prediction is part of the problem's ``params``, so new
start states or weights re-use the compiled solver).
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from planners import ilq, methods, race_problem
from planners.game_problem import GameProblem
from planners.precision import require_x64
from racing_env.dynamics import STATE_DIM, rk4_step

Array = jax.Array

__all__ = ["ILQRResult", "ego_problem", "predict_constant_velocity", "solve_ilqr"]


class ILQRResult(NamedTuple):
    """Outcome of :func:`solve_ilqr` (a pytree).

    Attributes:
        xs: ``(T+1, N, 6)`` joint trajectory: the ego's plan in row ``ego``, the opponents'
            predictions in the other rows.
        us: ``(T, N, 2)`` joint inputs: the ego's planned jerks in row ``ego``, zeros for the
            opponents (their predicted motion has zero jerk).
        predicted: ``(T+1, N, 6)`` the prediction the ego planned against: the one passed
            as ``predicted``, else the constant-velocity prediction of every car (the
            opponents' rows are what matters; the ego's row is not used).
        ego: index of the ego car.
        cost: the ego's total cost of the plan against the prediction.
        converged, status, iterations: as in :class:`planners.ilq.SolverResult`.
        plan: the single-player :class:`planners.ilq.SolverResult` (``xs (T+1, 6)``,
            ``us (T, 1, 2)``, ``K (T, 1, 2, 6)``, ``k``, histories).
    """

    xs: Array
    us: Array
    predicted: Array
    ego: Array
    cost: Array
    converged: Array
    status: Array
    iterations: Array
    plan: ilq.SolverResult


def predict_constant_velocity(game, x0) -> Array:
    """Constant-speed, constant-offset prediction of all cars: ``(T+1, N, 6)``.

    ``s(t) = s_0 + V_0 t dt``, ``V = V_0``, ``n = n_0``, ``chi = ax = ay = 0``. A concrete
    ``x0`` is predicted in NumPy (the same IEEE operations as JAX op by op, so the same
    numbers, without a device dispatch per operation inside an agent's re-plan), a traced
    one in ``jax.numpy``.
    """
    xp = jnp if isinstance(x0, jax.core.Tracer) else np
    x0 = xp.asarray(x0)
    if not xp.issubdtype(x0.dtype, xp.floating):
        x0 = x0.astype(jnp.result_type(float))
    steps = game.horizon + 1
    t = xp.arange(steps, dtype=x0.dtype)[:, None] * game.dt  # (T+1, 1)
    s = x0[:, 0] + x0[:, 1] * t  # (T+1, N)
    held = [xp.broadcast_to(x0[:, k], s.shape) for k in (1, 2)]  # V and n
    zeros = xp.zeros_like(s)
    return jnp.asarray(xp.stack([s, *held, zeros, zeros, zeros], axis=-1))


class _EgoParams(NamedTuple):
    game: object  # RaceGame
    predicted: Array  # (T+1, N, 6)
    ego: Array  # int scalar


def _ego_dynamics(params: _EgoParams, t, x, u):
    if not params.game.drag:
        return rk4_step(x, u[0], params.game.dt, params.game.track.kappa_at)
    # With drag the ego's speed depends on the wakes of the cars ahead: the joint step of the
    # ego and the predicted cars (at zero jerk from their stage-t prediction), the ego's row.
    joint = _ego_joint(params, t, x)
    inputs = jnp.zeros((joint.shape[0], u.shape[-1]), u.dtype).at[params.ego].set(u[0])
    return params.game.step(joint, inputs)[params.ego]


def _ego_joint(params: _EgoParams, t, x):
    return params.predicted[t].at[params.ego].set(x)


def _ego_stage_cost(params: _EgoParams, t, i, x, u_i):
    del i  # the only player
    return params.game.stage_cost(params.ego, _ego_joint(params, t, x), u_i)


def _ego_terminal_cost(params: _EgoParams, i, x):
    del i
    joint = _ego_joint(params, params.predicted.shape[0] - 1, x)
    return params.game.terminal_cost(params.ego, joint)


def _ego_stage_gauss_newton(params: _EgoParams, t, i, x, u_i):
    del i
    joint = _ego_joint(params, t, x).reshape(-1)
    return race_problem.race_stage_gauss_newton(params.game, t, params.ego, joint, u_i)


def _ego_stage_curvature(params: _EgoParams, t, i, x):
    del i
    joint = _ego_joint(params, t, x).reshape(-1)
    return race_problem.race_stage_curvature(params.game, t, params.ego, joint).reshape(-1, STATE_DIM)[params.ego]


def _ego_terminal_gauss_newton(params: _EgoParams, i, x):
    del i
    joint = _ego_joint(params, params.predicted.shape[0] - 1, x).reshape(-1)
    return race_problem.race_terminal_gauss_newton(params.game, params.ego, joint)


def _checked_prediction(game, predicted) -> Array:
    """``predicted`` as an array of shape ``(T+1, N, 6)``, refused if misshapen or non-finite."""
    shape = (game.horizon + 1, game.num_players, STATE_DIM)
    if np.shape(predicted) != shape:
        raise ValueError(f"predicted must have shape (T+1, N, 6) = {shape}, got {np.shape(predicted)}")
    if not isinstance(predicted, jax.core.Tracer) and not np.all(np.isfinite(np.asarray(predicted))):
        raise ValueError("predicted contains non-finite values")
    return jnp.asarray(predicted)


def ego_problem(game, x0, ego: int = 0, predicted=None) -> GameProblem:
    """The ego's single-player :class:`planners.game_problem.GameProblem` against a prediction.

    ``predicted (T+1, N, 6)``: the opponents' predicted trajectories (the ego's row is
    ignored); ``None`` is the paper's :func:`predict_constant_velocity`. Other predictions:
    :mod:`planners.prediction`.
    """
    x0 = jnp.asarray(x0)
    if x0.shape != (game.num_players, STATE_DIM):
        raise ValueError(
            f"x0 must have shape (N, 6) = ({game.num_players}, {STATE_DIM}), got {x0.shape}"
        )
    if not isinstance(ego, jax.core.Tracer) and not 0 <= int(ego) < game.num_players:
        raise ValueError(f"ego must be a car index in [0, {game.num_players}), got {ego!r}")
    if predicted is None:
        predicted = predict_constant_velocity(game, x0)
    else:
        predicted = _checked_prediction(game, predicted).astype(x0.dtype)
    params = _EgoParams(
        game=game,
        predicted=predicted,
        ego=jnp.asarray(ego, dtype=jnp.int32),
    )
    return GameProblem(
        dynamics=_ego_dynamics,
        stage_cost=_ego_stage_cost,
        terminal_cost=_ego_terminal_cost,
        num_players=1,
        state_dim=STATE_DIM,
        input_dim=game.input_dim,
        horizon=game.horizon,
        params=params,
        # the game's Gauss-Newton form of the ego's costs, opponents fixed at the prediction
        stage_gauss_newton=_ego_stage_gauss_newton,
        terminal_gauss_newton=_ego_terminal_gauss_newton,
        stage_curvature=_ego_stage_curvature,
    )


def solve_ilqr(game, x0, ego: int = 0, U0=None, *, predicted=None, options=None, budget_ms=None,
               **overrides) -> ILQRResult:
    """Plan the ego's inputs by iLQR against predictions of the opponents.

    Args:
        game: a :class:`racing_env.RaceGame`.
        x0: joint start state ``(N, 6)``.
        ego: index of the planning car.
        U0: initial ego inputs: ``None`` (zeros), ``(T, 2)``, ``(T, 1, 2)``, joint
            ``(T, N, 2)`` (the ego's row is used), or a previous result.
        predicted: the opponents' trajectories ``(T+1, N, 6)`` to plan against (the ego's
            row is ignored); ``None``: the paper's constant-velocity prediction
            (:func:`predict_constant_velocity`). See :mod:`planners.prediction`.
        options, overrides: :class:`planners.ilq.SolverOptions` and field overrides. The
            ``mode`` is irrelevant for one player (feedback and open loop coincide); the
            feedback recursion is used.
        budget_ms: a wall-clock budget [ms] of the solve (see :func:`planners.ilq.solve`).

    Returns:
        :class:`ILQRResult`.

    Needs 64-bit floats (``jax_enable_x64``), as :func:`planners.ilq.solve`.
    """
    require_x64("planners.ilqr.solve_ilqr")
    x0 = jnp.asarray(x0)
    if not jnp.issubdtype(x0.dtype, jnp.floating):
        x0 = x0.astype(jnp.result_type(float))
    problem = ego_problem(game, x0, ego, predicted)
    T = game.horizon
    if U0 is not None:
        U0 = ilq.as_array(getattr(U0, "us", U0))  # NumPy stays NumPy: no eager device ops
        if U0.shape == (T, game.num_players, game.input_dim) and game.num_players > 1:
            U0 = U0[:, ego]
        U0 = U0.reshape(T, 1, game.input_dim)
    overrides.setdefault("mode", methods.FEEDBACK)
    options = ilq.resolve_options(options, overrides)
    ilq.validate_problem(game, control_regularization=options.guaranteed_control_regularization)
    plan = ilq.solve(problem, x0[ego], U0, options=options, validate=False, budget_ms=budget_ms)
    pred = problem.params.predicted
    xs = pred.at[:, ego].set(plan.xs)
    us = jnp.zeros((T, game.num_players, game.input_dim), plan.us.dtype).at[:, ego].set(
        plan.us[:, 0]
    )
    return ILQRResult(
        xs=xs,
        us=us,
        predicted=pred,
        ego=problem.params.ego,
        cost=plan.costs[0],
        converged=plan.converged,
        status=plan.status,
        iterations=plan.iterations,
        plan=plan,
    )
