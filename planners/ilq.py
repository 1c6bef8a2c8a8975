"""Iterative linear-quadratic (iLQ) game solver: feedback and open-loop iLQGames, and iLQR.

The contract
------------
:func:`solve` takes a :class:`~planners.game_problem.GameProblem` (re-exported here), or a
game type registered with :func:`planners.game_problem.register_game_type` (a
:class:`racing_env.RaceGame`, via :mod:`planners.race_problem`), an initial state ``x0``
and optionally initial inputs ``(T, N, m)``, and returns a :class:`SolverResult`: the
trajectory ``xs (T+1, n)`` (in the game's own state shape for a registered game, e.g.
``(T+1, N, 6)``), the inputs ``us (T, N, m)``, the strategies ``K, k`` of the last local
game, every player's total cost, a status code and the per-iteration histories. A problem
is::

    dynamics(params, t, x, u) -> x_next        x (n,), u (N, m), t int stage index
    stage_cost(params, t, i, x, u_i) -> scalar  player i's g_t^i; depends on its own input only
    terminal_cost(params, i, x) -> scalar       player i's g_T^i

with static ``N, n, m, T`` and optional hooks (Gauss-Newton residuals, a curvature the
linearised dynamics drop, dynamics Jacobians). :class:`SolverOptions` holds the
configuration: its structural fields (mode, iteration cap, step rule, flags) are static, so
each structure compiles once per shapes and problem functions; its numbers (tolerance,
trust radius, step sizes, regularisation, :class:`SolverNumbers`) are traced arguments, so
configurations that differ only in them, new ``params`` and new initial states re-use the
compiled solver. Everything
inside :func:`solve` is one jitted function (``lax.while_loop`` over iterations,
``lax.scan`` for the recursions and rollouts, ``vmap`` over the horizon for derivatives);
it can be vmapped over initial states and ``params``. Batches: :mod:`planners.ilq_batch`;
Nash checks: :mod:`planners.nash`.

Failures are reported, never returned as NaN: a non-finite LQ solution stops the solve
with status ``NON_FINITE`` and the last finite iterate; a failed step-size search stops with
``LINE_SEARCH_FAILED``; the iteration cap gives ``MAX_ITERATIONS``. ``converged`` is True
only with status ``CONVERGED``.

One solver serves three planners of the paper (``reference/ilqgame-racing-paper.tex``,
Algorithm 1): feedback iLQGame (``mode="feedback"``, each iteration solves the feedback
Nash equilibrium of the local LQ game, :mod:`planners.lq_game`), open-loop iLQGame
(``mode="open_loop"``) and iLQR (``N = 1``, :mod:`planners.ilqr`); and, beyond the paper,
two-player leader-follower games (``mode="stackelberg"``: the local games' feedback
Stackelberg solutions, :mod:`planners.lq_stackelberg`; certificate:
:mod:`planners.stackelberg`).

One iteration (:func:`iterate`)
-------------------------------
Around the nominal trajectory ``(x_hat, u_hat)``:

1. :func:`~planners.local_game.linearize` the dynamics (``jax.jacfwd`` vmapped over the horizon, or the
   problem's ``dynamics_jacobians``): ``dx_{t+1} = A_t dx_t + sum_j B_t^j du_t^j``;
2. :func:`~planners.local_game.quadratize` each player's cost: ``Q_t^i, q_t^i`` (state) and ``R_t^{ii}, r_t^{ii}``
   (own input). Mixed state-input terms and ``R^{ij}, r^{ij}`` for ``i != j`` are zero (the
   paper's cost structure; dropped if a custom cost has them). The gradients ``q, r`` are
   always exact. The curvature, ``convexify``:

   * ``"gauss_newton"`` (the default where the problem has the hooks, as every RaceGame
     does): the problem writes player i's stage cost as ``sum_k rho_k(r_k(x, u_i))`` and
     returns ``r_k``, ``rho_k'`` and a curvature weight ``h_k >= 0``; then
     ``[Q, .; ., R] = J' diag(h) J`` and ``[q; r] = J' rho'`` with ``J = d r / d[x, u_i]``,
     one forward-mode pass, PSD by construction, no eigendecomposition;
   * ``"eig"`` (the default otherwise): exact Hessians, every ``Q_t^i`` projected onto the
     PSD cone; ``"diag"`` makes it diagonally dominant instead; ``"none"`` keeps the exact
     Hessian.

   With ``dynamics_curvature`` the problem's ``stage_curvature`` is added to the diagonal
   of each ``Q_t^i``: curvature of the true problem that the linearised dynamics drop;
3. :func:`regularize`: ``Q_t^i += state_regularization * I``,
   ``R_t^{ii} += lambda_u * I`` (fixed, or adapted per iteration with
   ``adaptive_regularization``; in feedback games ``feedforward_regularization`` puts
   ``lambda_u`` on the feed-forward terms only). Convexifying keeps every player's local
   problem convex, so each LQ solution is an equilibrium of the local game rather than a
   saddle point. It does not move open-loop fixed points (they depend on gradients
   only); it does change feedback ones (``K`` depends on ``Q``);
4. solve the LQ game in deviation coordinates. Feedback: ``du = -K dx - k``
   (:func:`~planners.lq_game.solve_feedback_own`, or the general pivoting
   :func:`~planners.lq_game.solve_feedback` with ``convexify="none"``); Stackelberg: the same
   form from :func:`~planners.lq_stackelberg.solve_feedback_stackelberg`. Open loop: the
   local game starts at ``dx_0 = 0``, so :func:`~planners.lq_game.solve_open_loop_own`
   with a zero initial deviation gives the whole update ``du_t = -k_t`` and ``K = 0``;
   then ``eta * k`` is exactly the equilibrium of the local game with its linear terms
   scaled by ``eta``;
5. :func:`forward` pass on the nonlinear dynamics from ``x_0``::

       u_t = u_hat_t - K_t (x_t - x_hat_t) - eta k_t,   x_{t+1} = f_t(x_t, u_t).

Step-size control
-----------------
``step_control="trust_region"`` (the default), as in the ilqgames reference
implementation (Fridovich-Keil et al., ICRA 2020): multiply ``eta`` by ``step_decay``
until ``max_t |x_new_t - x_hat_t|_inf <= trust_radius`` and the rollout is finite; give up
after ``max_backtracks`` reductions (``LINE_SEARCH_FAILED``). With
``oscillation_damping``, a step whose state change points against a decaying sum of the
previous unit steps (memory ``damping_memory``) is an overshoot, and the next iteration
starts at ``eta * step_decay``; otherwise at ``initial_step``. Both checks are
player-neutral: a game has no single merit function that every player's update
decreases, so there is no Armijo rule on costs. With ``player_steps`` each player has its
own ``eta_i``, cut by the trust region on its own states (games whose state stacks the
players' states): a player whose plan needs a long step no longer shortens the others'.

``step_control="residual"`` (open loop only) backtracks on the squared first-order Nash
residual ``sum_i |dJ^i/du^i|^2`` with sufficient decrease ``1 - 2e-4 eta``; when no trial
decreases it, the first trial inside the trust region is taken. ``step_control="none"``
applies a fixed ``eta = initial_step`` (the paper's plain update).

Convergence: the state change of a full step (``max_t |x_new_t - x_hat_t|_inf`` scaled by
``initial_step / eta``), less the rounding of the trajectory at its scale
(:func:`planners.precision.rounding_floor`: ~4e-13 m in float64, 2.2e-4 m in float32 at
positions near 230 m, ``precision="float32"``), is at most ``tolerance`` and the step was not
shortened by the trust region. At a fixed point ``k = 0``: for ``mode="open_loop"`` exactly the first-order
open-loop Nash condition of the nonlinear game (:func:`planners.nash.nash_residual`), for
``mode="feedback"`` the feedback condition of the sequence of local LQ games.

Anytime solves: ``budget_ms`` (:func:`solve_within`) stops the iterations when a wall-clock
budget has run out (``BUDGET_EXHAUSTED``); with ``best_iterate`` a solve that stops before
converging returns its iterate of smallest merit ``max |k_0|`` (:func:`finish`), the warm
start included.

Building blocks: a solve is :func:`initial_carry`, :func:`iterate` in a ``while_loop``
(:func:`iterate_while_running`), :func:`finish` and :func:`result`; :func:`solve_arrays` is that whole
computation jitted, without validation. The design discussion (why Gauss-Newton, the
progress curvature, the step-size rules) is in docs/solvers.md.
"""

