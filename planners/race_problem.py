"""The racing game's Gauss-Newton form for the iterative LQ solvers.

:func:`problem_from_race_game` turns a :class:`racing_env.RaceGame` into a
:class:`planners.game_problem.GameProblem`: the flat joint state ``x (6 N,)``, the inputs
``(N, 2)``, the game itself as the problem's ``params``, and the hooks that make the solver
fast and its local games convex:

* :func:`race_stage_gauss_newton` / :func:`race_terminal_gauss_newton`: every player's
  costs as ``sum_k rho_k(r_k)`` (the residuals of :mod:`racing_env.costs`) with their
  outer slopes and PSD curvature weights;
* :func:`race_stage_curvature`: the curvature of each car's progress in its own heading,
  which the linearised dynamics drop;
* :func:`race_dynamics_jacobians`: per-car Jacobians of the RK4 step (cars without drag do
  not interact through the dynamics); for a game with drag, the Jacobians of the joint step,
  whose off-diagonal blocks carry the slipstream (a car's speed depends on the cars ahead).

Importing this module registers :class:`racing_env.RaceGame` with the solvers
(:func:`planners.game_problem.register_game_type`): :func:`planners.ilq.solve`,
:func:`planners.ilq_batch.solve_batch` and :func:`planners.nash.nash_residual` accept a
game directly, with states in its ``(N, 6)`` shape.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from planners.game_problem import GameProblem, GameType, is_concrete, register_game_type
from racing_env.costs import collision_costs, terminal_weights
from racing_env.dynamics import CHI, MIN_FRENET_SCALE, N_LAT, S, STATE_DIM, V, rk4_step
from racing_env.game import RaceGame

__all__ = [
    "problem_from_race_game",
    "race_dynamics",
    "race_dynamics_jacobians",
    "race_stage_cost",
    "race_stage_curvature",
    "race_stage_gauss_newton",
    "race_terminal_cost",
    "race_terminal_gauss_newton",
    "validate_race_game",
]


def race_dynamics(game: RaceGame, t: jax.Array, x: jax.Array, u: jax.Array) -> jax.Array:
    """One step of every car: flat joint state ``x (6 N,)``, inputs ``u (N, 2)`` [m/s^3] ->
    ``(6 N,)`` (the dynamics do not depend on the stage ``t``)."""
    del t
    return game.step(x.reshape(u.shape[0], -1), u).reshape(-1)


def race_stage_cost(game: RaceGame, t: jax.Array, i: jax.Array, x: jax.Array, u_i: jax.Array) -> jax.Array:
    """Player ``i``'s stage cost at the flat joint state ``x (6 N,)`` with its input ``u_i (2,)``."""
    del t
    return game.stage_cost(i, x.reshape(game.num_players, -1), u_i)


def race_terminal_cost(game: RaceGame, i: jax.Array, x: jax.Array) -> jax.Array:
    """Player ``i``'s terminal cost at the flat joint state ``x (6 N,)``."""
    return game.terminal_cost(i, x.reshape(game.num_players, -1))


