"""Certificates of game solutions: local Nash equilibrium, saddle, or not stationary.

A converged iLQ solve is a fixed point of the iteration; that makes it stationary, not an
equilibrium. At a saddle some player lowers its cost by deviating alone. :func:`certify`
tells the cases apart from the nonlinear game itself, independently of the solver's local
models.

The contract
------------
``certify(game, x0, solution, mode)`` takes a :class:`~planners.game_problem.GameProblem` or
a registered game (a :class:`racing_env.RaceGame`), the start state ``x0`` and a solution:
a :class:`planners.ilq.SolverResult` (its ``xs``, ``us`` and, for feedback, its gains
``K``) or, for open loop, the inputs ``us (T, N, m)``. Each player ``i`` faces the others'
strategies, which are those of the solution:

* open loop: the others' input sequences, ``u^j_t = u_hat^j_t``;
* feedback: the others' feedback laws closed over the nonlinear dynamics,
  ``u^j_t(x) = u_hat^j_t - K^j_t (x_t - x_hat_t)``.

``J^i(u^i)`` is player i's total cost when it plays the input sequence ``u^i (T, m)``
against those strategies from ``x0``. From a fixed start state any deviation of player i is
an input sequence, so the solution is a local Nash equilibrium (of the strategies it
reports) exactly when every ``u_hat^i`` is a local minimiser of ``J^i``. The numbers:

* **stationarity** ``|dJ^i/du^i| / |H^i|`` [input units], ``H^i = d^2 J^i / du^i^2``
  (``T m x T m``, exact, through the rollout) and ``|H^i|`` its largest absolute eigenvalue:
  the gradient measured against the stiffest direction, so it does not depend on how the
  costs are scaled. For open loop the gradient
  is :func:`planners.nash.nash_residual`; a converged feedback solve also makes it vanish
  (its fixed point is the first-order condition against the others' laws);
* **curvature** ``lambda_min(H^i)``, dense (``jnp.linalg.eigvalsh``) up to
  :data:`DENSE_HESSIAN_SIZE`, beyond it by Lanczos iterations on Hessian-vector products
  (SciPy's ``eigsh``);
* feedback only, the **stage-wise condition** on the exact local game (exact cost Hessians,
  linearised dynamics, the solution's gains): every player's stage Hessian
  ``S^i_t = R^ii_t + B^i_t' P^i_{t+1} B^i_t`` must be positive definite, where ``P^i`` is
  its value Hessian under the strategy profile. It is the second-order condition at every
  stage and state (subgame perfection), which the trajectory test from ``x0`` cannot see;
* the **best-response test**: player i's iLQR best response to the others' strategies,
  closed over the nonlinear dynamics, and its gain ``J^i(u_hat^i) - J^i(u_BR^i)``: the
  nonlinear counterpart of the LQ best-response checks. It starts from ``u_hat^i`` and,
  where ``H^i`` has a negative eigenvalue, also from ``u_hat^i`` displaced by
  ``escape_step`` along its eigenvector (iLQR with a positive semi-definite curvature does
  not leave a point whose gradient vanishes, saddle or not); the lower cost counts.

The verdict (:class:`CertificateTolerances` holds the tolerances):

* ``"not stationary"``: some player's stationarity exceeds ``stationarity``;
* ``"saddle"``: stationary, but some player has ``lambda_min(H^i) < -curvature |H^i|``, or
  (feedback) a stage Hessian with such an eigenvalue, or a best
  response that gains more than ``best_response * (1 + |J^i|)``: that player gains by
  deviating alone;
* ``"local Nash equilibrium"``: neither. When some ``lambda_min`` lies within the curvature
  tolerance of zero only the second-order necessary condition holds (``strict`` is False).

``checks="cheap"`` skips the best-response solves: the form the game agents use on their
re-plans. On the paper's scene (N = 2, T = 50) a full certificate costs about 19 ms on one
CPU core, nearly all of it the two dense Hessians (100 forward-over-reverse passes each),
against 2 ms for a cold solve (``racing bench`` reports both). Everything numeric is one
jitted function of the problem's arrays; the verdict is read on the host.
"""