from __future__ import annotations

import dataclasses
import functools
import importlib
import math
import time
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from planners import local_game, lq_game, lq_stackelberg, methods, nash, precision as precisions
from planners.game_problem import GameProblem, as_problem, game_type_of, is_concrete, rollout, total_costs
from planners.precision import require_precision

Array = jax.Array

__all__ = [
    "BUDGET_EXHAUSTED",
    "BestIterate",
    "CONVERGED",
    "GameProblem",
    "LINE_SEARCH_FAILED",
    "MAX_ITERATIONS",
    "NON_FINITE",
    "RUNNING",
    "SolverCarry",
    "SolverNumbers",
    "SolverOptions",
    "SolverResult",
    "as_array",
    "at_precision",
    "check_adaptive_regularization",
    "check_budget_ms",
    "check_players",
    "finish",
    "forward",
    "initial_carry",
    "iterate",
    "iterate_while_running",
    "jit_arguments",
    "local_lq_game",
    "regularize",
    "resolve_options",
    "result",
    "rollout",
    "solve",
    "solve_arrays",
    "solve_within",
    "solver_dtype",
    "status_message",
    "total_costs",
    "validate_problem",
]

# Compatibility aliases for scripts written against planners.ilq: names that live in the
# modules built on this one (the package itself imports them from their modules).
_MOVED = {
    "solve_batch": "planners.ilq_batch",
    "nash_residual": "planners.nash",
    "problem_from_race_game": "planners.race_problem",
}


