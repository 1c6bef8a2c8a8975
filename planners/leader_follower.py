"""Leader-follower local games: the two-player game a Stackelberg planner solves at a re-plan.

A Stackelberg (leader-follower) game has exactly two players
(:func:`planners.ilq.solve` with ``mode="stackelberg"``). The planners ``ilqgame-leader`` and
``ilqgame-follower`` (:class:`planners.agents.receding_horizon.StackelbergGameAgent`) play it
with their nearest rival, in a race of two cars or of a field: the *pair game* of car ``ego``
is the local game (:mod:`planners.rival_game`) of the ego and its nearest rival
(:func:`planners.rival_game.field_orders`), every further car up to ``obstacles`` of them
predicted at constant speed and lateral offset and avoided as a moving obstacle; in a race
of two cars there is none, and the pair game is the race's game.

Its players are ordered *leader first*: the local game's ``order (N,)`` is
``[leader, follower, other cars nearest the ego first]``, and it is solved with
``SolverOptions(mode="stackelberg", leader=0)``. Which of the two leads is the car's
``role`` (:data:`ROLES`):

* ``"leader"``: the ego leads; ``"follower"``: the rival leads;
* ``"auto"``: the car ahead in the race leads, judged at each re-plan from the joint state it
  starts from: the larger race distance ``s`` (cumulative, laps included), equal distances
  to the lower car index (so that both cars of a pair, each planning with ``role="auto"``,
  agree on who leads). This is the position-dependent responsibility of Cinar and Laine
  (arXiv:2402.09548): the car ahead announces its plan and the car behind answers it.

Ordering the players instead of choosing the solver's ``leader`` keeps the leader a
structural constant of one compiled solver: the order is an array of the problem's params,
so the choice of ``"auto"`` is a traced ``where`` inside a compiled race
(:class:`planners.agents.compiled_planner.CompiledPlanner`) and the re-plans of races with
different leaders share one batched solve. The functions here run in NumPy on the host and,
on JAX arrays, traced.

Shapes: field state ``x (N, 6)``; the pair game's flat state ``(12,)``, inputs ``(T, 2, 2)``,
gains ``K (T, 2, 2, 12)`` (players' order: leader, follower), and ``M = min(obstacles, N - 2)``
predicted cars ``(T + 1, M, 6)``.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from planners import rival_game
from planners.game_problem import GameProblem
from planners.ilqr import predict_constant_velocity
from racing_env.dynamics import S, STATE_DIM

__all__ = ["AUTO", "FOLLOWER", "LEADER", "PLAYERS", "ROLES", "check_role", "ego_leads", "ego_rows", "pair_game",
           "pair_games", "pair_orders", "to_field_batch"]

LEADER, FOLLOWER, AUTO = "leader", "follower", "auto"
ROLES = (LEADER, FOLLOWER, AUTO)
"""The roles a Stackelberg planner's car may take in its pair game (module docstring)."""
PLAYERS = 2
"""The players of a pair game: a leader and a follower."""


def check_role(role: Any) -> str:
    """``role`` if it is one of :data:`ROLES`; else a ``ValueError`` naming them."""
    if not isinstance(role, str) or role not in ROLES:
        raise ValueError(f"role must be one of {', '.join(ROLES)} (the car's part in its leader-follower game; "
                         f"auto: the car ahead in the race leads), got {role!r}")
    return role


def _xp(*arrays):
    return rival_game._xp(*arrays)


def ego_leads(role: str, x, egos, rivals):
    """Whether each ego leads its pair game, ``(R,)`` bool.

    Args:
        role: one of :data:`ROLES` (static).
        x: the fields' joint states ``(R, N, 6)``; ``s`` [m] is the race distance.
        egos: ``(R,)`` the planning cars; rivals: ``(R,)`` their rivals.

    Returns:
        True for ``"leader"``, False for ``"follower"``; for ``"auto"``, whether the ego is
        ahead of its rival in race distance, equal distances to the lower car index.
    """
    check_role(role)
    xp = _xp(x, egos, rivals)
    egos, rivals = xp.asarray(egos), xp.asarray(rivals)
    if role != AUTO:
        return xp.full(egos.shape, role == LEADER)
    rows = xp.arange(x.shape[0])
    s_ego, s_rival = x[rows, egos, S], x[rows, rivals, S]
    return (s_ego > s_rival) | ((s_ego == s_rival) & (egos < rivals))


def pair_orders(track, x, egos, role: str, racing=None):
    """The car orders ``(R, N)`` of R pair games (:class:`planners.rival_game.RivalParams`'s
    ``order``): the leader and the follower of each ego and its nearest rival, then the other
    cars nearest the ego first (:func:`planners.rival_game.field_orders`, whose rival is the
    nearest car still racing). ``x (R, N, 6)``, ``egos (R,)``, ``racing (R, N)`` bool or None.
    NumPy in, NumPy out; JAX arrays (also traced) in, JAX out."""
    xp = _xp(x, egos, racing)
    orders = rival_game.field_orders(track, x, egos, 1, racing)
    leads = ego_leads(role, x, orders[:, 0], orders[:, 1])
    pair = xp.where(leads[:, None], orders[:, :PLAYERS], orders[:, PLAYERS - 1::-1])
    return xp.concatenate([pair, orders[:, PLAYERS:]], axis=1)


def ego_rows(orders, egos):
    """The ego's player index in each pair game, ``(R,)`` int: 0 where it leads, 1 where it
    follows. ``orders (R, N)`` of :func:`pair_orders`, ``egos (R,)``."""
    xp = _xp(orders, egos)
    return xp.where(orders[:, 0] == xp.asarray(egos), 0, 1)