from __future__ import annotations

import dataclasses
import functools
from typing import Any, Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from planners import local_game, methods
from planners.game_problem import GameProblem, as_problem
from planners.precision import require_x64

Array = jax.Array

__all__ = [
    "DENSE_HESSIAN_SIZE",
    "LOCAL_NASH",
    "NOT_STATIONARY",
    "SADDLE",
    "VERDICTS",
    "Certificate",
    "CertificateNumbers",
    "CertificateTolerances",
    "certificate_numbers",
    "certify",
    "deviation_cost",
    "verdict_of",
]

LOCAL_NASH = "local Nash equilibrium"
SADDLE = "saddle"
NOT_STATIONARY = "not stationary"
VERDICTS = (LOCAL_NASH, SADDLE, NOT_STATIONARY)

#: Largest own-input dimension ``T * m`` whose Hessian is formed densely; beyond it the
#: extreme eigenvalues come from Lanczos iterations on Hessian-vector products.
DENSE_HESSIAN_SIZE = 600


@dataclasses.dataclass(frozen=True)
class CertificateTolerances:
    """The tolerances of a certificate's verdict.

    Attributes:
        stationarity: largest ``|dJ^i/du^i| / |H^i|`` of a stationary point, in
            input units (the racing game: m/s^3 of jerk). A converged solve (state change
            below 1e-6 per iteration) sits orders of magnitude below it.
        curvature: relative: ``lambda_min < -curvature * |H|`` (the largest absolute
            eigenvalue) is a negative eigenvalue (of ``H^i``, or of a stage Hessian);
            ``|lambda_min|`` below it is treated as zero (eigenvalue round-off is ~1e-13
            relative).
        best_response: relative: a best response that lowers ``J^i`` by more than
            ``best_response * (1 + |J^i|)`` is a profitable deviation.
    """

    stationarity: float = 1e-4
    curvature: float = 1e-6
    best_response: float = 1e-6

    def __post_init__(self):
        for field in dataclasses.fields(self):
            value = getattr(self, field.name)
            if not (isinstance(value, (int, float)) and np.isfinite(value) and value >= 0):
                raise ValueError(f"tolerance {field.name} must be a finite number >= 0, got {value!r}")


class CertificateNumbers(NamedTuple):
    """The numbers behind a certificate, every field ``(N,)`` (NaN where not computed).

    Attributes:
        cost: ``J^i`` at the solution.
        gradient_norm: ``|dJ^i/du^i|_2``.
        min_eigenvalue, max_eigenvalue: extreme eigenvalues of ``H^i``.
        stage_min_eigenvalue, stage_max_eigenvalue: over the stages, the extreme
            eigenvalues of ``S^i_t`` (feedback).
        best_response_cost: ``J^i`` of player i's iLQR best response.
    """

    cost: Array
    gradient_norm: Array
    min_eigenvalue: Array
    max_eigenvalue: Array
    stage_min_eigenvalue: Array
    stage_max_eigenvalue: Array
    best_response_cost: Array


@dataclasses.dataclass(frozen=True)
class Certificate:
    """A solution's verdict and the numbers behind it (see the module docstring).

    Attributes:
        verdict: one of :data:`VERDICTS`.
        mode: ``"open_loop"`` or ``"feedback"``: the strategies the players were tested against.
        numbers: :class:`CertificateNumbers` as NumPy arrays.
        tolerances: the :class:`CertificateTolerances` applied.
        checks: ``"full"`` or ``"cheap"``.
        reasons: one line per failed condition (empty for a local Nash equilibrium).
        strict: the second-order sufficient condition holds (every ``lambda_min`` is
            positive beyond the curvature tolerance).
    """

    verdict: str
    mode: str
    numbers: CertificateNumbers
    tolerances: CertificateTolerances
    checks: str
    reasons: tuple[str, ...]
    strict: bool

    @property
    def is_local_nash(self) -> bool:
        return self.verdict == LOCAL_NASH

    @property
    def stationarity(self) -> np.ndarray:
        """``|dJ^i/du^i| / |H^i|`` per player [input units]."""
        return _stationarity(self.numbers)

    @property
    def best_response_gain(self) -> np.ndarray:
        """``J^i - J^i(best response)`` per player (NaN where not computed)."""
        return np.asarray(self.numbers.cost) - np.asarray(self.numbers.best_response_cost)

    def as_dict(self) -> dict[str, Any]:
        """JSON-ready: the verdict, the reasons, the tolerances and every number as a list."""
        numbers = {k: _json_floats(v) for k, v in self.numbers._asdict().items()}
        numbers["stationarity"] = _json_floats(self.stationarity)
        numbers["best_response_gain"] = _json_floats(self.best_response_gain)
        return {"verdict": self.verdict, "mode": self.mode, "checks": self.checks, "strict": self.strict,
                "reasons": list(self.reasons), "tolerances": dataclasses.asdict(self.tolerances), **numbers}