def __getattr__(name: str) -> Any:
    if name in _MOVED:
        return getattr(importlib.import_module(_MOVED[name]), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


# Status codes of a solve (SolverResult.status).
RUNNING = -1  # internal only: never returned
CONVERGED = 0
MAX_ITERATIONS = 1
NON_FINITE = 2
LINE_SEARCH_FAILED = 3
BUDGET_EXHAUSTED = 4

_STATUS_MESSAGES = {
    CONVERGED: "converged",
    MAX_ITERATIONS: "iteration cap reached before convergence",
    NON_FINITE: "non-finite LQ solution or trajectory; stopped at the last finite iterate",
    LINE_SEARCH_FAILED: "step-size control found no step inside the trust region",
    BUDGET_EXHAUSTED: "wall-clock budget ran out before convergence",
}


def status_message(status) -> str:
    """Human-readable meaning of a ``SolverResult.status`` code."""
    return _STATUS_MESSAGES.get(int(status), f"unknown status {int(status)}")


# --------------------------------------------------------------------------------------
# Options and result.
# --------------------------------------------------------------------------------------

_STEP_CONTROLS = ("trust_region", "residual", "none")
_CONVEXIFY = ("auto", "gauss_newton", "eig", "diag", "none")


class SolverNumbers(NamedTuple):
    """The numeric fields of :class:`SolverOptions` (see there for their meaning and units),
    a pytree of scalars: the jitted solvers take them as traced arguments, so that options
    which differ only in these numbers share one compiled solver. Python scalars in
    :meth:`SolverOptions.split` of concrete options; weakly typed JAX scalars on their way
    into a jitted solver (:func:`jit_arguments`; weak, as Python numbers are, so that they
    take the dtype of the arrays they meet, like the constants they replace); traced
    scalars inside it."""

    tolerance: Any
    trust_radius: Any
    initial_step: Any
    step_decay: Any
    max_backtracks: Any
    damping_memory: Any
    state_regularization: Any
    control_regularization: Any
    regularization_factor: Any


@dataclasses.dataclass(frozen=True)
class SolverOptions:
    """Configuration of :func:`solve`.

    The structural fields (``mode``, ``max_iterations``, which sizes the histories,
    ``step_control``, ``convexify`` and the flags) are static: a new combination compiles a
    new solver. The numbers (:class:`SolverNumbers`: ``tolerance``, ``trust_radius``,
    ``initial_step``, ``step_decay``, ``max_backtracks``, ``damping_memory``, the
    regularisations and ``regularization_factor``) are traced: options that differ only in
    them run the same compiled solver (:meth:`split`).

    Attributes:
        mode: ``"feedback"`` or ``"open_loop"`` Nash equilibrium of the local LQ games, or
            ``"stackelberg"``: their feedback Stackelberg solution (two players only,
            :func:`~planners.lq_stackelberg.solve_feedback_stackelberg`), player ``leader``
            leading.
        leader: the leading player's index (0 or 1) in ``mode="stackelberg"``; ignored
            otherwise.
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
        best_iterate: anytime solves: when the solve stops before convergence (the iteration
            cap or a wall-clock budget), return the iterate with the smallest merit instead of
            the last one. The merit of an iterate is ``max |k_0|``, the largest change of the
            first stage's inputs that the LQ game around it asks for (0 at a fixed point). The
            initial iterate (the warm start) is a candidate, so the result is never worse by
            this merit than the warm start; the last iterate is scored by one more LQ solve,
            whose gains ``K`` are then returned with it. See :func:`finish`.
        dynamics_curvature: add the problem's ``stage_curvature`` (see :class:`GameProblem`;
            RaceGame and iLQR: each car's progress in its heading) to the diagonal of every
            stage's ``Q^i``, in every ``convexify`` mode (before the PSD projection). The
            gradients, and so the open-loop fixed points, do not change; the feedback gains
            do (they follow ``Q``). No effect on problems without the hook.
        player_steps: one step size per player instead of one for all (trust-region rule
            only): player ``i``'s feed-forward term is scaled by its own ``eta_i``, which
            shrinks until the step changes player ``i``'s own states by at most
            ``trust_radius``. For games whose state stacks the players' states, ``n = N n_i``
            (player ``i``'s rows ``[i n_i, (i + 1) n_i)``; every RaceGame), refused for
            others when the solver is traced. With one ``eta`` a player whose own plan
            needs a long step (a car far off the track, whose boundary cost asks for
            hundreds of metres) cuts every player's step to a few percent; a real-time
            re-plan of a few iterations then barely moves the others' plans. The fixed
            points are the same (``k = 0``); a step counts toward convergence only when no
            player's ``eta`` was cut.
        precision: ``"float64"`` (the default: the certificates and the paper's figures) or
            ``"float32"``: the solve's arithmetic, whatever ``jax_enable_x64`` says (the
            problem's parameters, the initial state and inputs are cast inside the jitted
            solver; the result is in that dtype). Both test convergence with the
            trajectory's rounding allowed for (:func:`planners.precision.rounding_floor`),
            and float32 refuses a ``tolerance`` below its resolution (1.19e-7).
    """

    mode: str = methods.FEEDBACK
    leader: int = 0
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
    best_iterate: bool = False
    player_steps: bool = False
    precision: str = precisions.PRECISIONS[0]

    def split(self) -> tuple["SolverOptions", SolverNumbers]:
        """``(structure, numbers)``: ``structure`` is these options with every numeric field
        ``None`` (hashable; the static argument of the jitted solvers, equal for options that
        differ only in numbers), ``numbers`` the numeric fields (:class:`SolverNumbers`;
        concrete ones as Python ``float``, ``max_backtracks`` as ``int``, so that the
        compiled solver does not depend on their NumPy types; traced ones as they are).
        :meth:`with_numbers` puts them back together."""
        numbers = SolverNumbers(**{name: _plain_number(name, getattr(self, name)) for name in SolverNumbers._fields})
        return self._with_fields(dict.fromkeys(SolverNumbers._fields)), numbers

    def with_numbers(self, numbers: SolverNumbers) -> "SolverOptions":
        """These options with their numeric fields from ``numbers``: inside a jitted solver,
        the options whose numbers are its traced arguments. Not validated again (the numbers
        come from validated options through :meth:`split`, and traced ones cannot be)."""
        return self._with_fields(numbers._asdict())

    def _with_fields(self, values: dict) -> "SolverOptions":
        new = object.__new__(SolverOptions)
        for field in dataclasses.fields(SolverOptions):
            object.__setattr__(new, field.name, values.get(field.name, getattr(self, field.name)))
        return new

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
                     "dynamics_curvature", "best_iterate", "player_steps"):
            # a string such as "false" would be truthy
            if not isinstance(getattr(self, name), (bool, np.bool_)):
                raise ValueError(f"SolverOptions.{name} must be True or False, got {getattr(self, name)!r}")
        if self.mode not in methods.SOLVER_MODES:
            raise ValueError(f"mode must be one of {methods.SOLVER_MODES}, got {self.mode!r}")
        if isinstance(self.leader, (bool, np.bool_)) or self.leader not in lq_stackelberg.LEADERS:
            raise ValueError(f"SolverOptions.leader must be one of {lq_stackelberg.LEADERS} (the leading "
                             f"player's index, mode='stackelberg'), got {self.leader!r}")
        if self.step_control not in _STEP_CONTROLS:
            raise ValueError(
                f"step_control must be one of {_STEP_CONTROLS}, got {self.step_control!r}"
            )
        if self.step_control == "residual" and self.mode != methods.OPEN_LOOP:
            raise ValueError(
                "step_control='residual' needs mode='open_loop' (of the agents, ilqgame-ol): it "
                "decreases the open-loop Nash residual, which a feedback equilibrium does not zero"
            )
        if self.player_steps and self.step_control != "trust_region":
            raise ValueError(
                "player_steps needs step_control='trust_region': each player's step size is cut by "
                f"the trust region on its own states, got step_control={self.step_control!r}"
            )
        if self.adaptive_regularization and not self.control_regularization > 0:
            raise ValueError(
                "adaptive_regularization needs control_regularization > 0 (the value it starts "
                f"at and returns to after a reversing step), got {self.control_regularization!r}"
            )
        if self.feedforward_regularization and self.mode != methods.FEEDBACK:
            raise ValueError(
                "feedforward_regularization is for feedback games: an open-loop LQ step is all "
                "feed-forward, and control_regularization alone damps it"
            )
        if self.feedforward_regularization and not self.control_regularization > 0:
            raise ValueError(
                "feedforward_regularization needs control_regularization > 0 (the lambda_u it "
                f"puts on the feed-forward terms), got {self.control_regularization!r}"
            )
        precisions.check_precision(self.precision)
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
        precisions.check_tolerance(self.precision, self.tolerance)


