"""Certificates of iterative Stackelberg solutions (``planners.ilq.solve(mode="stackelberg")``).

A converged Stackelberg solve is a fixed point of the iteration: every local LQ game's
feedback Stackelberg solution asks for no change (``k = 0``). :func:`certify_stackelberg`
checks what that means on the nonlinear game, player by player:

* **the follower** plays a best response to the leader's feedback law: the follower's
  numbers of a feedback certificate (:func:`planners.certificates.certificate_numbers`,
  the leader's law ``u^l_t(x) = u_hat^l_t - K^l_t (x_t - x_hat_t)`` closed over the
  nonlinear dynamics): stationarity ``|dJ^f/du^f| / |H^f|``, the smallest eigenvalue of
  its own-input Hessian ``H^f``, its stage Hessians on the exact local game, and (with
  ``checks="full"``) the gain of its iLQR best response;
* **the leader** is stationary along the follower's reaction at every stage: the leader
  plays ``u^l_t + d_t`` and the follower answers at the same stage with ``-G_t d_t`` (its
  reaction gain in the local game at the solution, :mod:`planners.lq_stackelberg`), both
  following their feedback laws afterwards, over the nonlinear dynamics. The gradient of
  the leader's total cost in ``d_t`` (``jax.grad`` through that rollout) must vanish
  (``max_t |g_t| / |H_leader,t|``, input units), and the leader's stage Hessians
  ``H_leader`` in the local game must be positive definite (a minimum at every stage).

The local game is the one the solve iterated on (the ``options`` it used: curvature,
regularisation), since a feedback fixed point depends on it (docs/solvers.md).
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np

from planners import certificates, ilq, local_game, lq_stackelberg, methods
from planners.game_problem import GameProblem, as_problem
from planners.precision import require_x64

Array = jax.Array

__all__ = ["STACKELBERG_SOLUTION", "VERDICTS", "StackelbergCertificate", "certify_stackelberg", "leader_reaction_gradient"]

STACKELBERG_SOLUTION = "local Stackelberg solution"
VERDICTS = (STACKELBERG_SOLUTION, certificates.NOT_STATIONARY, "not a minimum")


@dataclasses.dataclass(frozen=True)
class StackelbergCertificate:
    """The verdict of :func:`certify_stackelberg` and the numbers behind it.

    Attributes:
        verdict: one of :data:`VERDICTS`.
        leader: the leading player's index.
        reasons: one line per failed condition (empty for a local Stackelberg solution).
        leader_stationarity: ``max_t |dJ^l/dd_t| / max_t |H_leader,t|`` [input units].
        leader_stage_min_eigenvalue: the smallest eigenvalue of the leader's stage Hessians.
        follower_stationarity: ``|dJ^f/du^f| / |H^f|`` against the leader's law [input units].
        follower_min_eigenvalue: the smallest eigenvalue of ``H^f``.
        follower_stage_min_eigenvalue: the smallest eigenvalue of its stage Hessians.
        follower_best_response_gain: ``J^f - J^f(best response)`` (NaN with ``checks="cheap"``).
        costs: ``(2,)`` both players' total costs.
    """

    verdict: str
    leader: int
    reasons: tuple[str, ...]
    leader_stationarity: float
    leader_stage_min_eigenvalue: float
    follower_stationarity: float
    follower_min_eigenvalue: float
    follower_stage_min_eigenvalue: float
    follower_best_response_gain: float
    costs: np.ndarray


@functools.partial(jax.jit, static_argnames=("options",))
def _leader_numbers(problem: GameProblem, x0: Array, xs: Array, us: Array, K: Array, options):
    """``(g (T, m), H_leader (T, m, m))``: the leader's gradient along the reaction and the
    stage Hessians of the local game at the solution."""
    A, B, Q, q, Rii, rii = ilq.local_lq_game(problem, xs, us, options)
    stages = lq_stackelberg.feedback_stackelberg_stages(A, B, Q, q, *local_game.own_to_full(Rii, rii),
                                                        leader=options.leader)
    g = leader_reaction_gradient(problem, x0, xs, us, K, stages.reaction, options.leader)
    return g, stages.H_leader


def leader_reaction_gradient(problem: GameProblem, x0: Array, xs: Array, us: Array, K: Array,
                             reaction: Array, leader: int) -> Array:
    """The gradient ``(T, m)`` of the leader's total cost in its stage deviations ``d_t``,
    the follower reacting with ``-reaction_t d_t`` at the same stage and both following
    ``u_t(x) = u_hat_t - K_t (x_t - x_hat_t)`` otherwise, over the nonlinear dynamics from
    ``x0``. ``xs (T+1, n)``, ``us (T, 2, m)``, ``K (T, 2, m, n)``, ``reaction (T, m, m)``."""
    params = problem.params
    follower = 1 - leader

    def cost(d):
        def body(carry, inp):
            x, total = carry
            t, x_hat, u_hat, K_t, G_t, d_t = inp
            u = u_hat - jnp.einsum("jmn,n->jm", K_t, x - x_hat)
            u = u.at[leader].add(d_t).at[follower].add(-G_t @ d_t)
            total = total + problem.stage_cost(params, t, leader, x, u[leader])
            return (problem.dynamics(params, t, x, u), total), None

        ts = jnp.arange(us.shape[0])
        (x_T, running), _ = jax.lax.scan(body, (x0, jnp.zeros((), x0.dtype)), (ts, xs[:-1], us, K, reaction, d))
        return running + problem.terminal_cost(params, leader, x_T)

    return jax.grad(cost)(jnp.zeros(us[:, leader].shape, us.dtype))


def certify_stackelberg(problem_or_game, x0, solution, *, options: ilq.SolverOptions | None = None,
                        checks: str = "full",
                        tolerances: certificates.CertificateTolerances | None = None) -> StackelbergCertificate:
    """Certify a ``mode="stackelberg"`` solution of a two-player game (module docstring).

    Args:
        problem_or_game: a :class:`GameProblem` or a registered game (a RaceGame).
        x0: the start state the solution was solved from.
        solution: its :class:`planners.ilq.SolverResult` (``xs``, ``us`` and gains ``K``).
        options: the :class:`planners.ilq.SolverOptions` of the solve, ``mode="stackelberg"``
            (its ``leader`` is the leader; default: leader 0 and the solver's defaults).
        checks: ``"full"`` or ``"cheap"`` (no best-response solve for the follower).
        tolerances: :class:`planners.certificates.CertificateTolerances`.

    Returns:
        :class:`StackelbergCertificate`.
    """
    require_x64("planners.stackelberg.certify_stackelberg")
    options = options or ilq.SolverOptions(mode=methods.STACKELBERG)
    if options.mode != methods.STACKELBERG:
        raise ValueError(f"options must have mode='stackelberg' (the solve's), got mode={options.mode!r}")
    tolerances = tolerances or certificates.CertificateTolerances()
    problem, _ = as_problem(problem_or_game)
    ilq.check_players(options, problem.num_players)
    if getattr(solution, "K", None) is None:
        raise ValueError("a Stackelberg certificate needs the solution's gains: pass the SolverResult")
    numbers, _ = certificates.certificate_numbers(problem_or_game, x0, solution, methods.FEEDBACK,
                                                  checks=checks, tolerances=tolerances)
    l, f = int(options.leader), 1 - int(options.leader)
    dtype = np.result_type(float)
    x0_flat = jnp.asarray(np.asarray(x0, dtype).reshape(-1))
    xs = jnp.asarray(np.asarray(solution.xs, dtype).reshape(problem.horizon + 1, -1))
    us, K = jnp.asarray(np.asarray(solution.us, dtype)), jnp.asarray(np.asarray(solution.K, dtype))
    g, H_l = _leader_numbers(problem, x0_flat, xs, us, K, options)
    g, H_l = np.asarray(g), np.asarray(H_l)
    eig_l = np.linalg.eigvalsh(H_l)
    leader_stationarity = float(np.max(np.linalg.norm(g, axis=-1)) / max(np.max(np.abs(eig_l)), np.finfo(float).tiny))
    H_f_scale = max(abs(float(numbers.min_eigenvalue[f])), abs(float(numbers.max_eigenvalue[f])), np.finfo(float).tiny)
    follower_stationarity = float(numbers.gradient_norm[f]) / H_f_scale
    reasons = []
    if not leader_stationarity <= tolerances.stationarity:
        reasons.append(f"leader (player {l}): |dJ/dd| / |H| along the follower's reaction = "
                       f"{leader_stationarity:.3g} > {tolerances.stationarity:g}")
    if not follower_stationarity <= tolerances.stationarity:
        reasons.append(f"follower (player {f}): |dJ/du| / |H| = {follower_stationarity:.3g} > {tolerances.stationarity:g}")
    verdict = certificates.NOT_STATIONARY if reasons else STACKELBERG_SOLUTION
    if not reasons:
        curvature = tolerances.curvature
        lo_l = float(eig_l.min())
        if lo_l < -curvature * float(np.abs(eig_l).max()):
            reasons.append(f"leader (player {l}): stage Hessian lambda_min = {lo_l:.4g} < 0")
        for label, lo, hi in (("own-input Hessian", numbers.min_eigenvalue[f], numbers.max_eigenvalue[f]),
                              ("stage Hessian", numbers.stage_min_eigenvalue[f], numbers.stage_max_eigenvalue[f])):
            if np.isfinite(lo) and lo < -curvature * max(abs(lo), abs(hi)):
                reasons.append(f"follower (player {f}): {label} lambda_min = {lo:.4g} < 0")
        J, J_br = float(numbers.cost[f]), float(numbers.best_response_cost[f])
        if np.isfinite(J_br) and J - J_br > tolerances.best_response * (1.0 + abs(J)):
            reasons.append(f"follower (player {f}): a best response lowers its cost by {J - J_br:.4g}")
        verdict = "not a minimum" if reasons else STACKELBERG_SOLUTION
    return StackelbergCertificate(
        verdict=verdict, leader=l, reasons=tuple(reasons),
        leader_stationarity=leader_stationarity, leader_stage_min_eigenvalue=float(eig_l.min()),
        follower_stationarity=follower_stationarity,
        follower_min_eigenvalue=float(numbers.min_eigenvalue[f]),
        follower_stage_min_eigenvalue=float(numbers.stage_min_eigenvalue[f]),
        follower_best_response_gain=float(numbers.cost[f] - numbers.best_response_cost[f]),
        costs=np.asarray(numbers.cost),
    )