def _json_floats(values) -> list[float | None]:
    return [None if not np.isfinite(v) else float(v) for v in np.asarray(values, float).reshape(-1)]


# --------------------------------------------------------------------------------------
# The players' costs against the others' strategies (pure JAX).
# --------------------------------------------------------------------------------------


def _joint_inputs(xs_hat: Array, us_hat: Array, K: Array, t, x: Array) -> Array:
    """Every player's strategy at stage ``t`` and state ``x (n,)``: ``u_hat_t - K_t (x - x_hat_t)``, ``(N, m)``."""
    return us_hat[t] - jnp.einsum("jmn,n->jm", K[t], x - xs_hat[t])


def deviation_cost(problem: GameProblem, x0: Array, xs_hat: Array, us_hat: Array, K: Array,
                   player) -> Callable[[Array], Array]:
    """``u_i (T, m) -> J^i``: player ``player``'s total cost when it plays ``u_i`` and every
    other player its strategy ``u^j_t(x) = u_hat^j_t - K^j_t (x_t - x_hat_t)`` (``K = 0``:
    open loop), from ``x0 (n,)`` over the problem's nonlinear dynamics.

    ``xs_hat (T+1, n)``, ``us_hat (T, N, m)``, ``K (T, N, m, n)``; ``player`` may be traced.
    """
    params = problem.params

    def cost(u_i: Array) -> Array:
        def body(carry, inp):
            x, total = carry
            t, u_it = inp
            u = _joint_inputs(xs_hat, us_hat, K, t, x).at[player].set(u_it)
            total = total + problem.stage_cost(params, t, player, x, u_it)
            return (problem.dynamics(params, t, x, u), total), None

        ts = jnp.arange(us_hat.shape[0])
        (x_T, running), _ = jax.lax.scan(body, (x0, jnp.zeros((), x0.dtype)), (ts, u_i))
        return running + problem.terminal_cost(params, player, x_T)

    return cost


class _BestResponseParams(NamedTuple):
    problem: GameProblem  # the game (a pytree: its params are leaves, its functions static)
    xs_hat: Array  # (T+1, n)
    us_hat: Array  # (T, N, m)
    K: Array  # (T, N, m, n)
    player: Array  # int scalar


def _br_dynamics(p: _BestResponseParams, t, x, u):
    joint = _joint_inputs(p.xs_hat, p.us_hat, p.K, t, x).at[p.player].set(u[0])
    return p.problem.dynamics(p.problem.params, t, x, joint)


def _br_stage_cost(p: _BestResponseParams, t, i, x, u_i):
    del i  # the only player
    return p.problem.stage_cost(p.problem.params, t, p.player, x, u_i)


def _br_terminal_cost(p: _BestResponseParams, i, x):
    del i
    return p.problem.terminal_cost(p.problem.params, p.player, x)


def _br_stage_gauss_newton(p: _BestResponseParams, t, i, x, u_i):
    del i
    return p.problem.stage_gauss_newton(p.problem.params, t, p.player, x, u_i)


