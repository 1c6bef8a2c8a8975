"""Local games of a field: a car's game with its nearest rivals, the rest of the field predicted.

In a race of N cars a game planner that solved the game of the whole field would pay for
an LQ recursion over all N players, which grows with the cube of N. A car in a field races
the few cars around it: the *local game* of car ``ego`` is the game of ``ego`` and its
``k`` nearest rivals (:func:`nearest_rivals`, by wrapped track distance), solved as an
ordinary ``(k + 1)``-player game. The next ``m`` nearest cars (``obstacles``; None: every
other car) are predicted (constant speed and lateral offset,
:func:`planners.ilqr.predict_constant_velocity`, or any trajectory the caller passes) and
enter every player's costs as moving obstacles: their collision terms with the players, and
their progress in the players' terminal costs (a constant). The players' costs are the costs
of the game of these ``k + 1 + m`` cars, evaluated at the joint state ``[players; predicted
cars at stage t]``, so a local game differs from the whole game in that the predicted cars do
not react (with drag, their wakes reach the players: the players' step is the joint step of
the players and the predicted cars, which drive on at zero jerk within it; the wake of a car
left out of the local game is not modelled), and, with ``obstacles``, in the collision terms of
the cars further away, left out: a car's collision term falls as ``exp(-2 (ds / l)^2)`` with
the gap ``ds`` over its length scale ``l`` (:mod:`racing_env.costs`), below 1e-300 beyond ~19
lengths, so a car that stays that far from every player over the horizon adds nothing a
float64 sum keeps.
With ``obstacles`` a local game's size, and so its cost, does not grow with N.

:func:`local_game` builds the problem (a :class:`planners.game_problem.GameProblem` whose
``params`` is a :class:`RivalParams` pytree: the local games of every car of a field have
the same shapes and structure, so they share one compiled solver and can be solved as one
batch, :func:`planners.ilq_batch.solve_batch` with :func:`batch_axes`). :func:`to_field`
writes a local solution back in the field's shapes: the players' plans in their rows, the
predicted cars' predictions in theirs.

With ``k >= N - 1`` there is nothing to leave out: the callers then solve the race's game
itself (bit for bit today's solve), not a local game.

Shapes: field state ``x (N, 6)``; a local game of ``P = k + 1`` players has flat state
``(6 P,)``, inputs ``(T, P, 2)``, and ``M = min(m, N - P)`` predicted cars ``(T + 1, M, 6)``.
``order (N,)``: the field's car indices, the players first (``order[0]`` the ego, then the
rivals nearest first), then the other cars nearest first (the first ``M`` of them predicted).
"""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from planners import race_problem
from planners.game_problem import GameProblem
from planners.ilqr import predict_constant_velocity
from racing_env.dynamics import S, STATE_DIM

Array = jax.Array

__all__ = ["LocalGame", "RivalParams", "batch_axes", "check_obstacles", "check_rivals", "field_orders", "game_axes",
           "local_game", "predicted_count",
           "local_games", "local_problem", "nearest_rivals", "ordered_game", "stack_params", "to_field", "to_field_batch"]


def check_rivals(rivals) -> int:
    """``rivals`` as an int, refused unless it is an integer >= 1."""
    if isinstance(rivals, bool) or not isinstance(rivals, (int, np.integer)) or rivals < 1:
        raise ValueError(f"rivals must be an integer >= 1 (the rivals a car plays its game with), got {rivals!r}")
    return int(rivals)


def check_obstacles(obstacles) -> int | None:
    """``obstacles`` as an int (or None: every other car), refused unless None or an
    integer >= 1."""
    if obstacles is None:
        return None
    if isinstance(obstacles, bool) or not isinstance(obstacles, (int, np.integer)) or obstacles < 1:
        raise ValueError(f"obstacles must be None (every other car predicted) or an integer >= 1 (the nearest other "
                         f"cars predicted as moving obstacles), got {obstacles!r}")
    return int(obstacles)


def predicted_count(num_cars: int, players: int, obstacles: int | None) -> int:
    """``M``: the predicted cars of a local game of ``players`` players in a field of
    ``num_cars`` with ``obstacles`` (None: all the others)."""
    others = num_cars - players
    return others if obstacles is None else min(int(obstacles), others)


