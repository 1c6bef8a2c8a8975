"""The local LQ game of a game problem around a trajectory: the model each iLQ iteration solves.

Along a nominal trajectory ``xs (T+1, n)``, ``us (T, N, m)`` of a
:class:`~planners.game_problem.GameProblem`:

* :func:`linearize`: the dynamics, ``dx_{t+1} = A_t dx_t + sum_j B_t^j du_t^j``;
* :func:`quadratize`: every player's quadratic cost model ``Q, q`` (state) and ``Rii, rii``
  (own input), from exact Hessians or from the problem's Gauss-Newton residuals
  (:func:`gauss_newton_terms`: ``J' diag(h) J`` and ``J' g``, PSD by construction);
* :func:`psd_part`: the positive semi-definite part of symmetric blocks (the ``"eig"``
  convexification).

Pure JAX, jit- and vmap-able; :mod:`planners.ilq` builds its iterations from these. The
design choices (Gauss-Newton, the progress curvature) are discussed in docs/solvers.md.
"""

from __future__ import annotations

from typing import Callable

import jax
import jax.numpy as jnp

from planners import lq_game
from planners.batching import one_at_a_time, with_batched_form
from planners.game_problem import GameProblem

Array = jax.Array

__all__ = ["gauss_newton_factors", "gauss_newton_terms", "hessian_and_gradient", "linearize", "own_to_full",
           "psd_part", "quadratize"]


def linearize(problem: GameProblem, xs: Array, us: Array) -> tuple[Array, Array]:
    """The dynamics linearised along ``xs (T+1, n)``, ``us (T, N, m)``:
    ``dx_{t+1} = A_t dx_t + sum_j B_t^j du_t^j`` with ``A (T, n, n)``, ``B (T, N, n, m)``
    (the problem's ``dynamics_jacobians`` hook, else ``jax.jacfwd``)."""
    params = problem.params
    if problem.dynamics_jacobians is not None:
        jac = lambda t, x, u: problem.dynamics_jacobians(params, t, x, u)
    else:
        jac = jax.jacfwd(lambda t, x, u: problem.dynamics(params, t, x, u), argnums=(1, 2))
    A, B = jax.vmap(jac)(jnp.arange(us.shape[0]), xs[:-1], us)  # B (T, n, N, m)
    return A, jnp.transpose(B, (0, 2, 1, 3))


def hessian_and_gradient(fun: Callable[[Array], Array], z: Array) -> tuple[Array, Array]:
    """Hessian and gradient of a scalar function in one forward-over-reverse pass."""
    grad = jax.grad(fun)

    def grad_twice(z_):
        g = grad(z_)
        return g, g

    return jax.jacfwd(grad_twice, has_aux=True)(z)


def gauss_newton_factors(fun: Callable, z: Array) -> tuple[Array, Array, Array]:
    """The residual Jacobian ``J (K, D)``, outer slopes ``g (K,)`` and clipped outer
    curvatures ``h >= 0 (K,)`` of ``sum_k rho_k(r_k(z))``, where ``fun(z) = (r, g, h)``
    (one forward-mode pass)."""
    J, (g, h) = jax.jacfwd(lambda z_: (lambda r, g, h: (r, (g, h)))(*fun(z_)), has_aux=True)(z)
    return J, jax.lax.stop_gradient(g), jax.lax.stop_gradient(jnp.maximum(h, 0.0))


# Multiply-adds of one product up to which it is written as fused code. Above it XLA
# rewrites the fused form into a dot anyway, and the dot is better written as one
# (docs/performance.md, "XLA settings and dispatch").
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


def gauss_newton_terms(fun: Callable, z: Array) -> tuple[Array, Array]:
    """Gauss-Newton Hessian ``J' diag(h) J`` and exact gradient ``J' g`` of
    ``sum_k rho_k(r_k(z))``, where ``fun(z) = (r, g, h)`` (one forward-mode pass)."""
    return _gauss_newton_products(*gauss_newton_factors(fun, z))