def _br_terminal_gauss_newton(p: _BestResponseParams, i, x):
    del i
    return p.problem.terminal_gauss_newton(p.problem.params, p.player, x)


def _br_stage_curvature(p: _BestResponseParams, t, i, x):
    del i
    return p.problem.stage_curvature(p.problem.params, t, p.player, x)


def best_response_problem(problem: GameProblem, xs_hat: Array, us_hat: Array, K: Array, player) -> GameProblem:
    """Player ``player``'s single-player problem against the others' strategies (see
    :func:`deviation_cost`): an iLQR solve of it is that player's best response. It keeps
    the game's Gauss-Newton and curvature hooks for that player's costs."""
    gauss_newton = problem.stage_gauss_newton is not None and problem.terminal_gauss_newton is not None
    return GameProblem(
        dynamics=_br_dynamics,
        stage_cost=_br_stage_cost,
        terminal_cost=_br_terminal_cost,
        num_players=1,
        state_dim=problem.state_dim,
        input_dim=problem.input_dim,
        horizon=problem.horizon,
        params=_BestResponseParams(problem, xs_hat, us_hat, K, jnp.asarray(player, jnp.int32)),
        stage_gauss_newton=_br_stage_gauss_newton if gauss_newton else None,
        terminal_gauss_newton=_br_terminal_gauss_newton if gauss_newton else None,
        stage_curvature=_br_stage_curvature if problem.stage_curvature is not None else None,
    )


def _stage_hessian_extremes(problem: GameProblem, xs_hat: Array, us_hat: Array, K: Array) -> tuple[Array, Array]:
    """Over the stages, the extreme eigenvalues of every player's stage Hessian
    ``S^i_t = R^ii_t + B^i_t' P^i_{t+1} B^i_t`` of the exact local game under the gains ``K``:
    ``(N,)`` minima and maxima. ``P^i_T = Q^i_T``;
    ``P^i_t = Q^i_t + K^i_t' R^ii_t K^i_t + F_t' P^i_{t+1} F_t`` with ``F_t = A_t - sum_j B^j_t K^j_t``."""
    A, B = local_game.linearize(problem, xs_hat, us_hat)  # (T, n, n), (T, N, n, m)
    Q, _, Rii, _ = local_game.quadratize(problem, xs_hat, us_hat)  # exact Hessians

    def backward(P, stage):
        A_t, B_t, Q_t, R_t, K_t = stage
        S = R_t + jnp.einsum("ina,inp,ipb->iab", B_t, P, B_t)  # (N, m, m)
        eig = jnp.linalg.eigvalsh(0.5 * (S + jnp.swapaxes(S, -1, -2)))
        F = A_t - jnp.einsum("jnm,jmp->np", B_t, K_t)
        own = jnp.einsum("iab,iac,icd->ibd", K_t, R_t, K_t)  # K^i' R^ii K^i
        P = Q_t + own + jnp.einsum("an,iab,bp->inp", F, P, F)
        return P, (eig[:, 0], eig[:, -1])

    _, (lo, hi) = jax.lax.scan(backward, Q[-1], (A, B, Q[:-1], Rii, K), reverse=True)
    return lo.min(axis=0), hi.max(axis=0)


def _dense_extremes(cost: Callable[[Array], Array], u_i: Array) -> tuple[Array, Array, Array, Array]:
    """Gradient norm, extreme Hessian eigenvalues and the unit eigenvector ``(T, m)`` of the
    smallest one, of ``cost`` at ``u_i (T, m)``."""
    H, g = local_game.hessian_and_gradient(lambda z: cost(z.reshape(u_i.shape)), u_i.reshape(-1))
    eig, vectors = jnp.linalg.eigh(0.5 * (H + H.T))
    return jnp.linalg.norm(g), eig[0], eig[-1], vectors[:, 0].reshape(u_i.shape)