def nearest_rivals(track, x: np.ndarray, ego: int, k: int, racing: np.ndarray | None = None) -> np.ndarray:
    """The ``k`` rivals of car ``ego`` nearest by track distance, nearest first: ``(k,)`` ints.

    The distance is the wrapped gap in arc length ``|ds|`` (:meth:`racing_env.Track.wrap_ds`;
    ahead or behind alike, so the rivals are a window around the car). Cars still racing
    (``racing (N,)`` bool, None: all) come before cars out of the race, which are ghosts in
    the game; equal distances go to the lower index. ``x (N, 6)``; needs ``k <= N - 1``.
    """
    x = np.asarray(x)
    return field_orders(track, x[None], np.array([ego]), k, None if racing is None else np.asarray(racing)[None])[0, 1:k + 1]


def _xp(*arrays):
    """``jax.numpy`` if any of ``arrays`` is traced or a JAX array, else NumPy: the functions
    here run on the host in the agents' loops and inside compiled races alike."""
    return jnp if any(isinstance(a, jax.Array) for a in arrays) else np


def field_orders(track, x, egos, k: int, racing=None):
    """The car orders ``(R, N)`` of R local games (:class:`RivalParams`'s ``order``): in each,
    the ego ``egos[r]``, then every other car as :func:`nearest_rivals` ranks them in the
    fields ``x (R, N, 6)`` (``racing (R, N)`` bool or None): cars racing before ghosts,
    nearest first, equal distances to the lower index; the first ``k`` are the rivals.
    Needs ``1 <= k <= N - 1``. NumPy in, NumPy out; JAX arrays (also traced) in, JAX out."""
    xp = _xp(x, egos, racing)
    R, N = x.shape[:2]
    if not 1 <= k <= N - 1:
        raise ValueError(f"need 1 <= k <= N - 1 = {N - 1} rivals, got k={k}")
    index = xp.broadcast_to(xp.arange(N), (R, N))
    is_ego = index == xp.asarray(egos)[:, None]
    ego_s = xp.sum(xp.where(is_ego, x[:, :, S], 0.0), axis=1)
    gaps = xp.where(is_ego, -xp.inf, xp.abs(track.wrap_ds_in(x[:, :, S] - ego_s[:, None], xp)))
    out = xp.zeros((R, N), dtype=int) if racing is None else (~xp.asarray(racing, dtype=bool)).astype(int)
    rank = xp.where(is_ego, -1, out)
    # lexsort sorts by its last key first: ego, then racing before ghosts, then distance, then index
    return xp.lexsort((index, gaps, rank), axis=-1)


class RivalParams(NamedTuple):
    """The ``params`` of a local game (a pytree).

    Attributes:
        game: the field's :class:`racing_env.RaceGame` (its ``racing`` an array, all True
            when every car races), cars in their own order.
        order: ``(N,)`` the field's car indices, the players first (the ego, then its rivals
            nearest first), then the other cars nearest first. The functions of the problem
            take the game's first ``P + M`` cars in this order (:func:`ordered_game`), so that
            the local games of a field share the game's arrays and differ in ``order`` alone.
        predicted: ``(T + 1, M, 6)`` the predicted cars' trajectories, in
            ``order[P:P + M]``'s order.
    """

    game: object
    order: Array
    predicted: Array


def ordered_game(params: RivalParams, players: int):
    """The game of the local game's ``players`` players and ``M`` predicted cars: the
    field's game with its cars ``params.order[:players + M]`` (JAX gathers: traceable); the
    collision scale, where the game has one, in that order along both axes."""
    game, field = params.game, params.order.shape
    order = params.order[: players + params.predicted.shape[-2]]
    # a leaf is one value for every car (a scalar) or one per car along its first axis ((N,),
    # or (N, K) for the knots of stacked limit tables)
    take = lambda fields: jax.tree_util.tree_map(
        lambda leaf: jnp.broadcast_to(leaf, field)[order] if jnp.ndim(leaf) == 0 else jnp.asarray(leaf)[order], fields)
    # cars of one class share one VehicleParams (scalar fields; a table's knots (K,) are not per car)
    vehicles = game.vehicles if jnp.ndim(game.vehicles.v_max) == 0 else take(game.vehicles)
    scale = game.collision_scale
    scale = None if scale is None else jnp.asarray(scale)[order][:, order]
    return game.replace(vehicles=vehicles, weights=take(game.weights), racing=game.racing[order],
                        collision_scale=scale)


class LocalGame(NamedTuple):
    """A car's local game: the ``problem`` (``P`` players), its start ``x0 (6 P,)``, its warm
    start ``init (T, P, 2)``, the field's car indices ``order (N,)`` (players first) and
    the predictions of every car not playing, ``others (T + 1, N - P, 6)`` in ``order[P:]``'s
    order (the first ``M`` of them the problem's)."""

    problem: GameProblem
    x0: Array
    init: Array
    order: np.ndarray
    others: np.ndarray


