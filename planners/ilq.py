"""Iterative linear-quadratic (iLQ) game solver: feedback and open-loop iLQGames, and iLQR.

One solver serves three planners of the paper (``reference/ilqgame-racing-paper.tex``,
Algorithm 1):

* feedback iLQGame (``mode="feedback"``): each iteration solves the feedback Nash
  equilibrium of the local LQ game (:func:`planners.lq_game.solve_feedback`);
* open-loop iLQGame (``mode="open_loop"``): the open-loop Nash equilibrium of the local LQ
  game (:func:`planners.lq_game.solve_open_loop_own`), otherwise the same code path;
* iLQR: the same solver with ``N = 1`` (see :mod:`planners.ilqr`, which predicts the
  opponents and hands a single-player, time-varying problem to :func:`solve`).

The game protocol
-----------------
A :class:`GameProblem` is a pytree whose only data is ``params`` (any pytree: a
``RaceGame``, weights, predicted trajectories, ...). Its functions are static and receive
``params`` as their first argument, so new weights or new initial states re-use the
compiled solver::

    dynamics(params, t, x, u) -> x_next        x (n,), u (N, m), t int stage index
    stage_cost(params, t, i, x, u_i) -> scalar  player i's g_t^i; depends on its own input only
    terminal_cost(params, i, x) -> scalar       player i's g_T^i

with static ``num_players N``, ``state_dim n``, ``input_dim m`` and ``horizon T``.
:func:`problem_from_race_game` adapts a :class:`racing_env.RaceGame` (joint state
``(N, 6)`` flattened to ``n = 6 N``). :func:`solve` and :func:`nash_residual` also accept a
``RaceGame`` directly; states then come and go in the game's ``(N, 6)`` shape.

One iteration
-------------
Around the nominal trajectory ``(x_hat, u_hat)``:

1. linearise the dynamics with ``jax.jacfwd`` (vmapped over the horizon), or with the
   problem's ``dynamics_jacobians`` hook (a RaceGame differentiates each car's RK4 step
   alone: the cars do not interact through the dynamics):
   ``dx_{t+1} = A_t dx_t + sum_j B_t^j du_t^j``;
2. quadratise each player's cost: ``Q_t^i, q_t^i`` (state) and ``R_t^{ii}, r_t^{ii}`` (own
   input). Mixed state-input terms and ``R^{ij}, r^{ij}`` for ``i != j`` are zero (the
   paper's cost structure; the mixed terms are dropped if a custom cost has them). The
   gradients ``q, r`` are always exact. The curvature, ``convexify``:

   * ``"gauss_newton"`` (the default where the problem has the hooks, as every RaceGame
     does): the problem writes player i's stage cost as ``sum_k rho_k(r_k(x, u_i))`` and
     returns ``r_k``, ``rho_k'`` and a curvature weight ``h_k >= 0``; then
     ``[Q, .; ., R] = J' diag(h) J`` and ``[q; r] = J' rho'`` with ``J = d r / d[x, u_i]``,
     one forward-mode pass, PSD by construction. For the racing costs: the squared
     hinges ``c max(z, 0)^2`` (track, ax and gg limits) get their exact outer curvature
     ``2 c 1{z > 0}`` (the inner curvature of ``z`` is dropped), the jerk term is exact,
     the terminal cost is linear, and each collision term gets the PSD part of its exact
     Hessian in its natural coordinates ``(ds / l, dn / w)`` (see
     :func:`_race_stage_gauss_newton`). No eigendecomposition is needed;
   * ``"eig"`` (the default otherwise): exact Hessians (``jax.hessian``, vmapped over
     stages and players), every ``Q_t^i`` projected onto the PSD cone (eigenvalues
     clipped at zero); ``"diag"`` makes it diagonally dominant instead; ``"none"`` keeps
     the exact Hessian.

   With ``dynamics_curvature`` (the default) the problem's ``stage_curvature`` is added to
   the diagonal of each ``Q_t^i``: curvature of the true problem that the linearised
   dynamics drop. For a RaceGame it is the curvature of each car's progress in its own
   heading (:func:`_race_stage_curvature`), without which the racing jerk weight leaves
   the lateral states of the local games almost flat on a straight;
3. regularisation: ``Q_t^i += state_regularization * I`` and
   ``R_t^{ii} += lambda_u * I``, ``lambda_u = control_regularization``, or adapted per
   iteration with ``adaptive_regularization`` (open loop and one player; see
   :class:`SolverOptions` and :func:`check_adaptive_regularization`). In feedback games
   ``feedforward_regularization`` puts ``lambda_u`` on the feed-forward terms only, which
   leaves the fixed points where they are, also with the adaptive rule. Why convexify: the collision term makes the
   exact ``Q^i`` indefinite; with it, the local LQ "equilibria" are often saddle points of
   a player's local problem and the iteration wanders (observed on the paper's scenario).
   A PSD ``Q^i`` keeps every player's local problem convex, so each LQ solution is a
   genuine equilibrium of the local game. The curvature does not move open-loop fixed
   points (they depend on gradients only); it does change feedback ones (``K`` depends
   on ``Q``), which is the usual price of a regularised feedback iLQGame: the Gauss-Newton
   and the eig-projected feedback solutions of the paper's scene differ by about 1 cm;
4. solve the LQ game in deviation coordinates. Feedback: ``du = -K dx - k``, by
   :func:`~planners.lq_game.solve_feedback_own` (the own-input structure and PSD ``Q``
   make its block elimination safe; with ``convexify="none"`` the general pivoting
   :func:`~planners.lq_game.solve_feedback`). Open loop: the
   LQ game starts at ``dx_0 = x_0 - x_hat_0 = 0``, so
   :func:`~planners.lq_game.solve_open_loop_own` is called with a ZERO initial deviation
   and its inputs ``du_t = -k_t`` are the whole
   update; ``K = 0``. With ``dx_0 = 0`` the open-loop equilibrium is linear in the
   gradients ``(q, r)``, so ``eta * k`` is exactly the equilibrium of the local game with
   its linear terms scaled by ``eta``: a consistent short step towards it;
5. forward pass on the nonlinear dynamics from ``x_0``::

       u_t = u_hat_t - K_t (x_t - x_hat_t) - eta k_t,   x_{t+1} = f_t(x_t, u_t).

Step-size control (``step_control="trust_region"``, the default)
---------------------------------------------------------------
1. A trust region on the state trajectory, as in the ilqgames reference implementation of
   Fridovich-Keil et al. (ICRA 2020, https://github.com/HJReachability/ilqgames:
   ``SolverParams::trust_region_size``, "maximum absolute difference between states ... to
   satisfy trust region", with the feed-forward terms ``alpha`` backed off geometrically by
   ``geometric_alpha_scaling`` in ``ILQSolver::ModifyLQStrategies``, and convergence on the
   max elementwise state difference; iLQGames.jl likewise has ``max_elwise_diff_step``).
   Here: multiply ``eta`` by ``step_decay`` until ``max_t |x_new_t - x_hat_t|_inf <=
   trust_radius`` and the rollout is finite; give up after ``max_backtracks`` reductions
   (status ``LINE_SEARCH_FAILED``). As ``eta -> 0`` the new trajectory tends to the nominal
   one, so the search terminates for any finite LQ solution.
2. Overshoot damping (``oscillation_damping=True``): the trust region alone bounds each
   step but does not make the iteration contract; on the paper's scenario both fixed
   ``eta = 1`` and the plain trust region run into limit cycles (e.g. period 7). A step
   whose state change points against a decaying sum of the previous unit steps (memory
   ``damping_memory``) reveals an overshoot: the next iteration starts at
   ``eta * step_decay``; otherwise it starts again at ``initial_step``.
   Near a stable fixed point this settles on a step that contracts (full steps where the
   iteration allows them).
Why no Armijo backtracking on costs: a game has no single merit function that every
player's Nash update decreases (a player's cost may rightly rise); both checks above are
player-neutral, mode-neutral and cost one rollout per trial.

``step_control="residual"`` (open loop only) backtracks on the one merit an open-loop game
does have: the squared first-order Nash residual ``sum_i |dJ^i/du^i|^2`` (zero exactly at
the open-loop fixed points; it has no feedback counterpart). ``eta`` starts at
``initial_step`` every iteration and is multiplied by ``step_decay`` until the step stays
inside the trust region and decreases the residual by the sufficient-decrease factor
``1 - 2e-4 eta``. The Gauss-Newton LQ game's step need not be a descent direction of the
residual (its model drops the dynamics' curvature and the limits' curvature jumps); when
no trial decreases it, the first trial inside the trust region is taken, the default
rule's step. Each trial costs one rollout and N reverse passes for the gradients.
``step_control="none"`` applies a fixed ``eta = initial_step`` (the paper's plain update),
for comparisons.

Convergence: the state change of a full step, ``max_t |x_new_t - x_hat_t|_inf`` scaled by
``initial_step / eta`` (exact for an accepted full step, first-order otherwise), is at most
``tolerance``, and the step was not shortened by the trust region (a step forced down by
the trust region, e.g. against a region where the dynamics are undefined, says nothing
about the full step). At a fixed point ``k = 0``; for ``mode="open_loop"`` this is exactly the
first-order open-loop Nash condition of the nonlinear game (regularisation does not move
it), see :func:`nash_residual`. For ``mode="feedback"`` it is the feedback condition of the
sequence of (regularised) local LQ games. The soft constraints ``max(z, 0)^2`` of the racing
costs have discontinuous Hessians, so feedback iterations can chatter where a trajectory
sits on a constraint boundary; such runs end with ``MAX_ITERATIONS``.

Failures are reported, never returned as NaN: a non-finite LQ solution stops the solve
with status ``NON_FINITE`` and the last finite iterate; a failed step-size search stops with
``LINE_SEARCH_FAILED``; the iteration cap gives ``MAX_ITERATIONS``. ``converged`` is True
only with status ``CONVERGED``.

Everything inside :func:`solve` is one jitted function (``lax.while_loop`` over
iterations, ``lax.scan`` only for the recursions and rollouts, ``vmap`` over the horizon for
derivatives), compiled once per shapes, problem functions and :class:`SolverOptions`.
It can be vmapped over initial states (and over ``params``); :func:`solve_batch` solves a
batch that way or, on CPU, one member after another (``batching``), optionally regrouping
the members still running between blocks of iterations (``regroup_every``). Internally a
solve is :func:`_initial_carry`, :func:`_iterate` in a ``while_loop``, and :func:`_result`.
"""