def _plain_number(name: str, value):
    """A concrete option number as a Python scalar (traced ones unchanged): ``max_backtracks``
    rounded down to an ``int`` (the trial counter is compared with it), the others ``float``."""
    if isinstance(value, jax.core.Tracer):
        return value
    return math.floor(value) if name == "max_backtracks" else float(value)


def jit_arguments(options: SolverOptions) -> tuple[SolverOptions, SolverNumbers]:
    """``options.split()`` for a call of a jitted solver: the static structure and the
    numbers, concrete numbers as weakly typed JAX scalars (what Python numbers become inside
    ``jit``). Made once per options and kept (a split and nine Python scalars, each a
    host-to-device transfer, would add tens of microseconds to every solve); options with
    traced numbers are split as they are."""
    if any(isinstance(getattr(options, name), jax.core.Tracer) for name in SolverNumbers._fields):
        return options.split()
    try:
        return _kept_jit_arguments(options, bool(jax.config.jax_enable_x64))
    except TypeError:  # unhashable numbers (JAX arrays): made for this call only
        return _concrete_jit_arguments(options)


def _concrete_jit_arguments(options: SolverOptions) -> tuple[SolverOptions, SolverNumbers]:
    """:func:`jit_arguments` of concrete options, the scalars made outside any trace."""
    structure, numbers = options.split()
    with jax.ensure_compile_time_eval():
        return structure, SolverNumbers(*(jnp.asarray(value) for value in numbers))


@functools.lru_cache(maxsize=256)
def _kept_jit_arguments(options: SolverOptions, x64: bool) -> tuple[SolverOptions, SolverNumbers]:
    """:func:`_concrete_jit_arguments`, kept per options and JAX's 64-bit mode ``x64`` (the
    scalars' width depends on it)."""
    del x64
    return _concrete_jit_arguments(options)