def _stagewise_gauss_newton_products(J: Array, g: Array, h: Array) -> tuple[Array, Array]:
    """:func:`_gauss_newton_products` of ``(T, N, ...)`` factors, one stage after another.

    As a loop over the stages the products compile into one kernel
    (:mod:`racing_env.xla_setup`). As one batched product over all stages XLA:CPU hands
    them to a library call, which is slower for these small shapes and keeps the solver's
    outer loop from becoming one kernel (docs/performance.md, "XLA settings and dispatch").
    """
    def stage(_, factors):
        return None, jax.vmap(_gauss_newton_products)(*factors)

    return jax.lax.scan(stage, None, (J, g, h))[1]


def _all_gauss_newton_products(J: Array, g: Array, h: Array) -> tuple[Array, Array]:
    """:func:`_gauss_newton_products` over any leading axes, as batched products."""
    return jnp.einsum("...ka,...k,...kb->...ab", J, h, J), jnp.einsum("...ka,...k->...a", J, g)


# Under vmap (batches of games) the batched products are faster than a loop over the
# stages per game, mapped or vmapped (docs/performance.md).
_quadratize_products = with_batched_form(_stagewise_gauss_newton_products, _all_gauss_newton_products)


def quadratize(problem: GameProblem, xs: Array, us: Array, gauss_newton: bool = False,
               dynamics_curvature: bool = False) -> tuple[Array, Array, Array, Array]:
    """Every player's quadratic cost model along ``xs (T+1, n)``, ``us (T, N, m)``.

    Returns ``Q (T+1, N, n, n)``, ``q (T+1, N, n)`` (state; index ``T`` is the terminal
    cost) and ``Rii (T, N, m, m)``, ``rii (T, N, m)`` (own input): exact Hessians, or with
    ``gauss_newton`` the problem's Gauss-Newton form (PSD; needs the problem's hooks). With
    ``dynamics_curvature`` the problem's ``stage_curvature`` (if it has one) is added to
    the diagonal of the stages' ``Q``. The gradients are exact either way. Not yet
    convexified or regularised (:func:`planners.ilq.regularize`).
    """
    params = problem.params
    n = problem.state_dim
    players = jnp.arange(problem.num_players)
    if gauss_newton:
        terms, stage_fn, terminal_fn = (
            gauss_newton_terms, problem.stage_gauss_newton, problem.terminal_gauss_newton
        )
    else:
        terms, stage_fn, terminal_fn = hessian_and_gradient, problem.stage_cost, problem.terminal_cost

    def stage(t, x, u):
        def player(i, u_i):
            fun = lambda z: stage_fn(params, t, i, z[:n], z[n:])
            return (gauss_newton_factors if gauss_newton else terms)(fun, jnp.concatenate([x, u_i]))

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


def own_to_full(Rii: Array, rii: Array) -> tuple[Array, Array]:
    """Embed own blocks ``(T, N, m, m)``, ``(T, N, m)`` into ``R (T, N, N, m, m)``, ``r``."""
    T, N, m = rii.shape
    idx = jnp.arange(N)
    R = jnp.zeros((T, N, N, m, m), Rii.dtype).at[:, idx, idx].set(Rii)
    r = jnp.zeros((T, N, N, m), rii.dtype).at[:, idx, idx].set(rii)
    return R, r


def _psd_part_one_by_one(Q: Array) -> Array:
    """The PSD part ``V max(w, 0) V'`` of every symmetric ``(n, n)`` block of ``Q (..., n, n)``,
    one eigendecomposition after another."""
    def one(M):
        w, V = jnp.linalg.eigh(M)
        return (V * jnp.maximum(w, 0.0)) @ V.T

    return jax.lax.map(one, Q.reshape((-1,) + Q.shape[-2:])).reshape(Q.shape)


# One LAPACK call per matrix, also in a vmapped batch split across CPU devices: a batched
# call hangs there (see planners.batching.one_at_a_time).
psd_part = one_at_a_time(_psd_part_one_by_one)