from __future__ import annotations

import dataclasses
import functools
from typing import Any, Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from planners import lq_game
from planners.batching import one_at_a_time, with_batched_form

Array = jax.Array

__all__ = [
    "CONVERGED",
    "GameProblem",
    "LINE_SEARCH_FAILED",
    "MAX_ITERATIONS",
    "NON_FINITE",
    "RUNNING",
    "SolverOptions",
    "SolverResult",
    "check_adaptive_regularization",
    "nash_residual",
    "problem_from_race_game",
    "rollout",
    "solve",
    "solve_batch",
    "status_message",
    "total_costs",
    "validate_problem",
]

# Status codes of a solve (SolverResult.status).
RUNNING = -1  # internal only: never returned
CONVERGED = 0
MAX_ITERATIONS = 1
NON_FINITE = 2
LINE_SEARCH_FAILED = 3

_STATUS_MESSAGES = {
    CONVERGED: "converged",
    MAX_ITERATIONS: "iteration cap reached before convergence",
    NON_FINITE: "non-finite LQ solution or trajectory; stopped at the last finite iterate",
    LINE_SEARCH_FAILED: "step-size control found no step inside the trust region",
}


def status_message(status) -> str:
    """Human-readable meaning of a ``SolverResult.status`` code."""
    return _STATUS_MESSAGES.get(int(status), f"unknown status {int(status)}")


# --------------------------------------------------------------------------------------
# The game protocol.
# --------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class GameProblem:
    """An N-player discrete-time game for :func:`solve` (a pytree: ``params`` is its data).

    Attributes:
        dynamics: ``(params, t, x (n,), u (N, m)) -> (n,)``.
        stage_cost: ``(params, t, i, x (n,), u_i (m,)) -> ()``, player ``i``'s stage cost.
        terminal_cost: ``(params, i, x (n,)) -> ()``.
        num_players, state_dim, input_dim, horizon: ``N, n, m, T`` (static ints).
        params: pytree of arrays passed to the functions (traced inside the solver).
        stage_gauss_newton: optional ``(params, t, i, x, u_i) -> (r (k,), g (k,), h (k,))``:
            player i's stage cost written as ``sum_k rho_k(r_k(x, u_i))`` with scalar outer
            functions ``rho_k``; ``g_k = rho_k'(r_k)`` and a curvature weight ``h_k >= 0``
            (``rho_k''(r_k)`` where that is non-negative). Enables the Gauss-Newton
            quadratisation (module docstring); ``g`` and ``h`` are not differentiated.
        terminal_gauss_newton: optional ``(params, i, x) -> (r, g, h)``, the same for
            ``terminal_cost`` (both hooks are needed for Gauss-Newton).
        stage_curvature: optional ``(params, t, i, x) -> (n,)``: a diagonal curvature
            (``>= 0``; negative entries are clipped) that player i's local game at stage t
            should have in the state but that quadratising its costs misses, because iLQ
            drops the dynamics' second derivatives (e.g. the curvature of a linear terminal
            reward through the dynamics; RaceGame: :func:`_race_stage_curvature`). Added to
            the diagonal of ``Q_t^i`` (``SolverOptions.dynamics_curvature``); the gradients,
            and so the open-loop fixed points, stay those of the costs.
        dynamics_jacobians: optional ``(params, t, x, u) -> (A (n, n), B (n, N, m))``, the
            Jacobians of ``dynamics`` (e.g. exploiting structure); default ``jax.jacfwd``.

    The functions are compared by identity for jit caching: define them once (module
    level), not as fresh lambdas per call, to avoid recompiling.
    """

    dynamics: Callable[..., Array]
    stage_cost: Callable[..., Array]
    terminal_cost: Callable[..., Array]
    num_players: int
    state_dim: int
    input_dim: int
    horizon: int
    params: Any = None
    stage_gauss_newton: Callable[..., tuple[Array, Array, Array]] | None = None
    terminal_gauss_newton: Callable[..., tuple[Array, Array, Array]] | None = None
    dynamics_jacobians: Callable[..., tuple[Array, Array]] | None = None
    stage_curvature: Callable[..., Array] | None = None

    @property
    def has_gauss_newton(self) -> bool:
        return self.stage_gauss_newton is not None and self.terminal_gauss_newton is not None

    def replace(self, **changes) -> "GameProblem":
        return dataclasses.replace(self, **changes)


jax.tree_util.register_dataclass(
    GameProblem,
    data_fields=["params"],
    meta_fields=[
        "dynamics",
        "stage_cost",
        "terminal_cost",
        "num_players",
        "state_dim",
        "input_dim",
        "horizon",
        "stage_gauss_newton",
        "terminal_gauss_newton",
        "dynamics_jacobians",
        "stage_curvature",
    ],
)


def _race_dynamics(game, t, x, u):
    del t
    return game.step(x.reshape(u.shape[0], -1), u).reshape(-1)


def _race_stage_cost(game, t, i, x, u_i):
    del t
    return game.stage_cost(i, x.reshape(game.num_players, -1), u_i)


def _race_terminal_cost(game, i, x):
    return game.terminal_cost(i, x.reshape(game.num_players, -1))


def _race_stage_gauss_newton(game, t, i, x, u_i):
    """Player i's racing stage cost as ``sum_k rho_k(r_k)`` (see ``racing_env.costs``).

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
    from racing_env.costs import _NORM_EPS, racing_pairs
    from racing_env.dynamics import AX, AY, N_LAT, S, V

    N = game.num_players
    X = x.reshape(N, -1)
    vehicles, weights, track = game.vehicles, game.weights, game.track
    s, v, n = X[:, S], X[:, V], X[:, N_LAT]
    ds = track.wrap_ds(s - s[i])
    dn = n - n[i]
    lengths, widths = jnp.asarray(vehicles.length), jnp.asarray(vehicles.width)
    length = 0.5 * (lengths[i] + lengths)
    width = 0.5 * (widths[i] + widths)
    a = (ds / length) ** 2 + (dn / width) ** 2  # (N,), a_ii = 0
    others = racing_pairs(game.racing, N, x.dtype)[i]  # zero for i itself and cars out of the race
    ce = jnp.asarray(weights.c_collision)[i] * jnp.exp(2.0 * (1.0 - a)) * others
    g_col = -2.0 * ce
    h_col = ce * jnp.maximum(4.0 * a - 1.0, 0.0) / jnp.maximum(a, 0.25)

    half_width = 0.5 * widths[i]
    ax_i, ay_i = X[i, AX], X[i, AY]
    z = jnp.stack(
        [
            n[i] - (track.width_left_at(s[i]) - half_width),
            -n[i] - (track.width_right_at(s[i]) - half_width),
            ax_i - vehicles.ax_max(v)[i],
            jnp.sqrt(ax_i**2 + ay_i**2 + _NORM_EPS) - vehicles.rho(v)[i],
            jnp.sqrt(ay_i**2 + _NORM_EPS) - vehicles.ay_turn_max(v)[i],
            -v[i],
        ]
    )
    c_track, c_ax, c_acc, c_reverse = (
        jnp.asarray(w)[i] for w in (weights.c_track, weights.c_ax, weights.c_acc, weights.c_reverse)
    )
    c = jnp.stack([c_track, c_track, c_ax, c_acc, c_acc, c_reverse])
    rj = jnp.asarray(weights.jerk_weights)[i]
    r = jnp.concatenate([a, z, u_i])
    g = jnp.concatenate([g_col, 2.0 * c * jnp.maximum(z, 0.0), 2.0 * rj * u_i])
    h = jnp.concatenate([h_col, 2.0 * c * (z > 0), 2.0 * rj])
    return r, g, h


def _race_stage_curvature(game, t, i, x):
    """The curvature of car i's progress over stage t in its own heading ``chi_i``, ``(n,)``.

    Player i's terminal cost rewards its arc length ``-s_T^i`` linearly, and ``s_T^i`` is
    the sum of the stages' progress, which is concave in the heading
    (``ds/dt = V cos(chi) / (1 - n kappa)``). That curvature reaches the player's total
    cost only through the dynamics' second derivatives, which the local LQ games drop; on a
    straight the jerk weight is then the only curvature in the lateral states, and at the
    racing weight (0.01) the iterations cycle laterally instead of converging (README,
    "Progress curvature"). The entry at ``chi_i`` is
    ``-d^2 (dt ds/dt) / d chi_i^2 = dt V cos(chi) / (1 - n kappa)``, the Euler step's
    (on a straight at constant speed and heading exactly the RK4 step's); every other
    entry is 0. The rivals' progress, which player i's terminal cost weights with ``+c_g``,
    would add negative curvature in their headings for ``c_g > 0``; like every concave part
    it is left out (for a negative ``c_g``, where it would be convex, too: only a player's
    own progress is added).
    An element-wise select, not a scatter: ``.at[].set`` here cost 0.03 ms per iteration.
    """
    del t
    from racing_env.dynamics import CHI, MIN_FRENET_SCALE, N_LAT, S, STATE_DIM, V

    s, v, n, chi = x.reshape(game.num_players, -1)[i, jnp.array([S, V, N_LAT, CHI])]
    scale = jnp.maximum(1.0 - n * game.track.kappa_at(s), MIN_FRENET_SCALE)
    h = game.dt * v * jnp.cos(chi) / scale
    return jnp.where(jnp.arange(x.shape[0]) == STATE_DIM * i + CHI, h, 0.0)


def _race_terminal_gauss_newton(game, i, x):
    """``-s_i + c_g sum_{j != i, j racing} s_j``: linear in the cars' arc lengths (zero curvature)."""
    from racing_env.costs import racing_flags
    from racing_env.dynamics import S

    N = game.num_players
    s = x.reshape(N, -1)[:, S]
    own = jnp.arange(N) == i
    rival = jnp.asarray(game.weights.c_gap)[i] * racing_flags(game.racing, N, x.dtype)
    g = jnp.where(own, -1.0, rival).astype(x.dtype)
    return s, g, jnp.zeros_like(s)


def _race_dynamics_jacobians(game, t, x, u):
    """Per-car Jacobians of the RK4 step (the cars do not interact through the dynamics):
    ``A`` is block diagonal, ``B^j`` is non-zero in car j's rows only."""
    del t
    from racing_env.dynamics import rk4_step

    N, m = u.shape
    X = x.reshape(N, -1)
    step = lambda xi, ui: rk4_step(xi, ui, game.dt, game.track.kappa_at)
    Ai, Bi = jax.vmap(jax.jacfwd(step, argnums=(0, 1)))(X, u)  # (N, 6, 6), (N, 6, m)
    d = Ai.shape[-1]
    # Car j's rows padded with zeros left and right of its own block. Zero padding fuses
    # into the Jacobian kernels; a mask product over (N, 6, N, 6) cost about a third of
    # the linearisation on CPU (0.146 -> 0.081-0.096 ms, N = 2, T = 50).
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
        dynamics=_race_dynamics,
        stage_cost=_race_stage_cost,
        terminal_cost=_race_terminal_cost,
        num_players=game.num_players,
        state_dim=game.num_players * game.state_dim,
        input_dim=game.input_dim,
        horizon=game.horizon,
        params=game,
        stage_gauss_newton=_race_stage_gauss_newton,
        terminal_gauss_newton=_race_terminal_gauss_newton,
        dynamics_jacobians=_race_dynamics_jacobians,
        stage_curvature=_race_stage_curvature,
    )