def _players(x) -> int:
    """P, from the players' flat state ``x (6 P,)`` (static)."""
    return x.shape[-1] // STATE_DIM


def _field_state(params: RivalParams, t, x):
    """The flat field state ``(6 N,)`` at stage ``t``: the players' ``x (6 P,)``, then the
    predicted cars."""
    return jnp.concatenate([x, params.predicted[t].reshape(-1)])


def _dynamics(params: RivalParams, t, x, u):
    if not params.game.drag:
        return race_problem.race_dynamics(params.game, t, x, u)  # the step is the same for every car
    # With drag every car has its own, and the wakes of the predicted cars reach the players:
    # the joint step of the players and the predicted cars (at zero jerk from their stage-t
    # prediction), the players' rows.
    players = _players(x)
    field = _field_state(params, t, x).reshape(-1, STATE_DIM)
    inputs = jnp.concatenate([u, jnp.zeros((field.shape[0] - players, u.shape[-1]), u.dtype)])
    return ordered_game(params, players).step(field, inputs)[:players].reshape(-1)


def _dynamics_jacobians(params: RivalParams, t, x, u):
    if params.game.drag:
        return jax.jacfwd(lambda xx, uu: _dynamics(params, t, xx, uu), argnums=(0, 1))(x, u)
    return race_problem.race_dynamics_jacobians(params.game, t, x, u)


def _stage_cost(params: RivalParams, t, i, x, u_i):
    return race_problem.race_stage_cost(ordered_game(params, _players(x)), t, i, _field_state(params, t, x), u_i)


def _terminal_cost(params: RivalParams, i, x):
    last = params.predicted.shape[0] - 1
    return race_problem.race_terminal_cost(ordered_game(params, _players(x)), i, _field_state(params, last, x))


def _stage_gauss_newton(params: RivalParams, t, i, x, u_i):
    return race_problem.race_stage_gauss_newton(ordered_game(params, _players(x)), t, i, _field_state(params, t, x), u_i)


def _terminal_gauss_newton(params: RivalParams, i, x):
    last = params.predicted.shape[0] - 1
    return race_problem.race_terminal_gauss_newton(ordered_game(params, _players(x)), i, _field_state(params, last, x))


def _stage_curvature(params: RivalParams, t, i, x):
    return race_problem.race_stage_curvature(ordered_game(params, _players(x)), t, i, _field_state(params, t, x))[: x.shape[0]]


def _with_racing_array(game):
    """``game`` with its ``racing`` flags as an array (all True for None): every local game of
    a field then has the same pytree structure."""
    return game if game.racing is not None else game.replace(racing=np.ones(game.num_players, dtype=bool))


def local_problem(players: int, state_dim: int, input_dim: int, horizon: int, params: RivalParams) -> GameProblem:
    """The local game of ``players`` players (each with ``state_dim`` states and ``input_dim``
    inputs, over ``horizon`` stages) with ``params`` (one game's, or stacked ones)."""
    return GameProblem(
        dynamics=_dynamics,
        stage_cost=_stage_cost,
        terminal_cost=_terminal_cost,
        num_players=players,
        state_dim=players * state_dim,
        input_dim=input_dim,
        horizon=horizon,
        params=params,
        stage_gauss_newton=_stage_gauss_newton,
        terminal_gauss_newton=_terminal_gauss_newton,
        dynamics_jacobians=_dynamics_jacobians,
        stage_curvature=_stage_curvature,
    )


def _checked_rivals(rivals, num_cars: int) -> int:
    k = check_rivals(rivals)
    if k > num_cars - 2:
        raise ValueError(f"a local game leaves at least one car out: rivals must be <= N - 2 = {num_cars - 2}, "
                         f"got {k} (with rivals >= N - 1 the planner solves the whole game)")
    return k