def race_stage_gauss_newton(game, t, i, x, u_i):
    """Player i's racing stage cost as ``(r, g, h)``: the residuals ``r`` of
    :meth:`racing_env.RaceGame.stage_residuals`, the slopes ``g = rho'(r)`` of their outer
    functions and PSD curvature weights ``h``.

    * collision with car j: ``r = a_ij = (ds_ij / l_ij)^2 + (dn_ij / w_ij)^2``,
      ``rho(a) = c_c exp(2 (1 - a))``. The term's exact Hessian is ``J' H_y J`` in the
      coordinates ``y = (ds / l, dn / w)`` (linear in x), with
      ``H_y = c e (16 y y' - 4 I)``, ``e = exp(2 (1 - a))``: indefinite. Its PSD part is
      ``c e max(16 - 4 / a, 0) y y'``, i.e. the weight ``h = c e max(4 - 1 / a, 0)`` on
      ``grad a grad a'`` (``grad a = 2 J' y``). Zero for ``a < 1/4`` (deep overlap).
    * track boundaries, ax limit, gg limit, turn limit, reversing: ``r = z``, ``rho(z) = c max(z, 0)^2``;
      ``h = 2 c 1{z > 0}``, the exact outer curvature (Gauss-Newton: the inner curvature of
      ``z`` is dropped, e.g. of ``ax_max(V)`` and of the norm ``|(ax, ay)|``).
    * jerk: ``r = u_i``, ``rho = r_j u^2``, exact.
    """
    del t
    res = game.stage_residuals(i, x.reshape(game.num_players, -1), u_i)
    a, z, c, rj = res.proximity, res.limits, res.limit_weights, res.jerk_weights
    ce = collision_costs(res)  # c_c exp(2 (1 - a)), zero for i itself and ghosts
    g_col = -2.0 * ce
    h_col = ce * jnp.maximum(4.0 * a - 1.0, 0.0) / jnp.maximum(a, 0.25)
    r = jnp.concatenate([a, z, u_i])
    g = jnp.concatenate([g_col, 2.0 * c * jnp.maximum(z, 0.0), 2.0 * rj * u_i])
    h = jnp.concatenate([h_col, 2.0 * c * (z > 0), 2.0 * rj])
    return r, g, h


def race_stage_curvature(game, t, i, x):
    """The curvature of car i's progress over stage t in its own heading ``chi_i``, ``(n,)``.

    Player i's terminal cost rewards its arc length ``-s_T^i`` linearly, and ``s_T^i`` is
    the sum of the stages' progress, which is concave in the heading
    (``ds/dt = V cos(chi) / (1 - n kappa)``). That curvature reaches the player's total
    cost only through the dynamics' second derivatives, which the local LQ games drop; on a
    straight the jerk weight is then the only curvature in the lateral states, and at a
    small racing jerk weight the iterations cycle laterally instead of converging
    (docs/solvers.md, "Curvature of the local games"). The entry at ``chi_i`` is
    ``-d^2 (dt ds/dt) / d chi_i^2 = dt V cos(chi) / (1 - n kappa)``, the Euler step's
    (on a straight at constant speed and heading exactly the RK4 step's); every other
    entry is 0. The rivals' progress, which player i's terminal cost weights with ``+c_g``,
    would add negative curvature in their headings for ``c_g > 0``; like every concave part
    it is left out (for a negative ``c_g``, where it would be convex, too: only a player's
    own progress is added). Written as an element-wise select, not a scatter, which is
    slower inside the solver's loop.
    """
    del t

    s, v, n, chi = x.reshape(game.num_players, -1)[i, jnp.array([S, V, N_LAT, CHI])]
    scale = jnp.maximum(1.0 - n * game.track.kappa_at(s), MIN_FRENET_SCALE)
    h = game.dt * v * jnp.cos(chi) / scale
    return jnp.where(jnp.arange(x.shape[0]) == STATE_DIM * i + CHI, h, 0.0)


def race_terminal_gauss_newton(game, i, x):
    """``-s_i + c_g sum_{j != i, j racing} s_j``: linear in the cars' arc lengths ``r = s``
    (:func:`racing_env.costs.terminal_weights`), zero curvature."""
    N = game.num_players
    s = x.reshape(N, -1)[:, S]
    g = terminal_weights(game.weights, game.racing, N, x.dtype)[i]
    return s, g, jnp.zeros_like(s)