@functools.partial(jax.jit, static_argnames=("dense_hessian", "stagewise"))
def _local_numbers(problem: GameProblem, x0: Array, xs_hat: Array, us_hat: Array, K: Array, *,
                   dense_hessian: bool, stagewise: bool):
    """Per player: ``J^i``, ``|dJ^i/du^i|``, the extreme eigenvalues of ``H^i`` and the
    eigenvector ``(N, T, m)`` of the smallest (dense only; NaN and zeros otherwise), and the
    stage-wise extremes (NaN unless ``stagewise``)."""
    nan = jnp.full((problem.num_players,), jnp.nan, x0.dtype)
    missing = jnp.asarray(jnp.nan, x0.dtype)  # a number not computed (broadcast over the players)

    def player(i):
        cost = deviation_cost(problem, x0, xs_hat, us_hat, K, i)
        u_i = us_hat[:, i]
        if dense_hessian:
            g, lo, hi, v = _dense_extremes(cost, u_i)
        else:
            g, lo, hi, v = jnp.linalg.norm(jax.grad(cost)(u_i)), missing, missing, jnp.zeros_like(u_i)
        return cost(u_i), g, lo, hi, v

    J, g, lo, hi, v = jax.vmap(player)(jnp.arange(problem.num_players))
    stage_lo, stage_hi = _stage_hessian_extremes(problem, xs_hat, us_hat, K) if stagewise else (nan, nan)
    return J, g, lo, hi, v, stage_lo, stage_hi


@functools.partial(jax.jit, static_argnames=("structure",))
def _best_response_costs(problem: GameProblem, x0: Array, xs_hat: Array, us_hat: Array, K: Array,
                         starts: Array, numbers, *, structure) -> Array:
    """Every player's best-response cost ``(N,)``: the lowest final cost of its iLQR solves
    (:func:`best_response_problem`) from ``starts (N, S, T, m)``; ``inf`` where none is finite.
    The solves' options are ``structure`` with the traced ``numbers``
    (:meth:`planners.ilq.SolverOptions.split`)."""
    from planners import ilq

    options = structure.with_numbers(numbers)

    def player(i, starts_i):
        problem_i = best_response_problem(problem, xs_hat, us_hat, K, i)
        costs = jax.vmap(lambda u: ilq.solve_arrays(problem_i, x0, u[:, None], options).costs[0])(starts_i)
        return jnp.min(jnp.where(jnp.isfinite(costs), costs, jnp.inf))

    return jax.vmap(player)(jnp.arange(problem.num_players), starts)