class SolverResult(NamedTuple):
    """Outcome of :func:`solve` (a pytree; batched along a leading axis by :func:`planners.ilq_batch.solve_batch`).

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


def regularize(Q: Array, Rii: Array, options: SolverOptions, convexify: str,
               control_regularization: Array | float | None = None) -> tuple[Array, Array]:
    """``Q (..., n, n)`` made PSD per ``convexify`` (a resolved mode: ``"gauss_newton"``,
    ``"eig"``, ``"diag"`` or ``"none"``) plus ``options.state_regularization``, and ``Rii``
    plus ``lambda_u``: ``control_regularization``, the current one (the solver state's,
    adapted or not; default: the options')."""
    # Gauss-Newton Q is PSD by construction (and symmetrised by the LQ solvers).
    if convexify != "gauss_newton":
        Q = 0.5 * (Q + jnp.swapaxes(Q, -1, -2))
    if convexify == "eig":
        Q = local_game.psd_part(Q)
    elif convexify == "diag":
        diag = jnp.diagonal(Q, axis1=-2, axis2=-1)
        off = jnp.sum(jnp.abs(Q), axis=-1) - jnp.abs(diag)
        Q = Q + jnp.eye(Q.shape[-1], dtype=Q.dtype) * jnp.maximum(off - diag, 0.0)[..., None]
    # Added also where they are 0 (exact: x + 0 = x): the numbers are traced, and options
    # that differ only in them share one compiled solver.
    Q = Q + options.state_regularization * jnp.eye(Q.shape[-1], dtype=Q.dtype)
    # feedforward_regularization: lambda_u enters the feedback LQ solve instead (the gains
    # stay those of the local game).
    if not options.feedforward_regularization:
        lam = options.control_regularization if control_regularization is None else control_regularization
        Rii = Rii + lam * jnp.eye(Rii.shape[-1], dtype=Rii.dtype)
    return Q, Rii


def local_lq_game(problem: GameProblem, xs: Array, us: Array, options: SolverOptions,
                  control_regularization: Array | float | None = None):
    """The local LQ game an iteration solves around ``xs (T+1, n)``, ``us (T, N, m)``:
    ``A, B, Q, q, Rii, rii`` (own-input weights, :func:`planners.lq_game.solve_feedback_own`'s
    arrays), linearised, quadratised per ``options.convexify`` and ``dynamics_curvature``,
    and regularised (:func:`regularize`; ``control_regularization``: the current
    ``lambda_u``, default the options')."""
    convexify = _convexify(problem, options)
    A, B = local_game.linearize(problem, xs, us)
    Q, q, Rii, rii = local_game.quadratize(problem, xs, us, convexify == "gauss_newton",
                                 options.dynamics_curvature)
    Q, Rii = regularize(Q, Rii, options, convexify, control_regularization)
    return A, B, Q, q, Rii, rii


def _lq_step(problem: GameProblem, xs: Array, us: Array, options: SolverOptions,
             control_regularization: Array | float):
    """Linearise, quadratise and solve the local LQ game: ``K (T, N, m, n)``, ``k (T, N, m)``
    (``control_regularization``: the current ``lambda_u``, see :func:`regularize`)."""
    convexify = _convexify(problem, options)
    A, B, Q, q, Rii, rii = local_lq_game(problem, xs, us, options, control_regularization)
    lam_k = control_regularization if options.feedforward_regularization else None
    if options.mode == methods.FEEDBACK and convexify != "none":
        # Every Q^i is PSD: the own-input solver's block elimination is safe.
        K, k = lq_game.solve_feedback_own(A, B, Q, q, Rii, rii, lam_k)
    elif options.mode == methods.FEEDBACK:
        K, k = lq_game.solve_feedback(A, B, Q, q, *local_game.own_to_full(Rii, rii), lam_k)
    elif options.mode == methods.STACKELBERG:
        check_players(options, problem.num_players)
        K, k = lq_stackelberg.solve_feedback_stackelberg(A, B, Q, q, *local_game.own_to_full(Rii, rii),
                                                         leader=int(options.leader))
    else:
        # Deviation coordinates: the local game starts at dx_0 = 0, not at x_0.
        k, _ = lq_game.solve_open_loop_own(A, B, Q, q, Rii, rii, jnp.zeros_like(xs[0]))
        K = jnp.zeros(k.shape + (xs.shape[-1],), k.dtype)
    return K, k


def forward(problem: GameProblem, xs_hat: Array, us_hat: Array, K: Array, k: Array,
            eta: Array | float) -> tuple[Array, Array]:
    """Nonlinear forward pass from ``xs_hat[0]`` with the strategies of a local game.

    ``u_t = u_hat_t - K_t (x_t - x_hat_t) - eta k_t``, ``x_{t+1} = f_t(x_t, u_t)`` with the
    nominal ``xs_hat (T+1, n)``, ``us_hat (T, N, m)``, gains ``K (T, N, m, n)`` and
    feed-forward terms ``k (T, N, m)``; ``eta`` a scalar, or ``(N, 1)`` for a step size per
    player (``SolverOptions.player_steps``). Returns the new ``xs (T+1, n)``, ``us (T, N, m)``.
    """
    params = problem.params

    def body(x, inp):
        t, x_hat, u_hat, K_t, k_t = inp
        # K_t (x - x_hat) as a fused multiply-sum: a dot is a separate XLA:CPU call.
        u = u_hat - jnp.sum(K_t * (x - x_hat), axis=-1) - eta * k_t
        return problem.dynamics(params, t, x, u), (x, u)

    ts = jnp.arange(us_hat.shape[0])
    # Not unrolled (nor are the other solver loops): compiled into one kernel, an unrolled
    # loop ran no faster and compiled for longer (docs/performance.md, "XLA settings and dispatch").
    xT, (xs, us) = jax.lax.scan(body, xs_hat[0], (ts, xs_hat[:-1], us_hat, K, k))
    return jnp.concatenate([xs, xT[None]], axis=0), us


def _deviation(xs_new: Array, xs_hat: Array) -> Array:
    """Max-norm state change; ``inf`` for a non-finite trajectory."""
    d = jnp.max(jnp.abs(xs_new - xs_hat))
    return jnp.where(jnp.isfinite(d), d, jnp.inf)


def _merit(problem: GameProblem, x0: Array, us: Array) -> Array:
    """``sum_i |dJ^i/du^i|^2``, the squared open-loop Nash residual of ``us (T, N, m)`` from
    ``x0 (n,)`` (see :func:`planners.nash.nash_residual`); ``inf`` where it is not finite."""
    merit = jnp.sum(nash.own_gradients(jax.jacrev(nash.costs_of_inputs(problem, x0))(us)) ** 2)
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
        xs, us = forward(problem, xs_hat, us_hat, K, k, eta)
        dev = _deviation(xs, xs_hat)
        # A trial outside the trust region is refused whatever its residual. Its N reverse
        # passes are computed anyway: such trials are rare, and a lax.cond around them
        # makes the common case slower on CPU.
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
        xs, us = forward(problem, xs_hat, us_hat, K, k, eta0)
        dev = _deviation(xs, xs_hat)
        return xs, us, eta0, dev, jnp.isfinite(dev), merit0
    if options.step_control == "residual":
        return _residual_step(problem, xs_hat, us_hat, K, k, eta0, merit0, options)

    if options.player_steps:
        return _player_step(problem, xs_hat, us_hat, K, k, eta0, merit0, options)
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
        xs, us = forward(problem, xs_hat, us_hat, K, k, eta)
        return xs, us, eta, _deviation(xs, xs_hat), trial + 1

    start = (xs_hat, us_hat, eta0, jnp.asarray(jnp.inf, xs_hat.dtype), 0)
    xs, us, eta, dev, _ = jax.lax.while_loop(cond, body, start)
    return xs, us, eta, dev, dev <= radius, merit0


def _player_deviations(xs_new: Array, xs_hat: Array, num_players: int) -> Array:
    """Max-norm change of each player's own states, ``(N,)``, for a state ``(T+1, n)`` that
    stacks the players' states (``n = N n_i``); ``inf`` where it is not finite."""
    n = xs_hat.shape[-1]
    if n % num_players:
        raise ValueError(f"player_steps needs a state that stacks the players' states (n = N n_i); "
                         f"got n = {n} for N = {num_players} players")
    d = jnp.abs(xs_new - xs_hat).reshape(xs_hat.shape[:-1] + (num_players, n // num_players))
    d = jnp.max(d, axis=tuple(range(d.ndim - 2)) + (d.ndim - 1,))
    return jnp.where(jnp.isfinite(d), d, jnp.inf)


def _player_step(problem, xs_hat, us_hat, K, k, eta0, merit0, options: SolverOptions):
    """The trust-region search with one step size per player (``options.player_steps``):
    every ``eta_i`` starts at ``eta0``; after each trial the players whose own states moved
    by more than ``trust_radius`` have theirs multiplied by ``step_decay``, until no player's
    did (or ``max_backtracks`` trials). A player's rollout depends on the others' through
    its gains ``K``, so every trial rolls out all players again. Returns ``(xs, us, eta,
    deviation, ok, merit0)`` as :func:`_step` does, with ``eta`` the smallest ``eta_i`` and
    ``deviation`` the largest of ``deviation_i * eta / eta_i``, so that ``deviation *
    initial_step / eta`` is the largest full-step change of a player (the convergence
    measure of :func:`iterate`)."""
    radius = options.trust_radius
    N = problem.num_players
    etas0 = jnp.full((N,), eta0, xs_hat.dtype)

    def cond(c):
        _, _, _, dev, trial = c
        return (trial == 0) | (jnp.any(dev > radius) & (trial <= options.max_backtracks))

    def body(c):
        _, _, etas, dev, trial = c
        etas = jnp.where((trial > 0) & (dev > radius), etas * options.step_decay, etas)
        xs, us = forward(problem, xs_hat, us_hat, K, k, etas[:, None])
        return xs, us, etas, _player_deviations(xs, xs_hat, N), trial + 1

    start = (xs_hat, us_hat, etas0, jnp.full((N,), jnp.inf, xs_hat.dtype), 0)
    xs, us, etas, dev, _ = jax.lax.while_loop(cond, body, start)
    eta = jnp.min(etas)
    scaled = jnp.max(dev * (eta / etas))
    return xs, us, eta, jnp.where(jnp.isfinite(scaled), scaled, jnp.inf), jnp.all(dev <= radius), merit0


class BestIterate(NamedTuple):
    """The best-scored iterate of an anytime solve (``SolverOptions.best_iterate``): its
    ``xs (T+1, n)``, ``us (T, N, m)``, the LQ game around it (``K (T, N, m, n)``,
    ``k (T, N, m)``) and its ``merit`` (``max |k_0|``; ``inf`` before any iterate was
    scored)."""

    xs: Array
    us: Array
    K: Array
    k: Array
    merit: Array


class SolverCarry(NamedTuple):
    """The solver's state between iterations (a pytree; the ``while_loop`` carry).

    ``it`` accepted steps so far; ``xs (T+1, n)``, ``us (T, N, m)`` the current iterate;
    ``K``, ``k``, ``eta`` of the last accepted step; ``status`` (``RUNNING`` while the
    iteration goes on) and the per-iteration histories of :class:`SolverResult`; ``best``
    the best-scored iterate so far (:class:`BestIterate`) with ``best_iterate``, else None.
    """

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
    best: BestIterate | None = None


def solver_dtype(options: SolverOptions, x0: Array, us0: Array):
    """The dtype a solve computes in: float32 for ``precision="float32"``; for float64 the
    widest float of ``x0``, ``us0`` and JAX's default (float64 with ``jax_enable_x64``)."""
    if options.precision == "float32":
        return jnp.float32
    return jnp.result_type(x0.dtype, us0.dtype, float)


def at_precision(problem: GameProblem, options: SolverOptions) -> GameProblem:
    """``problem`` with its floating-point parameters in the solve's dtype
    (``options.precision="float32"``: cast to float32, inside the jitted solvers, so that no
    operation of an iteration is promoted to float64); unchanged for float64."""
    if options.precision == "float32":
        return precisions.cast_floating(problem, jnp.float32)
    return problem


def initial_carry(problem: GameProblem, x0: Array, us0: Array, options: SolverOptions) -> SolverCarry:
    """The solver state before the first iteration: ``x0 (n,)``, ``us0 (T, N, m)`` (cast to
    the solve's dtype, :func:`solver_dtype`; ``problem`` in that precision,
    :func:`at_precision`)."""
    T, N, m = problem.horizon, problem.num_players, problem.input_dim
    dtype = solver_dtype(options, x0, us0)
    x0 = x0.reshape(-1).astype(dtype)
    us0 = us0.astype(dtype)
    xs0 = rollout(problem, x0, us0)
    nan_hist = jnp.full((options.max_iterations,), jnp.nan, dtype)
    return SolverCarry(
        it=jnp.zeros((), int),  # not weakly typed: the same type as after an iteration
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
        best=BestIterate(xs0, us0, jnp.zeros((T, N, m, x0.shape[0]), dtype), jnp.zeros((T, N, m), dtype),
                         jnp.asarray(jnp.inf, dtype)) if options.best_iterate else None,
    )


def iterate(problem: GameProblem, c: SolverCarry, options: SolverOptions) -> SolverCarry:
    """One iteration: the local LQ game around ``(c.xs, c.us)`` (:mod:`planners.local_game`,
    :func:`regularize`, an LQ solve), the step-size search over
    :func:`forward` passes, and the status update. Pure JAX, jit-able."""
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
        unit = step / jnp.maximum(jnp.sqrt(jnp.vdot(step, step)), jnp.finfo(dtype).tiny)
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
    # Convergence: the full step within the tolerance plus the rounding of the trajectory
    # at its scale (planners.precision.rounding_floor; tolerance 0 keeps its meaning, "run
    # every iteration"). The rounding is ~4e-13 m in float64; in float32 a fixed point's
    # rollouts differ by it (float32 spacing of speeds near 20 m/s: 1.9e-6), which a plain
    # max-norm test at 1e-6 would never pass.
    floor = jnp.where(options.tolerance > 0, precisions.rounding_floor(c.xs), 0.0)
    small = jnp.maximum(dev - floor, 0.0) * (options.initial_step / eta) <= options.tolerance
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
    best = c.best
    if best is not None:
        # (K, k) is the LQ game around the iterate this step started from, c.(xs, us)
        merit = _action_merit(k)
        best = _select(lq_ok & (merit < best.merit), BestIterate(c.xs, c.us, K, k, merit), best)
    keep = functools.partial(_select, ok)
    return SolverCarry(
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
        best=best,
    )


def result(problem: GameProblem, c: SolverCarry, x_shape: tuple[int, ...]) -> SolverResult:
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


def _action_merit(k: Array) -> Array:
    """The merit of an iterate in an anytime solve: ``max |k_0|``, the largest change of the
    first stage's inputs that the LQ game around the iterate asks for (input units; 0 at a
    fixed point). The first inputs are the ones a receding-horizon planner executes."""
    merit = jnp.max(jnp.abs(k[0]))
    return jnp.where(jnp.isfinite(merit), merit, jnp.inf)


def finish(problem: GameProblem, c: SolverCarry, options: SolverOptions) -> SolverCarry:
    """The solver state to report: ``c`` itself, or with ``options.best_iterate`` and a
    solve stopped before convergence (``MAX_ITERATIONS`` or ``BUDGET_EXHAUSTED``), its best
    iterate (:class:`BestIterate`). The last iterate has no score yet: one more LQ solve
    around it gives it one, and it is kept (with the gains of that LQ game) when it scores
    at least as well as the best earlier iterate."""
    best = c.best
    if best is None:
        return c

    def choose(c: SolverCarry) -> SolverCarry:
        K, k = _lq_step(problem, c.xs, c.us, options, c.control_regularization)
        finite = jnp.all(jnp.isfinite(K)) & jnp.all(jnp.isfinite(k))
        last = BestIterate(c.xs, c.us, K, k, jnp.where(finite, _action_merit(k), jnp.inf))
        chosen = _select(last.merit <= best.merit, last, best)
        return c._replace(xs=chosen.xs, us=chosen.us, K=chosen.K, k=chosen.k, best=chosen)

    stopped_early = (c.status == MAX_ITERATIONS) | (c.status == BUDGET_EXHAUSTED)
    return jax.lax.cond(stopped_early, choose, lambda c: c, c)


def iterate_while_running(problem: GameProblem, c: SolverCarry, options: SolverOptions,
                          steps: int | None = None) -> SolverCarry:
    """:func:`iterate` until the status is no longer ``RUNNING``, or for at most ``steps``
    iterations (a ``lax.while_loop``)."""
    if steps is None:
        return jax.lax.while_loop(lambda c: c.status == RUNNING, lambda c: iterate(problem, c, options), c)
    _, c = jax.lax.while_loop(
        lambda nc: (nc[1].status == RUNNING) & (nc[0] < steps),
        lambda nc: (nc[0] + 1, iterate(problem, nc[1], options)),
        (jnp.asarray(0), c),
    )
    return c


def solve_arrays(problem: GameProblem, x0: Array, us0: Array, options: SolverOptions) -> SolverResult:
    """The whole solve, jitted, without validation: ``x0`` has ``n`` entries in any shape
    (``xs`` is returned in that shape per stage), ``us0 (T, N, m)`` the initial inputs.
    Reshapes and casts happen inside, so a call from :func:`solve` dispatches a single
    computation. The options' structure is static, their numbers are traced
    (:meth:`SolverOptions.split`): options that differ only in numbers share the compiled
    solver."""
    structure, numbers = jit_arguments(options)
    return _solve_compiled(problem, x0, us0, numbers, structure=structure)


@functools.partial(jax.jit, static_argnames=("structure",))
def _solve_compiled(problem: GameProblem, x0: Array, us0: Array, numbers: SolverNumbers, *,
                    structure: SolverOptions) -> SolverResult:
    """The jitted function behind :func:`solve_arrays`: the options as their static
    ``structure`` and traced ``numbers`` (:meth:`SolverOptions.split`)."""
    options = structure.with_numbers(numbers)
    problem = at_precision(problem, options)
    c = initial_carry(problem, x0, us0, options)
    return result(problem, finish(problem, iterate_while_running(problem, c, options), options), x0.shape)


@functools.partial(jax.jit, static_argnames=("structure",))
def _start(problem: GameProblem, x0: Array, us0: Array, numbers: SolverNumbers, *,
           structure: SolverOptions) -> SolverCarry:
    return initial_carry(at_precision(problem, structure), x0, us0, structure.with_numbers(numbers))


@functools.partial(jax.jit, static_argnames=("structure",))
def _iterate_once(problem: GameProblem, c: SolverCarry, numbers: SolverNumbers, *,
                  structure: SolverOptions) -> SolverCarry:
    return iterate(at_precision(problem, structure), c, structure.with_numbers(numbers))


@functools.partial(jax.jit, static_argnames=("structure", "x_shape"))
def _finished_result(problem: GameProblem, c: SolverCarry, numbers: SolverNumbers, *,
                     structure: SolverOptions, x_shape) -> SolverResult:
    problem = at_precision(problem, structure)
    return result(problem, finish(problem, c, structure.with_numbers(numbers)), x_shape)


def solve_within(problem: GameProblem, x0: Array, us0: Array, options: SolverOptions,
                 budget_s: float) -> SolverResult:
    """:func:`solve_arrays` under a wall-clock budget of ``budget_s`` seconds: one jitted
    :func:`iterate` per call, until the solve stops by itself or the budget has run out
    (status ``BUDGET_EXHAUSTED``); at least one iteration runs. With
    ``options.best_iterate`` the best iterate is returned (:func:`finish`). Needs concrete
    inputs (it reads the status between iterations). Needs 64-bit floats for float64, as :func:`solve`."""
    require_precision(options.precision, "planners.ilq.solve_within")
    deadline = time.perf_counter() + budget_s
    structure, numbers = jit_arguments(options)
    c = _start(problem, x0, us0, numbers, structure=structure)
    while True:
        c = _iterate_once(problem, c, numbers, structure=structure)
        if int(c.status) != RUNNING:
            break
        if time.perf_counter() >= deadline:
            c = c._replace(status=jnp.asarray(BUDGET_EXHAUSTED, c.status.dtype))
            break
    return _finished_result(problem, c, numbers, structure=structure, x_shape=tuple(x0.shape))


# --------------------------------------------------------------------------------------
# Validation (outside jit).
# --------------------------------------------------------------------------------------


@jax.jit
def _first_own_hessians(problem: GameProblem, x0: Array, us0: Array) -> Array:
    xs = rollout(problem, x0, us0)
    return local_game.quadratize(problem, xs, us0)[2]


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
    game_type = game_type_of(problem_or_game)
    if game_type is not None and game_type.validate is not None:
        game_type.validate(problem_or_game, control_regularization)
        return
    problem, _ = as_problem(problem_or_game)
    if x0 is None:
        raise ValueError("validate_problem needs x0 for a GameProblem")
    x0 = jnp.asarray(x0)
    if us0 is None:
        us0 = jnp.zeros((problem.horizon, problem.num_players, problem.input_dim), x0.dtype)
    if not is_concrete(problem, x0, us0):
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
    if (options.adaptive_regularization and options.mode != methods.OPEN_LOOP and num_players > 1
            and not options.feedforward_regularization):
        raise ValueError(
            "adaptive_regularization is for open-loop games and one-player problems (ilqgame-ol, "
            "ilqr): in a feedback or Stackelberg game the gains, and with them the solution, depend on the "
            "adapted control_regularization; add feedforward_regularization=true to damp the "
            "feed-forward terms only"
        )


def check_players(options: SolverOptions, num_players: int) -> None:
    """Refuse ``mode="stackelberg"`` for a game of other than two players (one leader, one
    follower)."""
    if options.mode == methods.STACKELBERG and num_players != 2:
        raise ValueError(
            f"mode='stackelberg' needs a game of exactly 2 players (a leader and a follower), got "
            f"{num_players}; games of other sizes: mode='feedback' or 'open_loop'"
        )


def check_budget_ms(budget_ms) -> None:
    """Refuse a wall-clock budget that is not a finite number of milliseconds > 0."""
    try:
        ok = np.isfinite(float(budget_ms)) and float(budget_ms) > 0
    except (TypeError, ValueError):
        ok = False
    if not ok or isinstance(budget_ms, bool):
        raise ValueError(f"budget_ms must be a finite number of milliseconds > 0, got {budget_ms!r}")


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


def as_array(a) -> np.ndarray | Array:
    """``a`` as an array for the solver: NumPy inputs stay NumPy (the jitted solver takes
    them as they are, without a separate dispatch); JAX arrays and tracers are kept."""
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
    us = as_array(getattr(init, "us", init))  # a SolverResult / ILQRResult or an array
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
    budget_ms: float | None = None,
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
        budget_ms: a wall-clock budget [ms] (:func:`solve_within`): iterations stop once it
            has run out (status ``BUDGET_EXHAUSTED``), at least one runs. Combine it with
            ``best_iterate=True`` for an anytime solve. Not under ``jit``/``vmap``.

    Returns:
        :class:`SolverResult`. For a RaceGame, ``xs`` has shape ``(T+1, N, 6)``.

    Works under ``jax.vmap``/``jax.jit`` (validation then only happens on concrete inputs).
    In float64 (the default ``precision``) it needs 64-bit floats (``jax_enable_x64``): its
    tolerances go down to 1e-8..1e-12, and with x64 off it raises ``RuntimeError`` saying
    how to turn them on; ``precision="float32"`` solves in float32 either way.
    """
    options = resolve_options(options, overrides)
    require_precision(options.precision, "planners.ilq.solve")
    problem, game_type = as_problem(problem_or_game)
    _convexify(problem, options)  # a clear error for an unusable convexification
    check_adaptive_regularization(options, problem.num_players)
    check_players(options, problem.num_players)
    x0 = as_array(x0)
    if not jnp.issubdtype(x0.dtype, jnp.floating):
        x0 = x0.astype(jnp.result_type(float))
    if x0.size != problem.state_dim:
        raise ValueError(
            f"x0 must have {problem.state_dim} entries"
            + (f" (shape {game_type.state_shape(problem_or_game)})" if game_type is not None else "")
            + f", got shape {x0.shape}"
        )
    if game_type is None:
        x0 = x0.reshape(-1)
    us0 = _initial_inputs(problem, init, x0.dtype)
    if validate:
        if game_type is not None:
            validate_problem(problem_or_game, control_regularization=options.guaranteed_control_regularization)
        else:
            validate_problem(problem, x0, us0, options.guaranteed_control_regularization)
    if budget_ms is not None:
        check_budget_ms(budget_ms)
        if not is_concrete(problem, x0, us0):
            raise ValueError("budget_ms needs concrete inputs: a wall-clock budget cannot run under jit or vmap")
        return solve_within(problem, x0, us0, options, float(budget_ms) / 1e3)
    return solve_arrays(problem, x0, us0, options)