def race_dynamics_jacobians(game, t, x, u):
    """Jacobians ``A (6 N, 6 N)`` and ``B (6 N, N, m)`` of the joint RK4 step at the flat joint
    state ``x (6 N,)`` and inputs ``u (N, m)``.

    Without drag the cars do not interact through the dynamics: per-car Jacobians, ``A`` block
    diagonal, ``B^j`` non-zero in car j's rows only. With drag (``game.drag``) the slipstream
    couples them: the Jacobians of the joint step, whose off-diagonal blocks are car i's
    dependence on the cars whose wakes reach it (zero where none does).
    """
    del t

    N, m = u.shape
    if game.drag:
        A, B = jax.jacfwd(lambda xx, uu: race_dynamics(game, None, xx, uu), argnums=(0, 1))(x, u)
        return A, B
    X = x.reshape(N, -1)
    step = lambda xi, ui: rk4_step(xi, ui, game.dt, game.track.kappa_at)
    Ai, Bi = jax.vmap(jax.jacfwd(step, argnums=(0, 1)))(X, u)  # (N, 6, 6), (N, 6, m)
    d = Ai.shape[-1]
    # Car j's rows padded with zeros left and right of its own block: zero padding fuses
    # into the Jacobian kernels, where a mask product over (N, 6, N, 6) would not.
    pad = lambda M, j, axis: jnp.pad(M, [(d * j, d * (N - 1 - j)) if a == axis else (0, 0) for a in range(M.ndim)])
    A = jnp.concatenate([pad(Ai[j], j, 1) for j in range(N)], axis=0)  # (6 N, 6 N)
    B = jnp.stack([pad(Bi[j], j, 0) for j in range(N)], axis=1)  # (6 N, N, m)
    return A, B


def problem_from_race_game(game) -> GameProblem:
    """Adapt a :class:`racing_env.RaceGame`: flat joint state ``x (6 N,)``, inputs ``(N, 2)``.

    The game is the problem's ``params``, so solving games that differ only in weights,
    vehicles or track arrays (same shapes) re-uses the compiled solver. The problem has
    the Gauss-Newton hooks of the racing costs and per-car dynamics Jacobians.
    """
    return GameProblem(
        dynamics=race_dynamics,
        stage_cost=race_stage_cost,
        terminal_cost=race_terminal_cost,
        num_players=game.num_players,
        state_dim=game.num_players * game.state_dim,
        input_dim=game.input_dim,
        horizon=game.horizon,
        params=game,
        stage_gauss_newton=race_stage_gauss_newton,
        terminal_gauss_newton=race_terminal_gauss_newton,
        dynamics_jacobians=race_dynamics_jacobians,
        stage_curvature=race_stage_curvature,
    )


def validate_race_game(game, control_regularization: float = 0.0) -> None:
    """Refuse a game whose input weights ``R^{ii} = 2 diag(r_jx, r_jy) + control_regularization``
    are not positive definite (a traced game is not checked).

    Raises:
        ValueError: naming the player.
    """
    if not is_concrete(game.weights):
        return
    weights = game.weights  # NumPy only: no device dispatch on every solve
    jerk = np.stack(np.broadcast_arrays(np.asarray(weights.r_jx, float), np.asarray(weights.r_jy, float)), -1)
    w = 2.0 * np.atleast_2d(jerk) + control_regularization
    for i in range(w.shape[0]):
        if not np.all(w[i] > 0):
            raise ValueError(
                f"player {i}'s input weight R^ii = 2 diag(r_jx, r_jy) = diag{tuple(w[i])} "
                "is not positive definite: the LQ game (and the Nash equilibrium) is not "
                "defined; use jerk weights r_jx, r_jy > 0"
            )


def _game_costs_of_inputs(game, x0, us):
    """Every player's total cost of ``us (T, N, 2)`` from ``x0 (N, 6)``, through
    ``RaceGame.rollout`` and ``RaceGame.costs``."""
    return game.costs(game.rollout(x0, us), us)


register_game_type(
    RaceGame,
    GameType(
        to_problem=problem_from_race_game,
        state_shape=lambda game: (game.num_players, game.state_dim),
        validate=validate_race_game,
        costs_of_inputs=_game_costs_of_inputs,
    ),
)