def _is_race_game(obj) -> bool:
    from racing_env.game import RaceGame  # local import: the solver does not need racing_env

    return isinstance(obj, RaceGame)


def _as_problem(problem_or_game) -> tuple[GameProblem, bool]:
    if isinstance(problem_or_game, GameProblem):
        return problem_or_game, False
    if _is_race_game(problem_or_game):
        return problem_from_race_game(problem_or_game), True
    raise TypeError(
        f"expected a GameProblem or a racing_env.RaceGame, got {type(problem_or_game).__name__}"
    )


# --------------------------------------------------------------------------------------
# Options and result.
# --------------------------------------------------------------------------------------

_MODES = ("feedback", "open_loop")
_STEP_CONTROLS = ("trust_region", "residual", "none")
_CONVEXIFY = ("auto", "gauss_newton", "eig", "diag", "none")


@dataclasses.dataclass(frozen=True)
class SolverOptions:
    """Configuration of :func:`solve` (static: a new configuration compiles a new solver).

    Attributes:
        mode: ``"feedback"`` or ``"open_loop"`` Nash equilibrium of the local LQ games.
        max_iterations: iteration cap (>= 1).
        tolerance: convergence when a full step changes the state trajectory by at most this
            much (max-norm over stages and state entries, state units).
        step_control: ``"trust_region"`` (shrink ``eta`` until the step stays inside
            ``trust_radius``, plus overshoot damping), ``"residual"`` (open loop only:
            shrink it until the step also decreases the open-loop Nash residual) or
            ``"none"`` (fixed ``eta = initial_step``).
        trust_radius: largest accepted max-norm change of the state trajectory per iteration.
        initial_step: the largest ``eta``, tried first, in ``(0, 1]``.
        step_decay: factor in ``(0, 1)`` by which ``eta`` shrinks per trial.
        max_backtracks: trials after the first before the search gives up.
        oscillation_damping: start the next iteration at a shorter ``eta`` after a step that
            reverses the recent direction of travel (trust-region mode only).
        damping_memory: decay in ``[0, 1)`` of the running sum of past step directions.
        state_regularization: ``lambda_x >= 0`` added to the diagonal of every ``Q_t^i``.
        convexify: ``"gauss_newton"`` (PSD Gauss-Newton quadratisation from the problem's
            ``stage_gauss_newton``/``terminal_gauss_newton`` hooks; every RaceGame has them),
            ``"eig"`` (exact Hessians, every ``Q_t^i`` projected onto the PSD cone),
            ``"diag"`` (exact Hessians made diagonally dominant: more conservative),
            ``"none"`` (exact Hessians), or ``"auto"`` (the default): ``"gauss_newton"``
            where the problem has the hooks, else ``"eig"``.
        control_regularization: ``lambda_u >= 0`` added to the diagonal of every ``R_t^{ii}``
            (a proximal term on the input change: it shortens the LQ step without moving an
            open-loop fixed point); with ``feedforward_regularization``, to the feed-forward
            rows of the feedback LQ step instead.
        adaptive_regularization: adapt ``lambda_u`` per iteration (Levenberg-Marquardt
            style; open loop, one player, or feedback with ``feedforward_regularization``):
            divided by ``regularization_factor``
            after a step that continues the recent direction of travel, raised to
            ``max(factor * lambda_u, control_regularization)`` after one that reverses it,
            and 0 after a step within ``tolerance``: only an undamped step certifies
            convergence. Starts at ``control_regularization``, which must then be > 0.
        regularization_factor: that factor, > 1.
        feedforward_regularization: feedback games: ``lambda_u`` (fixed or adaptive) damps
            only the feed-forward terms ``k`` of the LQ step, not ``R^{ii}``
            (:func:`~planners.lq_game.solve_feedback`'s ``feedforward_regularization``,
            which also says when it damps), the gains ``K`` stay those of the local game. A
            feedback game's fixed points then stay its equilibria (all ``k = 0`` exactly
            where the undamped ones are), so ``adaptive_regularization`` is allowed for it.
            Needs ``control_regularization > 0``; refused in open loop, where the whole LQ
            step is feed-forward (``control_regularization`` alone damps it).
        dynamics_curvature: add the problem's ``stage_curvature`` (see :class:`GameProblem`;
            RaceGame and iLQR: each car's progress in its heading) to the diagonal of every
            stage's ``Q^i``, in every ``convexify`` mode (before the PSD projection). The
            gradients, and so the open-loop fixed points, do not change; the feedback gains
            do (they follow ``Q``). No effect on problems without the hook.
    """

    mode: str = "feedback"
    max_iterations: int = 100
    tolerance: float = 1e-6
    step_control: str = "trust_region"
    trust_radius: float = 2.0
    initial_step: float = 1.0
    step_decay: float = 0.5
    max_backtracks: int = 25
    oscillation_damping: bool = True
    damping_memory: float = 0.8
    state_regularization: float = 0.0
    convexify: str = "auto"
    control_regularization: float = 0.0
    adaptive_regularization: bool = False
    regularization_factor: float = 1.5
    feedforward_regularization: bool = False
    dynamics_curvature: bool = True

    @property
    def guaranteed_control_regularization(self) -> float:
        """The ``lambda_u`` that every LQ step adds to ``R^{ii}`` (what
        :func:`validate_problem` may count on): ``control_regularization``, or 0 where it is
        adapted (it drops to 0 before a step may certify) or on the feed-forward terms."""
        if self.adaptive_regularization or self.feedforward_regularization:
            return 0.0
        return self.control_regularization

    def __post_init__(self) -> None:
        for name in ("oscillation_damping", "adaptive_regularization", "feedforward_regularization",
                     "dynamics_curvature"):
            # a string such as "false" would be truthy
            if not isinstance(getattr(self, name), (bool, np.bool_)):
                raise ValueError(f"SolverOptions.{name} must be True or False, got {getattr(self, name)!r}")
        if self.mode not in _MODES:
            raise ValueError(f"mode must be one of {_MODES}, got {self.mode!r}")
        if self.step_control not in _STEP_CONTROLS:
            raise ValueError(
                f"step_control must be one of {_STEP_CONTROLS}, got {self.step_control!r}"
            )
        if self.step_control == "residual" and self.mode != "open_loop":
            raise ValueError(
                "step_control='residual' needs mode='open_loop' (of the agents, ilqgame-ol): it "
                "decreases the open-loop Nash residual, which a feedback equilibrium does not zero"
            )
        if self.adaptive_regularization and not self.control_regularization > 0:
            raise ValueError(
                "adaptive_regularization needs control_regularization > 0 (the value it starts "
                f"at and returns to after a reversing step), got {self.control_regularization!r}"
            )
        if self.feedforward_regularization and self.mode != "feedback":
            raise ValueError(
                "feedforward_regularization is for feedback games: an open-loop LQ step is all "
                "feed-forward, and control_regularization alone damps it"
            )
        if self.feedforward_regularization and not self.control_regularization > 0:
            raise ValueError(
                "feedforward_regularization needs control_regularization > 0 (the lambda_u it "
                f"puts on the feed-forward terms), got {self.control_regularization!r}"
            )
        if self.convexify not in _CONVEXIFY:
            raise ValueError(f"convexify must be one of {_CONVEXIFY}, got {self.convexify!r}")
        if int(self.max_iterations) < 1:
            raise ValueError(f"max_iterations must be >= 1, got {self.max_iterations!r}")
        if int(self.max_backtracks) < 0:
            raise ValueError(f"max_backtracks must be >= 0, got {self.max_backtracks!r}")
        checks = {
            "tolerance": self.tolerance >= 0,
            "trust_radius": self.trust_radius > 0,
            "initial_step": 0 < self.initial_step <= 1,
            "step_decay": 0 < self.step_decay < 1,
            "damping_memory": 0 <= self.damping_memory < 1,
            "state_regularization": self.state_regularization >= 0,
            "control_regularization": self.control_regularization >= 0,
            "regularization_factor": self.regularization_factor > 1,
        }
        allowed = {
            "tolerance": ">= 0 (0: run all max_iterations unless a step is exactly zero)",
            "trust_radius": "> 0",
            "initial_step": "in (0, 1]",
            "step_decay": "in (0, 1)",
            "damping_memory": "in [0, 1)",
            "state_regularization": ">= 0",
            "control_regularization": ">= 0",
            "regularization_factor": "> 1",
        }
        for name, ok in checks.items():
            value = getattr(self, name)
            if not (np.isfinite(value) and ok):
                raise ValueError(f"SolverOptions.{name} must be {allowed[name]}, got {value!r}")