def _lanczos_extremes(problem: GameProblem, x0, xs_hat, us_hat, K) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Extreme eigenvalues of every player's ``H^i`` and the unit eigenvector ``(N, T, m)`` of
    the smallest, by Lanczos (SciPy ``eigsh``) on Hessian-vector products (forward over
    reverse): for ``T m`` too large to form ``H^i``."""
    from scipy.sparse.linalg import LinearOperator, eigsh

    T, N, m = us_hat.shape

    @jax.jit
    def hvp(i, u_i, v):
        cost = deviation_cost(problem, x0, xs_hat, us_hat, K, i)
        return jax.jvp(jax.grad(cost), (u_i,), (v.reshape(u_i.shape),))[1].reshape(-1)

    lo, hi, vectors = np.empty(N), np.empty(N), np.empty((N, T, m))
    for i in range(N):
        u_i = us_hat[:, i]
        op = LinearOperator((T * m, T * m), matvec=lambda v: np.asarray(hvp(i, u_i, jnp.asarray(v.reshape(-1), u_i.dtype))),
                            dtype=np.float64)
        values, v = eigsh(op, k=1, which="SA", tol=1e-10)
        lo[i], vectors[i] = values[0], v[:, 0].reshape(T, m)
        hi[i] = eigsh(op, k=1, which="LA", return_eigenvectors=False, tol=1e-10)[0]
    return lo, hi, vectors


# --------------------------------------------------------------------------------------
# The public entry points.
# --------------------------------------------------------------------------------------


def _solution_arrays(problem: GameProblem, solution, mode: str | None, dtype) -> tuple[np.ndarray, np.ndarray, str]:
    """``(us_hat (T, N, m), K (T, N, m, n), mode)`` of a solution, checked."""
    T, N, m, n = problem.horizon, problem.num_players, problem.input_dim, problem.state_dim
    us = np.asarray(getattr(solution, "us", solution), dtype)
    if us.shape != (T, N, m):
        raise ValueError(f"the solution's inputs must have shape (T, N, m) = {(T, N, m)}, got {us.shape}")
    if not np.all(np.isfinite(us)):
        raise ValueError("the solution's inputs contain non-finite values")
    gains = getattr(solution, "K", None)
    K = np.zeros((T, N, m, n), dtype) if gains is None else np.asarray(gains, dtype)
    if K.shape != (T, N, m, n):
        raise ValueError(f"the solution's gains K must have shape (T, N, m, n) = {(T, N, m, n)}, got {K.shape}")
    if mode is None:
        mode = methods.FEEDBACK if np.any(K != 0) else methods.OPEN_LOOP
    if mode not in methods.NASH_MODES:
        raise ValueError(f"mode must be 'feedback' or 'open_loop', got {mode!r}")
    if mode == methods.FEEDBACK and gains is None:
        raise ValueError("a feedback certificate needs the solution's gains: pass the SolverResult, not its inputs")
    if mode == methods.OPEN_LOOP:
        K = np.zeros_like(K)  # the others' input sequences, whatever gains the solve reported
    return us, K, mode


def certificate_numbers(problem_or_game, x0, solution, mode: str | None = None, *, checks: str = "full",
                        tolerances: CertificateTolerances | None = None, best_response_options=None,
                        escape_step: float = 1.0) -> tuple[CertificateNumbers, str]:
    """The numbers of :func:`certify` (NumPy arrays) and the mode, without a verdict
    (``tolerances`` decide only which eigenvalues count as negative for the second
    best-response start)."""
    from planners import ilq

    require_x64("planners.certificates.certify")  # eigenvalue and stationarity tolerances of 1e-8..1e-10
    if checks not in ("full", "cheap"):
        raise ValueError(f"checks must be 'full' or 'cheap', got {checks!r}")
    problem, _ = as_problem(problem_or_game)
    dtype = np.result_type(float)
    x0 = jnp.asarray(np.asarray(x0, dtype).reshape(-1))
    if x0.shape != (problem.state_dim,):
        raise ValueError(f"x0 must have {problem.state_dim} entries, got {x0.size}")
    us, K, mode = _solution_arrays(problem, solution, mode, dtype)
    us, K = jnp.asarray(us), jnp.asarray(K)
    xs = getattr(solution, "xs", None)
    xs = jnp.asarray(np.asarray(xs, dtype).reshape(problem.horizon + 1, -1)) if xs is not None else None
    if xs is None or xs.shape[1] != problem.state_dim:
        from planners.game_problem import rollout

        xs = rollout(problem, x0, us)
    feedback = mode == methods.FEEDBACK
    dense = problem.horizon * problem.input_dim <= DENSE_HESSIAN_SIZE
    J, g, lo, hi, v, stage_lo, stage_hi = (np.asarray(a) for a in _local_numbers(
        problem, x0, xs, us, K, dense_hessian=dense, stagewise=feedback))
    if not dense:
        lo, hi, v = _lanczos_extremes(problem, x0, xs, us, K)
    best = np.full_like(J, np.nan)
    if checks == "full":
        # from the solution, and displaced along its most negative curvature: a Gauss-Newton
        # iLQR started exactly at a stationary point does not move, even at a saddle
        curvature = (tolerances or CertificateTolerances()).curvature
        negative = lo < -curvature * np.maximum(np.abs(lo), np.abs(hi))
        own = np.swapaxes(np.asarray(us), 0, 1)  # (N, T, m)
        displaced = own + np.where(negative, escape_step, 0.0)[:, None, None] * v
        starts = np.stack([own, displaced], axis=1)  # (N, 2, T, m)
        structure, solver_numbers = ilq.jit_arguments(best_response_options or ilq.SolverOptions(mode=methods.FEEDBACK))
        best = np.asarray(_best_response_costs(problem, x0, xs, us, K, jnp.asarray(starts), solver_numbers,
                                               structure=structure))
    numbers = CertificateNumbers(J, g, lo, hi, stage_lo, stage_hi, best)
    return numbers, mode


def _stationarity(numbers: CertificateNumbers) -> np.ndarray:
    scale = np.maximum(np.abs(np.asarray(numbers.min_eigenvalue, float)), np.abs(np.asarray(numbers.max_eigenvalue, float)))
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.asarray(numbers.gradient_norm, float) / np.maximum(scale, np.finfo(float).tiny)


def verdict_of(numbers: CertificateNumbers, tolerances: CertificateTolerances = CertificateTolerances()
               ) -> tuple[str, tuple[str, ...], bool]:
    """``(verdict, reasons, strict)`` of certificate numbers under ``tolerances``."""
    stationarity = _stationarity(numbers)
    reasons = [f"player {i}: |dJ/du| / |H| = {s:.3g} > {tolerances.stationarity:g}"
               for i, s in enumerate(stationarity) if not s <= tolerances.stationarity]
    if reasons:
        return NOT_STATIONARY, tuple(reasons), False
    strict = True
    for label, lo, hi in (("own-input Hessian", numbers.min_eigenvalue, numbers.max_eigenvalue),
                          ("stage Hessian", numbers.stage_min_eigenvalue, numbers.stage_max_eigenvalue)):
        for i, (a, b) in enumerate(zip(np.asarray(lo, float), np.asarray(hi, float))):
            if not np.isfinite(a):
                continue
            bound = tolerances.curvature * max(abs(a), abs(b), np.finfo(float).tiny)
            if a < -bound:
                reasons.append(f"player {i}: {label} lambda_min = {a:.4g} < 0 (lambda_max = {b:.4g})")
            strict &= bool(a > bound)
    cost, br = np.asarray(numbers.cost, float), np.asarray(numbers.best_response_cost, float)
    for i, (J, J_br) in enumerate(zip(cost, br)):
        if np.isfinite(J_br) and J - J_br > tolerances.best_response * (1.0 + abs(J)):
            reasons.append(f"player {i}: a best response lowers its cost by {J - J_br:.4g} (from {J:.6g})")
    return (SADDLE if reasons else LOCAL_NASH), tuple(reasons), strict and not reasons


def certify(problem_or_game, x0, solution, mode: str | None = None, *, checks: str = "full",
            tolerances: CertificateTolerances | None = None, best_response_options=None,
            escape_step: float = 1.0) -> Certificate:
    """Certify a solution as a local Nash equilibrium, a saddle, or not stationary.

    Args:
        problem_or_game: a :class:`GameProblem` or a registered game (a RaceGame).
        x0: the start state (``(n,)``, or the game's layout, e.g. ``(N, 6)``).
        solution: a :class:`planners.ilq.SolverResult` (``xs``, ``us``, ``K``), or for open
            loop the inputs ``us (T, N, m)``.
        mode: ``"open_loop"`` (the others keep their input sequences) or ``"feedback"`` (the
            others keep their feedback laws); ``None`` takes feedback when the solution has
            non-zero gains.
        checks: ``"full"`` (every number) or ``"cheap"`` (no best-response solves).
        tolerances: :class:`CertificateTolerances` (the defaults are documented there).
        best_response_options: :class:`planners.ilq.SolverOptions` of the best-response
            iLQR solves (default: the solver's defaults).
        escape_step: length [input units, 2-norm of the displacement of the sequence] of
            the second best-response start, displaced from ``u_hat^i`` along the eigenvector
            of ``H^i``'s negative smallest eigenvalue (where there is one).

    Returns:
        :class:`Certificate`.
    """
    tolerances = tolerances or CertificateTolerances()
    numbers, mode = certificate_numbers(problem_or_game, x0, solution, mode, checks=checks, tolerances=tolerances,
                                        best_response_options=best_response_options, escape_step=escape_step)
    verdict, reasons, strict = verdict_of(numbers, tolerances)
    return Certificate(verdict, mode, numbers, tolerances, checks, reasons, strict)