def local_game(game, x0: np.ndarray, ego: int, rivals: int, init: np.ndarray | None = None,
               predicted: np.ndarray | None = None, obstacles: int | None = None) -> LocalGame:
    """Car ``ego``'s game with its ``rivals`` nearest rivals (module docstring).

    Args:
        game: the field's :class:`racing_env.RaceGame` (``N`` cars; its ``racing`` flags mark
            the ghosts, which are chosen as rivals only when too few cars race).
        x0: the field's state ``(N, 6)``.
        ego: the planning car.
        rivals: ``k``, ``1 <= k <= N - 2`` (with ``k >= N - 1`` solve ``game`` itself).
        init: the field's warm start ``(T, N, 2)`` [m/s^3] (None: zeros); the players' rows
            are the local game's warm start, so a rival keeps its own warm start whenever it
            is among the nearest.
        predicted: the field's predicted trajectories ``(T + 1, N, 6)`` (the players' rows are
            not used); None: constant speed and lateral offset from ``x0``.
        obstacles: the nearest other cars the game predicts as moving obstacles (None: all).
    """
    x0 = np.asarray(x0, dtype=np.float64)
    N, T = game.num_players, game.horizon
    if x0.shape != (N, STATE_DIM):
        raise ValueError(f"x0 must have shape (N, 6) = ({N}, {STATE_DIM}), got {x0.shape}")
    k = _checked_rivals(rivals, N)
    M = predicted_count(N, k + 1, check_obstacles(obstacles))
    racing = None if game.racing is None else np.asarray(game.racing)[None]
    order = field_orders(game.track, x0[None], np.array([ego]), k, racing)[0]
    players = order[: k + 1]
    if predicted is None:
        predicted = np.asarray(predict_constant_velocity(game, x0))
    elif np.shape(predicted) != (T + 1, N, STATE_DIM):
        raise ValueError(f"predicted must have shape (T+1, N, 6) = {(T + 1, N, STATE_DIM)}, got {np.shape(predicted)}")
    us = np.zeros((T, N, game.input_dim)) if init is None else np.asarray(init, dtype=np.float64)
    others = np.asarray(predicted)[:, order[k + 1:]]
    params = RivalParams(game=_with_racing_array(game), order=order, predicted=others[:, :M])
    problem = local_problem(k + 1, STATE_DIM, game.input_dim, T, params)
    return LocalGame(problem=problem, x0=x0[players].reshape(-1), init=us[:, players], order=order, others=others)