class SolverResult(NamedTuple):
    """Outcome of :func:`solve` (a pytree; batched along a leading axis by :func:`solve_batch`).

    Attributes:
        xs: state trajectory ``(T+1, n)``, or ``(T+1, N, 6)`` when a RaceGame was passed.
        us: inputs ``(T, N, m)``.
        converged: bool, status == CONVERGED.
        status: int code, see :func:`status_message`.
        iterations: number of accepted steps (each: one LQ solve and one forward pass with
            step-size search).
        costs: ``(N,)`` total cost of every player along ``(xs, us)``.
        eta: step size of the last accepted step.
        K: ``(T, N, m, n)`` feedback gains of the last LQ solve (zeros for open loop).
        k: ``(T, N, m)`` feed-forward terms of the last LQ solve (around the previous
            nominal; at convergence they vanish).
        history: ``(max_iterations,)`` the convergence measure per iteration: state change of
            the step scaled to a full step (NaN after the end).
        step_history: ``(max_iterations,)`` accepted ``eta`` per iteration.
        k_history: ``(max_iterations,)`` ``max |k|`` of every LQ solve.
    """

    xs: Array
    us: Array
    converged: Array
    status: Array
    iterations: Array
    costs: Array
    eta: Array
    K: Array
    k: Array
    history: Array
    step_history: Array
    k_history: Array


# --------------------------------------------------------------------------------------
# Building blocks (pure JAX).
# --------------------------------------------------------------------------------------


def rollout(problem: GameProblem, x0: Array, us: Array) -> Array:
    """Simulate ``us (T, N, m)`` from ``x0 (n,)``: ``xs (T+1, n)``."""
    params = problem.params

    def body(x, inp):
        t, u = inp
        x_next = problem.dynamics(params, t, x, u)
        return x_next, x_next

    ts = jnp.arange(us.shape[0])
    _, xs = jax.lax.scan(body, x0, (ts, us))
    return jnp.concatenate([x0[None], xs], axis=0)


def total_costs(problem: GameProblem, xs: Array, us: Array) -> Array:
    """Total cost of every player along ``xs (T+1, n)``, ``us (T, N, m)``: ``(N,)``."""
    params = problem.params
    players = jnp.arange(problem.num_players)
    ts = jnp.arange(us.shape[0])

    def stage(t, x, u):
        return jax.vmap(lambda i, u_i: problem.stage_cost(params, t, i, x, u_i))(players, u)

    running = jax.vmap(stage)(ts, xs[:-1], us).sum(axis=0)
    terminal = jax.vmap(lambda i: problem.terminal_cost(params, i, xs[-1]))(players)
    return running + terminal


def _linearize(problem: GameProblem, xs: Array, us: Array) -> tuple[Array, Array]:
    """``A (T, n, n)`` and ``B (T, N, n, m)`` along the nominal trajectory."""
    params = problem.params
    if problem.dynamics_jacobians is not None:
        jac = lambda t, x, u: problem.dynamics_jacobians(params, t, x, u)
    else:
        jac = jax.jacfwd(lambda t, x, u: problem.dynamics(params, t, x, u), argnums=(1, 2))
    A, B = jax.vmap(jac)(jnp.arange(us.shape[0]), xs[:-1], us)  # B (T, n, N, m)
    return A, jnp.transpose(B, (0, 2, 1, 3))


def _hess_grad(fun: Callable[[Array], Array], z: Array) -> tuple[Array, Array]:
    """Hessian and gradient of a scalar function in one forward-over-reverse pass."""
    grad = jax.grad(fun)

    def grad_twice(z_):
        g = grad(z_)
        return g, g

    return jax.jacfwd(grad_twice, has_aux=True)(z)


def _gauss_newton_factors(fun: Callable, z: Array) -> tuple[Array, Array, Array]:
    """The residual Jacobian ``J (K, D)``, outer slopes ``g (K,)`` and clipped outer
    curvatures ``h >= 0 (K,)`` of ``sum_k rho_k(r_k(z))``, where ``fun(z) = (r, g, h)``
    (one forward-mode pass)."""
    J, (g, h) = jax.jacfwd(lambda z_: (lambda r, g, h: (r, (g, h)))(*fun(z_)), has_aux=True)(z)
    return J, jax.lax.stop_gradient(g), jax.lax.stop_gradient(jnp.maximum(h, 0.0))


# Multiply-adds of one product up to which it is written as fused code. XLA rewrote the
# fused form into a dot, which jaxlib 0.10 hands to YNNPACK, at 3,600 (three cars: K = 9,
# D = 20); at 1,568 (two cars: K = 8, D = 14) it did not.
_GRAM_FUSED_MAX = 2048


def _gauss_newton_products(J: Array, g: Array, h: Array) -> tuple[Array, Array]:
    """``J' diag(h) J (D, D)`` and ``J' g (D,)`` of factors ``J (K, D)``, ``g, h (K,)``."""
    Jh = J * h[:, None]
    if J.size * J.shape[1] <= _GRAM_FUSED_MAX:
        H = lq_game._contract("ka,kb->ab", Jh, J)
    else:
        # Contracted axis leading: XLA emits the dot itself (see lq_game._sandwich).
        H = jax.lax.dot_general(Jh, J, (((0,), (0,)), ((), ())))
    return H, lq_game._contract("ka,k->a", J, g)


def _gauss_newton_terms(fun: Callable, z: Array) -> tuple[Array, Array]:
    """Gauss-Newton Hessian ``J' diag(h) J`` and exact gradient ``J' g`` of
    ``sum_k rho_k(r_k(z))``, where ``fun(z) = (r, g, h)`` (one forward-mode pass)."""
    return _gauss_newton_products(*_gauss_newton_factors(fun, z))


def _stagewise_gauss_newton_products(J: Array, g: Array, h: Array) -> tuple[Array, Array]:
    """:func:`_gauss_newton_products` of ``(T, N, ...)`` factors, one stage after another.

    As a loop over the stages the products compile into one kernel
    (:mod:`racing_env.xla_setup`). As one batched product over all stages XLA:CPU hands
    them to a YNNPACK library call, which cost 2.2-2.6x as much for the paper scene's
    shapes and, being the last library call in a two-car solver iteration, kept the solver's
    outer loop from becoming one kernel too (README, Loop kernels).
    """
    def stage(_, factors):
        return None, jax.vmap(_gauss_newton_products)(*factors)

    return jax.lax.scan(stage, None, (J, g, h))[1]


def _all_gauss_newton_products(J: Array, g: Array, h: Array) -> tuple[Array, Array]:
    """:func:`_gauss_newton_products` over any leading axes, as batched products."""
    return jnp.einsum("...ka,...k,...kb->...ab", J, h, J), jnp.einsum("...ka,...k->...a", J, g)


# Under vmap (batches of games) the batched products are faster than a loop over the
# stages per game: 396-402 ms against 473 ms (lax.map of the loop) and 698 ms (the loop
# vmapped) for a vmapped batch of 64 paper scenes on one core.
_quadratize_products = with_batched_form(_stagewise_gauss_newton_products, _all_gauss_newton_products)


def _quadratize(problem: GameProblem, xs: Array, us: Array, gauss_newton: bool = False,
                dynamics_curvature: bool = False):
    """Per-player ``Q (T+1, N, n, n)``, ``q (T+1, N, n)``, ``Rii (T, N, m, m)``, ``rii (T, N, m)``.

    Exact Hessians, or with ``gauss_newton`` the problem's Gauss-Newton form (PSD); with
    ``dynamics_curvature`` the problem's ``stage_curvature`` (if it has one) is added to the
    diagonal of the stages' ``Q``. The gradients are exact either way.
    """
    params = problem.params
    n = problem.state_dim
    players = jnp.arange(problem.num_players)
    if gauss_newton:
        terms, stage_fn, terminal_fn = (
            _gauss_newton_terms, problem.stage_gauss_newton, problem.terminal_gauss_newton
        )
    else:
        terms, stage_fn, terminal_fn = _hess_grad, problem.stage_cost, problem.terminal_cost

    def stage(t, x, u):
        def player(i, u_i):
            fun = lambda z: stage_fn(params, t, i, z[:n], z[n:])
            return (_gauss_newton_factors if gauss_newton else terms)(fun, jnp.concatenate([x, u_i]))

        return jax.vmap(player)(players, u)

    stages = jax.vmap(stage)(jnp.arange(us.shape[0]), xs[:-1], us)
    H, g = _quadratize_products(*stages) if gauss_newton else stages
    Q, q, Rii, rii = H[..., :n, :n], g[..., :n], H[..., n:, n:], g[..., n:]
    QT, qT = jax.vmap(lambda i: terms(lambda x: terminal_fn(params, i, x), xs[-1]))(players)
    if dynamics_curvature and problem.stage_curvature is not None:
        def diagonal(t, x):
            return jax.vmap(lambda i: problem.stage_curvature(params, t, i, x))(players)

        d = jax.lax.stop_gradient(jax.vmap(diagonal)(jnp.arange(us.shape[0]), xs[:-1]))  # (T, N, n)
        Q = Q + jnp.maximum(d, 0.0)[..., None] * jnp.eye(n, dtype=Q.dtype)
    Q = jnp.concatenate([Q, QT[None]], axis=0)
    q = jnp.concatenate([q, qT[None]], axis=0)
    return Q, q, Rii, rii