def pair_game(game, x0: np.ndarray, ego: int, role: str, init: np.ndarray | None = None,
              predicted: np.ndarray | None = None, obstacles: int | None = None) -> rival_game.LocalGame:
    """Car ``ego``'s pair game in the field ``x0 (N, 6)`` (module docstring), as a
    :class:`planners.rival_game.LocalGame` (its ``order`` leader first).

    Args:
        game: the field's :class:`racing_env.RaceGame` (``N >= 2`` cars).
        x0: the field's state ``(N, 6)``.
        ego: the planning car; role: one of :data:`ROLES`.
        init: the field's warm start ``(T, N, 2)`` [m/s^3] (None: zeros).
        predicted: the field's predicted trajectories ``(T + 1, N, 6)`` (the players' rows are
            not used); None: constant speed and lateral offset from ``x0``.
        obstacles: the nearest other cars predicted as moving obstacles (None: all).
    """
    x0 = np.asarray(x0, dtype=np.float64)
    N, T = game.num_players, game.horizon
    if x0.shape != (N, STATE_DIM):
        raise ValueError(f"x0 must have shape (N, 6) = ({N}, {STATE_DIM}), got {x0.shape}")
    if predicted is None:
        predicted = np.asarray(predict_constant_velocity(game, x0))
    elif np.shape(predicted) != (T + 1, N, STATE_DIM):
        raise ValueError(f"predicted must have shape (T+1, N, 6) = {(T + 1, N, STATE_DIM)}, got {np.shape(predicted)}")
    us = np.zeros((T, N, game.input_dim)) if init is None else np.asarray(init, dtype=np.float64)
    racing = None if game.racing is None else np.asarray(game.racing)[None]
    problem, x0s, inits, orders, others = pair_games(
        rival_game._with_racing_array(game), x0[None], np.array([ego]), role, us[None], np.asarray(predicted)[None],
        obstacles, racing)
    params = problem.params
    problem = problem.replace(params=params._replace(order=params.order[0], predicted=params.predicted[0]))
    return rival_game.LocalGame(problem=problem, x0=x0s[0], init=inits[0], order=orders[0], others=others[0])


def pair_games(game, x0s: np.ndarray, egos: np.ndarray, role: str, inits: np.ndarray, predicted: np.ndarray,
               obstacles: int | None = None, racing=None) -> tuple[GameProblem, Any, Any, Any, Any]:
    """R pair games at once, for :func:`planners.ilq_batch.solve_batch` with the
    ``params_axes`` of :func:`planners.rival_game.batch_axes` (as
    :func:`planners.rival_game.local_games`).

    Args:
        game: the field's game (for a batch: per-race ``weights`` and ``racing``, leaves
            ``(R, N)``; the track and the cars' parameters shared).
        x0s: ``(R, N, 6)``; egos: ``(R,)``; role: one of :data:`ROLES`; inits: ``(R, T, N, 2)``;
        predicted: ``(R, T + 1, N, 6)`` (the players' rows are not used).
        obstacles: the nearest other cars each game predicts as moving obstacles (None: all).
        racing: ``(R, N)`` bool, the flags the rivals are chosen by; default ``game.racing``.

    Returns:
        ``(problem, x0 (R, 12), init (R, T, 2, 2), orders (R, N), others (R, T + 1, N - 2, 6))``,
        the players leader first; ``others`` the predictions of the cars not playing, in the
        orders' order (for :func:`to_field_batch`). NumPy arrays in, NumPy out; JAX arrays
        (also traced) in, JAX out.
    """
    xp = _xp(x0s, egos, inits, predicted)
    R, N = x0s.shape[:2]
    M = rival_game.predicted_count(N, PLAYERS, rival_game.check_obstacles(obstacles))
    racing = game.racing if racing is None else racing
    orders = pair_orders(game.track, x0s, egos, role, None if racing is None else xp.asarray(racing))
    rows = xp.arange(R)[:, None]
    players = orders[:, :PLAYERS]
    others = xp.transpose(predicted[rows, :, orders[:, PLAYERS:]], (0, 2, 1, 3))
    params = rival_game.RivalParams(game=game, order=orders, predicted=others[:, :, :M])
    x0 = x0s[rows, players].reshape(R, -1)
    init = xp.transpose(inits[rows, :, players], (0, 2, 1, 3))
    problem = rival_game.local_problem(PLAYERS, STATE_DIM, game.input_dim, game.horizon, params)
    return problem, x0, init, orders, others


def to_field_batch(orders, egos, xs, us, K, inits, others):
    """R pair-game solutions in the field's shapes: :func:`planners.rival_game.to_field_batch`
    with each ego's gains taken from its own player row (:func:`ego_rows`).

    Args:
        orders: ``(R, N)`` of :func:`pair_orders`; egos: ``(R,)``.
        xs: ``(R, T + 1, 12)``; us: ``(R, T, 2, 2)``; K: ``(R, T, 2, 2, 12)`` or None.
        inits: the fields' warm starts ``(R, T, N, 2)``; others: ``(R, T + 1, N - 2, 6)``.

    Returns:
        ``xs (R, T + 1, N, 6)``, ``us (R, T, N, 2)`` and the egos' gains on the field's state
        ``(R, T, 2, 6 N)`` (zero on the cars not playing) or None.
    """
    xp = _xp(orders, xs, us, inits)
    if K is not None:
        rows = ego_rows(orders, egos)
        K = K[xp.arange(K.shape[0]), :, rows][:, :, None]  # (R, T, 1, 2, 12): the ego's row first
    return rival_game.to_field_batch(orders, xs, us, K, inits, others)