def local_games(game, x0s: np.ndarray, egos: np.ndarray, rivals: int, inits: np.ndarray, predicted: np.ndarray,
                obstacles: int | None = None) -> tuple[GameProblem, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """R local games at once (e.g. one car's in R races), for :func:`planners.ilq_batch.solve_batch`
    with ``params_axes=``:func:`batch_axes`.

    Args:
        game: the field's game with per-race ``weights`` and ``racing`` (leaves ``(R, N)``; the
            track and the cars' parameters shared).
        x0s: ``(R, N, 6)``; egos: ``(R,)``; rivals: ``k <= N - 2``; inits: ``(R, T, N, 2)``;
        predicted: ``(R, T + 1, N, 6)`` (the players' rows are not used).
        obstacles: the nearest other cars each game predicts as moving obstacles (None: all).

    Returns:
        ``(problem, x0 (R, 6 P), init (R, T, P, 2), orders (R, N), others (R, T + 1, N - P, 6))``:
        the problem's params are the R games stacked (:class:`RivalParams` with leading axis
        R); ``others`` the predictions of the cars not playing, in their orders (for
        :func:`to_field_batch`).
    """
    R, N = x0s.shape[:2]
    k = _checked_rivals(rivals, N)
    M = predicted_count(N, k + 1, check_obstacles(obstacles))
    orders = field_orders(game.track, x0s, np.asarray(egos), k, np.asarray(game.racing))
    rows = np.arange(R)[:, None]
    players = orders[:, : k + 1]
    others = np.transpose(predicted[rows, :, orders[:, k + 1:]], (0, 2, 1, 3))
    params = RivalParams(game=game, order=orders, predicted=others[:, :, :M])
    x0 = x0s[rows, players].reshape(R, -1)
    init = np.transpose(inits[rows, :, players], (0, 2, 1, 3))
    return local_problem(k + 1, STATE_DIM, game.input_dim, game.horizon, params), x0, init, orders, others


def batch_axes(local: LocalGame) -> RivalParams:
    """The ``params_axes`` of :func:`planners.ilq_batch.solve_batch` for local games stacked by
    :func:`stack_params`: the weights, racing flags, collision scales (where the games have
    them), orders and predictions batched, the track and the cars' parameters shared."""
    return RivalParams(game=game_axes(local.problem.params.game), order=0, predicted=0)


def game_axes(game):
    """The batch axes of games stacked along a new leading axis that share their track and
    cars' parameters: the weights, racing flags and collision scale (where the games have one)
    batched (a pytree of :class:`racing_env.RaceGame`'s shape for ``solve_batch``)."""
    scale = None if game.collision_scale is None else 0
    return game.replace(track=None, vehicles=None, weights=0, racing=0, collision_scale=scale)


def stack_params(locals_: list[LocalGame]) -> RivalParams:
    """The params of local games of one field (the same track and cars' parameters: those of
    the first are used) stacked along a new leading axis."""
    params = [local.problem.params for local in locals_]
    first = params[0].game
    N = first.num_players
    weights = {f.name: np.stack([np.broadcast_to(np.asarray(getattr(p.game.weights, f.name)), (N,)) for p in params])
               for f in dataclasses.fields(first.weights)}
    scale = None if first.collision_scale is None else np.stack([p.game.collision_scale for p in params])
    game = first.replace(weights=dataclasses.replace(first.weights, **weights),
                         racing=np.stack([p.game.racing for p in params]), collision_scale=scale)
    return RivalParams(game=game, order=np.stack([p.order for p in params]),
                       predicted=np.stack([p.predicted for p in params]))


def to_field(local: LocalGame, xs: np.ndarray, us: np.ndarray, K: np.ndarray | None, init: np.ndarray | None = None
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """A local solution in the field's shapes.

    Args:
        local: the local game solved.
        xs: its trajectory ``(T + 1, 6 P)`` (or ``(T + 1, P, 6)``); us: ``(T, P, 2)``;
        K: its feedback gains ``(T, P, 2, 6 P)`` or None.
        init: the field's warm start the local game was built from ``(T, N, 2)`` (None: zeros).

    Returns:
        ``xs (T + 1, N, 6)`` (the players' plans and the predicted cars' predictions),
        ``us (T, N, 2)`` (the players' plans; the other cars keep their rows of ``init``, their
        warm start should they be among the nearest again) and, with ``K``, the ego's gains
        on the field's state ``(T, 2, 6 N)`` (zero on the predicted cars: its plan does not
        react to them).
    """
    T = np.shape(us)[0]
    N = local.order.shape[0]
    init = np.zeros((T, N, np.shape(us)[-1])) if init is None else init
    out = to_field_batch(np.asarray(local.order)[None], np.asarray(xs)[None], np.asarray(us)[None],
                         None if K is None else np.asarray(K)[None], np.asarray(init, dtype=np.float64)[None],
                         np.asarray(local.others)[None])
    return out[0][0], out[1][0], None if K is None else out[2][0]


def to_field_batch(orders, xs, us, K, inits, predicted):
    """:func:`to_field` of R local solutions: ``orders (R, N)``, ``xs (R, T + 1, 6 P)``,
    ``us (R, T, P, 2)``, ``K (R, T, P, 2, 6 P)`` or None, the warm starts ``inits (R, T, N, 2)``
    and the trajectories of the cars not playing ``(R, T + 1, N - P, 6)`` (their predictions,
    in the orders' order, :attr:`LocalGame.others`). Returns ``xs (R, T + 1, N, 6)``,
    ``us (R, T, N, 2)`` and the egos' gains ``(R, T, 2, 6 N)`` or None. Written with gathers
    (the inverse of each order), so it runs in NumPy and, on JAX arrays, traced."""
    xp = _xp(orders, xs, us, inits)
    R, N = orders.shape
    T, P = us.shape[1], us.shape[2]
    inverse = xp.argsort(orders, axis=1)  # field car j is entry inverse[j] of the order

    def to_field_order(ordered, axis):  # (R, ..., N, ...) in the local order -> the field's order
        shape = (R,) + (1,) * (axis - 1) + (N,) + (1,) * (ordered.ndim - axis - 1)
        return xp.take_along_axis(ordered, inverse.reshape(shape), axis=axis)

    others = orders[:, P:]
    field_xs = to_field_order(xp.concatenate([xs.reshape(R, T + 1, P, STATE_DIM), predicted], axis=2), 2)
    kept = xp.take_along_axis(inits, others[:, None, :, None], axis=2)  # the other cars' warm starts
    field_us = to_field_order(xp.concatenate([us, kept], axis=2), 2)
    if K is None:
        return field_xs, field_us, None
    K_ego = K[:, :, 0].reshape(R, T, -1, P, STATE_DIM)  # (R, T, 2, P, 6)
    padded = xp.concatenate([K_ego, xp.zeros((R, T, K_ego.shape[2], N - P, STATE_DIM), K_ego.dtype)], axis=3)
    return field_xs, field_us, to_field_order(padded, 3).reshape(R, T, K_ego.shape[2], N * STATE_DIM)