def _own_to_full(Rii: Array, rii: Array) -> tuple[Array, Array]:
    """Embed own blocks ``(T, N, m, m)``, ``(T, N, m)`` into ``R (T, N, N, m, m)``, ``r``."""
    T, N, m = rii.shape
    idx = jnp.arange(N)
    R = jnp.zeros((T, N, N, m, m), Rii.dtype).at[:, idx, idx].set(Rii)
    r = jnp.zeros((T, N, N, m), rii.dtype).at[:, idx, idx].set(rii)
    return R, r


def _convexify(problem: GameProblem, options: SolverOptions) -> str:
    """The convexification actually used (``"auto"`` resolved)."""
    if options.convexify == "auto":
        return "gauss_newton" if problem.has_gauss_newton else "eig"
    if options.convexify == "gauss_newton" and not problem.has_gauss_newton:
        raise ValueError(
            'convexify="gauss_newton" needs a problem with stage_gauss_newton and '
            "terminal_gauss_newton hooks (see GameProblem); use \"eig\" or \"auto\""
        )
    return options.convexify


def _psd_part_sequential(Q: Array) -> Array:
    """The PSD part ``V max(w, 0) V'`` of every symmetric ``(n, n)`` block of ``Q (..., n, n)``,
    one eigendecomposition after another."""
    def one(M):
        w, V = jnp.linalg.eigh(M)
        return (V * jnp.maximum(w, 0.0)) @ V.T

    return jax.lax.map(one, Q.reshape((-1,) + Q.shape[-2:])).reshape(Q.shape)


# One LAPACK call per matrix, also in a vmapped batch split across CPU devices: a batched
# call hangs there (see planners.batching.one_at_a_time).
_psd_part = one_at_a_time(_psd_part_sequential)


def _regularize(Q: Array, Rii: Array, options: SolverOptions, convexify: str,
                control_regularization: Array | float | None = None) -> tuple[Array, Array]:
    """PSD ``Q`` per ``convexify`` and the diagonal terms; ``control_regularization`` is the
    current ``lambda_u`` (the solver state's, adapted or not; default: the options')."""
    # Gauss-Newton Q is PSD by construction (and symmetrised by the LQ solvers).
    if convexify != "gauss_newton":
        Q = 0.5 * (Q + jnp.swapaxes(Q, -1, -2))
    if convexify == "eig":
        Q = _psd_part(Q)
    elif convexify == "diag":
        diag = jnp.diagonal(Q, axis1=-2, axis2=-1)
        off = jnp.sum(jnp.abs(Q), axis=-1) - jnp.abs(diag)
        Q = Q + jnp.eye(Q.shape[-1], dtype=Q.dtype) * jnp.maximum(off - diag, 0.0)[..., None]
    if options.state_regularization > 0:
        Q = Q + options.state_regularization * jnp.eye(Q.shape[-1], dtype=Q.dtype)
    # feedforward_regularization: lambda_u enters the feedback LQ solve instead (the gains
    # stay those of the local game).
    if options.control_regularization > 0 and not options.feedforward_regularization:
        lam = options.control_regularization if control_regularization is None else control_regularization
        Rii = Rii + lam * jnp.eye(Rii.shape[-1], dtype=Rii.dtype)
    return Q, Rii


def _lq_step(problem: GameProblem, xs: Array, us: Array, options: SolverOptions,
             control_regularization: Array | float):
    """Linearise, quadratise and solve the local LQ game: ``K (T, N, m, n)``, ``k (T, N, m)``
    (``control_regularization``: the current ``lambda_u``, see :func:`_regularize`)."""
    convexify = _convexify(problem, options)
    A, B = _linearize(problem, xs, us)
    Q, q, Rii, rii = _quadratize(problem, xs, us, convexify == "gauss_newton",
                                 options.dynamics_curvature)
    Q, Rii = _regularize(Q, Rii, options, convexify, control_regularization)
    lam_k = control_regularization if options.feedforward_regularization else None
    if options.mode == "feedback" and convexify != "none":
        # Every Q^i is PSD: the own-input solver's block elimination is safe.
        K, k = lq_game.solve_feedback_own(A, B, Q, q, Rii, rii, lam_k)
    elif options.mode == "feedback":
        K, k = lq_game.solve_feedback(A, B, Q, q, *_own_to_full(Rii, rii), lam_k)
    else:
        # Deviation coordinates: the local game starts at dx_0 = 0, not at x_0.
        k, _ = lq_game.solve_open_loop_own(A, B, Q, q, Rii, rii, jnp.zeros_like(xs[0]))
        K = jnp.zeros(k.shape + (xs.shape[-1],), k.dtype)
    return K, k


def _forward(problem: GameProblem, xs_hat: Array, us_hat: Array, K: Array, k: Array, eta):
    """Nonlinear forward pass ``u = u_hat - K (x - x_hat) - eta k`` from ``xs_hat[0]``."""
    params = problem.params

    def body(x, inp):
        t, x_hat, u_hat, K_t, k_t = inp
        # K_t (x - x_hat) as a fused multiply-sum: a dot is a separate XLA:CPU call.
        u = u_hat - jnp.sum(K_t * (x - x_hat), axis=-1) - eta * k_t
        return problem.dynamics(params, t, x, u), (x, u)

    ts = jnp.arange(us_hat.shape[0])
    # Not unrolled (nor are the other solver loops): compiled into one kernel, an unrolled
    # loop ran no faster and compiled for longer (docs/performance.md, Compile time).
    xT, (xs, us) = jax.lax.scan(body, xs_hat[0], (ts, xs_hat[:-1], us_hat, K, k))
    return jnp.concatenate([xs, xT[None]], axis=0), us


def _deviation(xs_new: Array, xs_hat: Array) -> Array:
    """Max-norm state change; ``inf`` for a non-finite trajectory."""
    d = jnp.max(jnp.abs(xs_new - xs_hat))
    return jnp.where(jnp.isfinite(d), d, jnp.inf)


def _merit(problem: GameProblem, x0: Array, us: Array) -> Array:
    """``sum_i |dJ^i/du^i|^2``, the squared open-loop Nash residual of ``us (T, N, m)`` from
    ``x0 (n,)`` (see :func:`nash_residual`); ``inf`` where it is not finite."""
    merit = jnp.sum(_own_gradients(jax.jacrev(_costs_of_inputs(problem, x0))(us)) ** 2)
    return jnp.where(jnp.isfinite(merit), merit, jnp.inf)


# Sufficient decrease of the residual rule: accept eta when the squared residual falls to
# (1 - 2 c eta) of its value, the first-order decrease of an exact Newton step (1 - eta)^2
# with Armijo's customary c = 1e-4.
_RESIDUAL_DECREASE = 1e-4


def _residual_step(problem, xs_hat, us_hat, K, k, eta0, merit0, options: SolverOptions):
    """Backtracking on the open-loop Nash residual (``step_control="residual"``).

    Tries ``eta0 * step_decay^j`` until the step stays inside the trust region and
    decreases ``sum_i |dJ^i/du^i|^2`` sufficiently from ``merit0``, that of ``us_hat``
    (carried from the previous iteration, so each point's residual is computed once). If
    no trial does (the Gauss-Newton LQ game's direction need not be a descent direction of
    the residual, e.g. from a cold start), it takes the first trial inside the trust
    region, the default rule's step. Returns ``(xs, us, eta, deviation, ok, merit)`` like
    :func:`_step`, ``merit`` that of the step taken.
    """
    radius = options.trust_radius
    x0 = xs_hat[0]
    inf = jnp.asarray(jnp.inf, xs_hat.dtype)

    def accepted(dev, merit, eta):
        return (dev <= radius) & (merit <= (1.0 - 2.0 * _RESIDUAL_DECREASE * eta) * merit0)

    def cond(c):
        _, _, eta, dev, merit, trial, _ = c
        return (trial == 0) | (~accepted(dev, merit, eta) & (trial <= options.max_backtracks))

    def body(c):
        _, _, eta, _, _, trial, inside = c
        eta = jnp.where(trial == 0, eta, eta * options.step_decay)
        xs, us = _forward(problem, xs_hat, us_hat, K, k, eta)
        dev = _deviation(xs, xs_hat)
        # A trial outside the trust region is refused whatever its residual. (A lax.cond
        # that skips its N reverse passes halved the compile time but made the paper
        # scene's solve 35% slower on CPU: such trials are rare.)
        merit = jnp.where(dev <= radius, _merit(problem, x0, us), inf)
        first_inside = (dev <= radius) & (inside[3] > radius)
        inside = _select(first_inside, (xs, us, eta, dev, merit), inside)
        return xs, us, eta, dev, merit, trial + 1, inside

    start = (xs_hat, us_hat, eta0, inf, inf, 0, (xs_hat, us_hat, eta0, inf, inf))
    xs, us, eta, dev, merit, _, inside = jax.lax.while_loop(cond, body, start)
    xs, us, eta, dev, merit = _select(accepted(dev, merit, eta), (xs, us, eta, dev, merit), inside)
    return xs, us, eta, dev, dev <= radius, merit


def _select(pred: Array, new, old):
    """``new`` where the scalar ``pred`` holds, else ``old`` (pytrees of equal structure)."""
    return jax.tree_util.tree_map(lambda a, b: jnp.where(pred, a, b), new, old)


def _step(problem, xs_hat, us_hat, K, k, eta0, merit0, options: SolverOptions):
    """Step-size search from ``eta0``. Returns ``(xs, us, eta, deviation, ok, merit)``;
    ``merit`` is the residual rule's (see :func:`_residual_step`), ``merit0`` for the
    other rules, which do not compute it."""
    eta0 = jnp.asarray(eta0, xs_hat.dtype)
    if options.step_control == "none":
        xs, us = _forward(problem, xs_hat, us_hat, K, k, eta0)
        dev = _deviation(xs, xs_hat)
        return xs, us, eta0, dev, jnp.isfinite(dev), merit0
    if options.step_control == "residual":
        return _residual_step(problem, xs_hat, us_hat, K, k, eta0, merit0, options)

    radius = options.trust_radius
    # Trial 0 runs at eta0, trial j > 0 at eta0 * step_decay^j. The first trial is a pass of
    # the loop too, so the compiled solver holds one forward pass instead of two (compile
    # time; the trials and their results are the same).
    def cond(c):
        _, _, _, dev, trial = c
        return (trial == 0) | ((dev > radius) & (trial <= options.max_backtracks))

    def body(c):
        _, _, eta, _, trial = c
        eta = jnp.where(trial == 0, eta, eta * options.step_decay)
        xs, us = _forward(problem, xs_hat, us_hat, K, k, eta)
        return xs, us, eta, _deviation(xs, xs_hat), trial + 1

    start = (xs_hat, us_hat, eta0, jnp.asarray(jnp.inf, xs_hat.dtype), 0)
    xs, us, eta, dev, _ = jax.lax.while_loop(cond, body, start)
    return xs, us, eta, dev, dev <= radius, merit0


class _Carry(NamedTuple):
    it: Array
    xs: Array
    us: Array
    K: Array
    k: Array
    eta: Array
    cap: Array  # eta tried first in the next iteration
    last_step: Array  # decaying sum of the accepted steps' directions (overshoot detection)
    control_regularization: Array  # lambda_u of the next LQ game (adapted or constant)
    merit: Array  # the residual rule's squared Nash residual of (xs, us); nan for other rules
    status: Array
    history: Array
    step_history: Array
    k_history: Array


def _initial_carry(problem: GameProblem, x0: Array, us0: Array, options: SolverOptions) -> _Carry:
    """The solver state before the first iteration: ``x0 (n,)``, ``us0 (T, N, m)``."""
    T, N, m = problem.horizon, problem.num_players, problem.input_dim
    dtype = jnp.result_type(x0.dtype, us0.dtype, float)
    x0 = x0.reshape(-1).astype(dtype)
    us0 = us0.astype(dtype)
    xs0 = rollout(problem, x0, us0)
    nan_hist = jnp.full((options.max_iterations,), jnp.nan, dtype)
    return _Carry(
        it=jnp.asarray(0),
        xs=xs0,
        us=us0,
        K=jnp.zeros((T, N, m, x0.shape[0]), dtype),
        k=jnp.zeros((T, N, m), dtype),
        eta=jnp.asarray(0.0, dtype),
        cap=jnp.asarray(options.initial_step, dtype),
        last_step=jnp.zeros_like(xs0),
        control_regularization=jnp.asarray(options.control_regularization, dtype),
        merit=_merit(problem, x0, us0) if options.step_control == "residual" else jnp.asarray(jnp.nan, dtype),
        status=jnp.where(jnp.all(jnp.isfinite(xs0)), RUNNING, NON_FINITE),
        history=nan_hist,
        step_history=nan_hist,
        k_history=nan_hist,
    )


def _iterate(problem: GameProblem, c: _Carry, options: SolverOptions) -> _Carry:
    """One iteration: LQ game around ``(c.xs, c.us)``, step-size search, status update."""
    damping = options.step_control == "trust_region" and options.oscillation_damping
    adaptive = options.adaptive_regularization
    dtype = c.xs.dtype
    K, k = _lq_step(problem, c.xs, c.us, options, c.control_regularization)
    lq_ok = jnp.all(jnp.isfinite(K)) & jnp.all(jnp.isfinite(k))
    xs, us, eta, dev, step_ok, merit = _step(problem, c.xs, c.us, K, k, c.cap, c.merit, options)
    ok = lq_ok & step_ok
    it = c.it + ok.astype(c.it.dtype)
    # Convergence measure: the state change of a full step (exact for eta = 1; the
    # change is linear in eta to first order).
    measure = dev * (options.initial_step / eta)
    step = xs - c.xs
    direction = c.last_step
    if damping or adaptive:
        # A step that reverses the recent direction of travel (negative inner product with
        # a decaying sum of the previous unit steps) was too long for a contraction.
        reversed_ = jnp.vdot(step, c.last_step) < 0
        unit = step / jnp.maximum(jnp.sqrt(jnp.vdot(step, step)), 1e-300)
        direction = options.damping_memory * c.last_step + unit
    if damping:
        # Overshoot damping: after a reversal the next search starts at eta * step_decay.
        # Otherwise the next search starts again at initial_step: a step cut short by
        # the trust region says nothing about the next one (typically a soft
        # constraint just became active and the next proposal is orders of magnitude
        # smaller), and a trial costs one rollout, a fraction of an LQ solve.
        cap = jnp.where(
            reversed_,
            eta * options.step_decay,
            jnp.asarray(options.initial_step, dtype),
        )
    else:
        cap = jnp.asarray(options.initial_step, dtype)
    lam = c.control_regularization
    small = measure <= options.tolerance
    certifies = True
    if adaptive:
        # Levenberg-Marquardt: more damping of the LQ step after a reversal (the iterates
        # cycle between active sets of the limit costs), less while they keep going.
        # A damped step is short because of lambda_u, not only because the iterate is near
        # a fixed point: a step below the tolerance is checked by an undamped one, and only
        # an undamped step certifies convergence (the test of the other rules).
        factor = options.regularization_factor
        lam = jnp.where(small, 0.0, jnp.where(reversed_, jnp.maximum(lam * factor, options.control_regularization),
                                              lam / factor))
        certifies = c.control_regularization == 0
    status = jnp.where(
        ~lq_ok,
        NON_FINITE,
        jnp.where(
            ~step_ok,
            jnp.where(jnp.isfinite(dev), LINE_SEARCH_FAILED, NON_FINITE),
            jnp.where(
                small & (eta >= c.cap) & certifies,
                CONVERGED,
                jnp.where(it >= options.max_iterations, MAX_ITERATIONS, RUNNING),
            ),
        ),
    )
    keep = functools.partial(_select, ok)
    return _Carry(
        it=it,
        xs=keep(xs, c.xs),
        us=keep(us, c.us),
        K=keep(K, c.K),
        k=keep(k, c.k),
        eta=keep(eta, c.eta),
        cap=keep(cap, c.cap),
        last_step=keep(direction, c.last_step),
        control_regularization=keep(lam, c.control_regularization),
        merit=keep(merit, c.merit),
        status=status,
        history=c.history.at[c.it].set(jnp.where(ok, measure, jnp.nan)),
        step_history=c.step_history.at[c.it].set(jnp.where(ok, eta, jnp.nan)),
        k_history=c.k_history.at[c.it].set(jnp.max(jnp.abs(k))),
    )


def _result(problem: GameProblem, c: _Carry, x_shape: tuple[int, ...]) -> SolverResult:
    """The :class:`SolverResult` of a finished solver state (states in ``x_shape`` per stage)."""
    return SolverResult(
        xs=c.xs.reshape((c.xs.shape[0],) + tuple(x_shape)),
        us=c.us,
        converged=c.status == CONVERGED,
        status=c.status,
        iterations=c.it,
        costs=total_costs(problem, c.xs, c.us),
        eta=c.eta,
        K=c.K,
        k=c.k,
        history=c.history,
        step_history=c.step_history,
        k_history=c.k_history,
    )


def _iterate_while_running(problem: GameProblem, c: _Carry, options: SolverOptions, steps: int | None = None) -> _Carry:
    """Iterate until the status is no longer RUNNING, or for at most ``steps`` iterations."""
    if steps is None:
        return jax.lax.while_loop(lambda c: c.status == RUNNING, lambda c: _iterate(problem, c, options), c)
    _, c = jax.lax.while_loop(
        lambda nc: (nc[1].status == RUNNING) & (nc[0] < steps),
        lambda nc: (nc[0] + 1, _iterate(problem, nc[1], options)),
        (jnp.asarray(0), c),
    )
    return c


@functools.partial(jax.jit, static_argnames=("options",))
def _solve_jit(problem: GameProblem, x0: Array, us0: Array, options: SolverOptions):
    """The whole solve. ``x0`` has ``n`` entries in any shape (``xs`` is returned in that
    shape per stage). Reshapes and casts happen here, so a call from :func:`solve`
    dispatches a single computation."""
    c = _initial_carry(problem, x0, us0, options)
    return _result(problem, _iterate_while_running(problem, c, options), x0.shape)


# --------------------------------------------------------------------------------------
# Validation (outside jit).
# --------------------------------------------------------------------------------------


@jax.jit
def _first_own_hessians(problem: GameProblem, x0: Array, us0: Array) -> Array:
    xs = rollout(problem, x0, us0)
    return _quadratize(problem, xs, us0)[2]


def _is_concrete(*trees) -> bool:
    leaves = jax.tree_util.tree_leaves(trees)
    return not any(isinstance(leaf, jax.core.Tracer) for leaf in leaves)


def validate_problem(problem_or_game, x0=None, us0=None, control_regularization: float = 0.0):
    """Refuse games whose own-input Hessians ``R_t^{ii}`` are not positive definite.

    For a RaceGame ``R^{ii} = 2 diag(r_jx, r_jy)`` of player i's jerk weights, checked
    directly. For a GameProblem the first quadratisation (along the rollout of ``us0``,
    zeros by default, from ``x0``) is checked at every stage. ``control_regularization``
    is added first: the part the solver adds in every LQ step
    (:attr:`SolverOptions.guaranteed_control_regularization`).

    Raises:
        ValueError: naming the player (and stage) and the smallest eigenvalue.
    """
    if _is_race_game(problem_or_game):
        game = problem_or_game
        if not _is_concrete(game.weights):
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
        return
    problem, _ = _as_problem(problem_or_game)
    if x0 is None:
        raise ValueError("validate_problem needs x0 for a GameProblem")
    x0 = jnp.asarray(x0)
    if us0 is None:
        us0 = jnp.zeros((problem.horizon, problem.num_players, problem.input_dim), x0.dtype)
    if not _is_concrete(problem, x0, us0):
        return
    Rii = np.asarray(_first_own_hessians(problem, x0, jnp.asarray(us0)))
    Rii = 0.5 * (Rii + np.swapaxes(Rii, -1, -2))
    Rii = Rii + control_regularization * np.eye(Rii.shape[-1])
    if not np.all(np.isfinite(Rii)):
        raise ValueError("the own-input Hessians R^ii are not finite along the initial rollout")
    eig = np.linalg.eigvalsh(Rii)  # (T, N, m)
    lam = eig.min(axis=-1)
    scale = np.maximum(1.0, np.abs(Rii).max(axis=(-1, -2)))
    bad = ~(lam > 1e-12 * scale)
    if np.any(bad):
        t, i = map(int, np.argwhere(bad)[0])
        raise ValueError(
            f"R^ii of player {i} (Hessian of its stage cost w.r.t. its own input) is not "
            f"positive definite at stage {t}: min eigenvalue {lam[t, i]:.3e}. The LQ game "
            "needs R^ii > 0 at every stage (make the input cost strictly convex or raise "
            "control_regularization)"
        )


# --------------------------------------------------------------------------------------
# Public API.
# --------------------------------------------------------------------------------------


def check_adaptive_regularization(options: SolverOptions, num_players: int) -> None:
    """Refuse ``adaptive_regularization`` on ``R^{ii}`` for a feedback game of ``num_players > 1``.

    ``lambda_u`` does not move an open-loop fixed point (``k = 0`` exactly where every
    player's gradient vanishes) nor a one-player one, but a feedback game's fixed point
    depends on the players' gains ``K``, which depend on ``R^{ii} + lambda_u I``: a
    ``lambda_u`` that changes with every reversal moves the point the iterates converge to.
    With ``feedforward_regularization`` the gains do not see ``lambda_u``, and it is allowed.
    """
    if (options.adaptive_regularization and options.mode == "feedback" and num_players > 1
            and not options.feedforward_regularization):
        raise ValueError(
            "adaptive_regularization is for open-loop games and one-player problems (ilqgame-ol, "
            "ilqr): in a feedback game the gains, and with them the equilibrium, depend on the "
            "adapted control_regularization; add feedforward_regularization=true to damp the "
            "feed-forward terms only"
        )


def resolve_options(options: SolverOptions | None, overrides: dict) -> SolverOptions:
    """``options`` (the defaults for None) with ``overrides`` (field name -> value) applied,
    as :func:`solve` resolves its keyword overrides. Raises TypeError for unknown names."""
    if options is None:
        options = SolverOptions()
    if overrides:
        unknown = set(overrides) - {f.name for f in dataclasses.fields(SolverOptions)}
        if unknown:
            raise TypeError(f"unknown solver options: {sorted(unknown)}")
        options = dataclasses.replace(options, **overrides)
    return options


def _as_array(a):
    """NumPy inputs stay NumPy (the jitted solver takes them as they are, without a
    separate dispatch); JAX arrays and tracers are kept."""
    return a if isinstance(a, (jax.Array, jax.core.Tracer)) else np.asarray(a)


def _initial_inputs(problem: GameProblem, init, dtype):
    """The ``(T, N, m)`` inputs of ``init``; zeros (a NumPy array) for ``None``.

    Zeros are passed like any other initial guess, so cold and warm-started solves share
    one compiled solver (a receding-horizon agent's first re-plan is cold, the next ones
    warm: two variants would compile again at the second step).
    """
    shape = (problem.horizon, problem.num_players, problem.input_dim)
    if init is None:
        return np.zeros(shape, dtype)
    us = _as_array(getattr(init, "us", init))  # a SolverResult / ILQRResult or an array
    if us.shape != shape:
        raise ValueError(f"initial inputs must have shape (T, N, m) = {shape}, got {us.shape}")
    return us


def solve(
    problem_or_game,
    x0,
    init=None,
    *,
    options: SolverOptions | None = None,
    validate: bool = True,
    **overrides,
) -> SolverResult:
    """Solve a game by iterative LQ games (feedback or open-loop Nash), or iLQR for ``N = 1``.

    Args:
        problem_or_game: a :class:`GameProblem` or a :class:`racing_env.RaceGame`.
        x0: initial state, ``(n,)`` (GameProblem) or ``(N, 6)`` (RaceGame).
        init: initial inputs: ``None`` (zeros), an array ``(T, N, m)`` (warm start), or a
            previous result (its ``us``, e.g. open loop started from a feedback solution).
        options: a :class:`SolverOptions`; keyword ``overrides`` replace its fields
            (e.g. ``mode="open_loop"``, ``max_iterations=50``).
        validate: refuse non-PD ``R^{ii}`` with a ValueError (skipped when traced).

    Returns:
        :class:`SolverResult`. For a RaceGame, ``xs`` has shape ``(T+1, N, 6)``.

    Works under ``jax.vmap``/``jax.jit`` (validation then only happens on concrete inputs).
    """
    options = resolve_options(options, overrides)
    problem, is_game = _as_problem(problem_or_game)
    _convexify(problem, options)  # a clear error for an unusable convexification
    check_adaptive_regularization(options, problem.num_players)
    x0 = _as_array(x0)
    if not jnp.issubdtype(x0.dtype, jnp.floating):
        x0 = x0.astype(jnp.result_type(float))
    if x0.size != problem.state_dim:
        raise ValueError(
            f"x0 must have {problem.state_dim} entries"
            + (f" (shape ({problem.num_players}, 6))" if is_game else "")
            + f", got shape {x0.shape}"
        )
    if not is_game:
        x0 = x0.reshape(-1)
    us0 = _initial_inputs(problem, init, x0.dtype)
    if validate:
        if is_game:
            validate_problem(problem_or_game, control_regularization=options.guaranteed_control_regularization)
        else:
            validate_problem(problem, x0, us0, options.guaranteed_control_regularization)
    return _solve_jit(problem, x0, us0, options)


_BATCHING = ("auto", "map", "vmap")


def _resolve_batching(batching: str, devices) -> str:
    """``"auto"`` resolved for these devices: ``"map"`` if all are CPUs, else ``"vmap"``."""
    if batching != "auto":
        return batching
    return "map" if all(d.platform == "cpu" for d in devices) else "vmap"


def solve_batch(
    problem_or_game,
    x0s,
    init=None,
    *,
    params_axes=None,
    devices=None,
    batching: str = "auto",
    regroup_every: int | None = None,
    options: SolverOptions | None = None,
    validate: bool = True,
    **overrides,
) -> SolverResult:
    """:func:`solve` over a batch of initial states ``x0s (B, ...)``.

    ``init``: ``None``, inputs shared by the batch ``(T, N, m)``, or batched ``(B, T, N, m)``
    (or a batched result). ``params_axes``: vmap axes of the problem's ``params`` (a pytree
    prefix, e.g. a RaceGame whose ``weights`` leaves are batched: build the game with
    stacked weights and pass ``params_axes=game.replace(track=None, vehicles=None, racing=None,
    weights=0)``); ``None`` shares the params. The result has a leading batch axis.

    ``devices``: the batch is split evenly across these devices and the parts run in
    parallel, each part stopping when its own members are done; the default is every
    local device of JAX's default backend. On CPU that is one device
    unless :func:`planners.devices.use_cpu_cores` was called. Every member's result is the
    same either way. Compiled once per shapes, :class:`SolverOptions`, ``params_axes``,
    devices and ``batching``.

    ``batching``: how a device solves its part. ``"vmap"``: all members at once, in lock
    step (the vectorised form an accelerator wants). ``"map"``: one member after another,
    each a whole single solve that stops at its own convergence (a ``lax.map`` of the
    solver, which XLA:CPU compiles like a single solve). ``"auto"`` (default): ``"map"`` on
    CPU devices, where it was 1.7-2.3x faster than ``"vmap"`` for a batch of 64 paper
    scenes (README, Benchmarks), ``"vmap"`` on any other platform.

    ``regroup_every`` (for ``batching="vmap"``): a vmapped solve computes every member until
    the slowest one is done, so one member that needs ``max_iterations`` makes the whole
    batch pay for them. With
    ``regroup_every=k`` the batch runs ``k`` iterations at a time and, in between, only the
    members still running go on, gathered into a smaller batch (sizes are powers of two
    times the device count, and every new size compiles once). Each member's result is the
    same as without regrouping. Worth it when a few members run much longer than the rest
    and the process solves many batches (or the compilation cache is on). With ``"map"``
    no member waits for another, and ``regroup_every`` is ignored.
    """
    if batching not in _BATCHING:
        raise ValueError(f"batching must be one of {_BATCHING}, got {batching!r}")
    options = resolve_options(options, overrides)
    problem, is_game = _as_problem(problem_or_game)
    check_adaptive_regularization(options, problem.num_players)
    x0s = jnp.asarray(x0s)
    if not jnp.issubdtype(x0s.dtype, jnp.floating):
        x0s = x0s.astype(jnp.result_type(float))
    if x0s.ndim < 2 or x0s[0].size != problem.state_dim:
        raise ValueError(
            f"x0s must be a batch (B, ...) of initial states with {problem.state_dim} entries "
            f"each, got shape {x0s.shape}"
        )
    if regroup_every is not None and not (
        isinstance(regroup_every, (int, np.integer)) and not isinstance(regroup_every, bool) and regroup_every >= 1
    ):
        raise ValueError(f"regroup_every must be None or an integer >= 1, got {regroup_every!r}")
    shape = (problem.horizon, problem.num_players, problem.input_dim)
    us0 = jnp.zeros(shape, x0s.dtype) if init is None else jnp.asarray(getattr(init, "us", init))
    us_axis = None if us0.shape == shape else 0
    if us_axis == 0 and us0.shape != (x0s.shape[0],) + shape:
        raise ValueError(f"init must have shape {shape} or {(x0s.shape[0],) + shape}, got {us0.shape}")
    if validate and is_game and params_axes is None:
        validate_problem(problem_or_game, control_regularization=options.guaranteed_control_regularization)
    elif validate and params_axes is None:
        validate_problem(problem, x0s[0].reshape(-1), us0 if us_axis is None else us0[0],
                         options.guaranteed_control_regularization)

    from jax.sharding import Mesh

    mesh = Mesh(np.asarray(jax.local_devices() if devices is None else list(devices)), ("batch",))
    batching = _resolve_batching(batching, mesh.devices.flat)
    leaf_axes = _leaf_axes(params_axes, problem.params)
    if us_axis is None:
        us0 = jnp.broadcast_to(us0, (x0s.shape[0],) + shape)
    batch = (x0s.reshape(x0s.shape[0], -1), us0)
    if regroup_every is None or batching == "map":  # mapped members never wait: nothing to regroup
        result = _map_split("solve", problem, batch, leaf_axes=leaf_axes, options=options, mesh=mesh,
                            batching=batching)
    else:
        result = _solve_regrouped(problem, batch, leaf_axes, options, mesh, int(regroup_every))
    return result._replace(xs=result.xs.reshape(result.xs.shape[:2] + x0s.shape[1:]))


def _solve_regrouped(problem: GameProblem, batch, leaf_axes, options, mesh, every: int) -> SolverResult:
    """A vmapped :func:`solve_batch` in blocks of ``every`` iterations, each block on the
    members still running (see ``regroup_every``)."""
    run = functools.partial(_map_split, leaf_axes=leaf_axes, options=options, mesh=mesh, batching="vmap")
    carry = run("start", problem, batch)
    batch_size = int(carry.status.shape[0])
    while True:
        active = np.flatnonzero(np.asarray(carry.status) == RUNNING)
        if active.size == 0:
            break
        size = mesh.size * 2 ** int(np.ceil(np.log2(max(1.0, active.size / mesh.size))))
        size = min(size, batch_size + (-batch_size % mesh.size))
        # Padding repeats the last active member; its copies compute the same values, so
        # writing them all back is writing that member's result.
        rows = jnp.asarray(np.concatenate([active, np.repeat(active[-1:], size - active.size)]))
        part_problem, part = _gather_members(problem, carry, rows, leaf_axes)
        part = run("continue", part_problem, part, steps=every)
        carry = _write_members(carry, rows, part)
    return run("finish", problem, carry)


@functools.partial(jax.jit, static_argnames=("leaf_axes",))
def _gather_members(problem: GameProblem, carry: _Carry, rows: Array, leaf_axes):
    """The batch members ``rows`` of the solver states and of the batched params."""
    leaves, treedef = jax.tree_util.tree_flatten(problem.params)
    leaves = [leaf if axis is None else jnp.take(leaf, rows, axis=axis) for leaf, axis in zip(leaves, leaf_axes)]
    part = jax.tree_util.tree_map(lambda leaf: leaf[rows], carry)
    return problem.replace(params=jax.tree_util.tree_unflatten(treedef, leaves)), part


@jax.jit
def _write_members(carry: _Carry, rows: Array, part: _Carry) -> _Carry:
    """``carry`` with its members ``rows`` replaced by ``part``."""
    return jax.tree_util.tree_map(lambda whole, new: whole.at[rows].set(new), carry, part)


def _leaf_axes(params_axes, params) -> tuple:
    """The vmap axis (or None) of every leaf of ``params``, from the prefix ``params_axes``."""
    if params_axes is None:
        return (None,) * len(jax.tree_util.tree_leaves(params))
    axes, prefix = jax.tree_util.tree_flatten(params_axes, is_leaf=lambda a: a is None or isinstance(a, int))
    subtrees = prefix.flatten_up_to(params)  # the part of params each prefix axis covers
    return tuple(axis for axis, sub in zip(axes, subtrees) for _ in jax.tree_util.tree_leaves(sub))


def _member(kind: str, problem: GameProblem, args, options: SolverOptions, steps: int | None):
    """One batch member's share of a batched solve: ``kind`` is ``"solve"`` (``args`` =
    ``(x0, us0)``, returns a result), ``"start"`` (returns the initial solver state),
    ``"continue"`` (``args`` = a state; at most ``steps`` iterations) or ``"finish"``."""
    if kind == "solve":
        return _solve_jit(problem, *args, options)
    if kind == "start":
        return _initial_carry(problem, *args, options)
    if kind == "continue":
        return _iterate_while_running(problem, args, options, steps)
    return _result(problem, args, (args.xs.shape[-1],))


@functools.partial(jax.jit, static_argnames=("kind", "leaf_axes", "options", "mesh", "batching", "steps"))
def _map_split(kind: str, problem: GameProblem, batch, *, leaf_axes, options, mesh, batching, steps=None):
    """:func:`_member` over axis 0 of every leaf of ``batch`` (and over the params leaves
    whose ``leaf_axes`` entry is not None), with the batch split evenly across ``mesh``'s
    devices; on each device vmapped (``batching="vmap"``) or one member after another
    (``"map"``).

    The batch is padded to a multiple of the device count by repeating its last member;
    every device runs its part (``shard_map``: no communication, so each part's while loops
    end with its own members) and the padding is cut off again.
    """
    from jax.sharding import PartitionSpec

    leaves, treedef = jax.tree_util.tree_flatten(problem.params)
    size = jax.tree_util.tree_leaves(batch)[0].shape[0]
    pad = -size % mesh.size

    def padded(leaf, axis):
        if axis is None or pad == 0:
            return leaf
        last = jax.lax.slice_in_dim(leaf, leaf.shape[axis] - 1, leaf.shape[axis], axis=axis)
        return jnp.concatenate([leaf] + [last] * pad, axis=axis)

    def spec(leaf, axis):
        return PartitionSpec() if axis is None else PartitionSpec(*([None] * (axis % leaf.ndim)), "batch")

    batch_def = jax.tree_util.tree_structure(batch)

    def one(*flat):
        """One member from flat arrays: the params leaves, then the leaves of ``batch``."""
        p = problem.replace(params=jax.tree_util.tree_unflatten(treedef, flat[: len(leaves)]))
        return _member(kind, p, jax.tree_util.tree_unflatten(batch_def, flat[len(leaves):]), options, steps)

    # "map": under vmap, one_at_a_time runs the members one after another (a lax.map).
    member = one if batching == "vmap" else one_at_a_time(one)

    def part(leaves, batch):
        flat = (*leaves, *jax.tree_util.tree_leaves(batch))
        return jax.vmap(member, in_axes=(*leaf_axes, *[0] * batch_def.num_leaves))(*flat)

    leaves = [padded(leaf, axis) for leaf, axis in zip(leaves, leaf_axes)]
    batch = jax.tree_util.tree_map(lambda leaf: padded(leaf, 0), batch)
    in_specs = ([spec(leaf, axis) for leaf, axis in zip(leaves, leaf_axes)],
                jax.tree_util.tree_map(lambda leaf: spec(leaf, 0), batch))
    # check_vma=False: the solver's loop carries start as constants and become per-device.
    result = jax.shard_map(part, mesh=mesh, in_specs=in_specs, out_specs=PartitionSpec("batch"),
                           check_vma=False)(leaves, batch)
    return jax.tree_util.tree_map(lambda leaf: leaf[:size], result) if pad else result


def _costs_of_inputs(problem: GameProblem, x0: Array) -> Callable[[Array], Array]:
    """``us (T, N, m) -> (N,)`` every player's total cost of the rollout from ``x0``."""
    return lambda us: total_costs(problem, rollout(problem, x0, us), us)


@jax.jit
def _nash_residual_problem(problem: GameProblem, x0: Array, us: Array) -> Array:
    return _own_gradient_norms(jax.jacrev(_costs_of_inputs(problem, x0))(us))


@jax.jit
def _nash_residual_game(game, x0: Array, us: Array) -> Array:
    def J(U):
        return game.costs(game.rollout(x0, U), U)

    return _own_gradient_norms(jax.jacrev(J)(us))


def _own_gradients(G: Array) -> Array:
    """``G (N, T, N, m)`` = dJ^i/du^j -> ``(N, T, m)``, every player's dJ^i/du^i."""
    idx = jnp.arange(G.shape[0])
    return G[idx, :, idx, :]


def _own_gradient_norms(G: Array) -> Array:
    """``G (N, T, N, m)`` = dJ^i/du^j -> ``(N,)`` norms of dJ^i/du^i."""
    return jnp.sqrt(jnp.sum(_own_gradients(G) ** 2, axis=(1, 2)))


def nash_residual(problem_or_game, x0, us) -> Array:
    """First-order open-loop Nash residual: ``|| dJ^i / du^i ||_2`` for every player, ``(N,)``.

    ``J^i(u)`` is player i's total cost of the trajectory simulated from ``x0`` with the
    joint inputs ``us (T, N, m)``; the gradient w.r.t. its own input sequence is taken with
    ``jax.grad`` (reverse mode) through the rollout. For a RaceGame this goes through
    ``RaceGame.rollout`` and ``RaceGame.costs`` (``x0 (N, 6)``). It vanishes at an open-loop
    Nash equilibrium (and at its iLQ fixed point); a feedback equilibrium generally does not
    satisfy it when the players interact.
    """
    us = jnp.asarray(getattr(us, "us", us))
    if _is_race_game(problem_or_game):
        return _nash_residual_game(problem_or_game, jnp.asarray(x0, us.dtype), us)
    problem, _ = _as_problem(problem_or_game)
    return _nash_residual_problem(problem, jnp.asarray(x0, us.dtype).reshape(-1), us)
