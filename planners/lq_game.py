"""Finite-horizon, discrete-time linear-quadratic (LQ) dynamic games.

Notation (all arrays float; ``T`` horizon, ``N`` players, ``n`` state size, ``m`` input size
shared by all players)::

    A (T, n, n)        B (T, N, n, m)        Q (T+1, N, n, n)      q (T+1, N, n)
    R (T, N, N, m, m)  r (T, N, N, m)        R[t, i, j] = R_t^{ij}: player i's weight on u^j

Dynamics ``x_{t+1} = A_t x_t + sum_j B_t^j u_t^j`` and cost of player ``i``::

    J^i = 1/2 sum_{t<T} [x_t' Q_t^i x_t + 2 q_t^i' x_t
                         + sum_j (u_t^j' R_t^{ij} u_t^j + 2 r_t^{ij}' u_t^j)]
          + 1/2 x_T' Q_T^i x_T + q_T^i' x_T.

Solvers:

* :func:`solve_feedback`: feedback (closed-loop, subgame-perfect) Nash equilibrium,
  ``u_t^i = -K_t^i x_t - k_t^i``, by the coupled Riccati recursion.
* :func:`solve_feedback_own`: the same equilibrium for games in which every player's
  input cost involves only its own input (``R^{ij} = r^{ij} = 0`` for ``i != j``, the
  structure of the iterative LQ games), with ``Q^i >= 0``: a faster recursion (no LAPACK
  calls, products of small operands written as fused element-wise code).
* :func:`solve_feedback_own_batched`: :func:`solve_feedback_own` for a batch of games in one
  recursion whose products are batched dots across the games (the layout an accelerator
  wants; on CPU ``racing bench`` times it against the per-game form).
* :func:`solve_open_loop`: open-loop Nash equilibrium, ``u_t^i = -k_t^i``, from each player's
  Pontryagin conditions with an affine costate ``lambda_t^i = M_t^i x_t + m_t^i``.
* :func:`solve_open_loop_own`: the same for own-input costs, without ``n x n`` solves
  (Woodbury identity, fused small products, the ``(N m) x (N m)`` systems solved by
  :func:`pivoted_solve` instead of LAPACK): the open-loop counterpart of
  :func:`solve_feedback_own`.
* :func:`lqr`: plain single-player LQR (an independent oracle for ``N = 1``).

All solvers are pure JAX (``lax.scan`` over time), jitted (compiled once per shape), freely
composable with ``jit``/``vmap``/``grad``, and do no validation: call :func:`validate_lq_game`
once, outside ``jit``, on the raw arrays. Under ``jax.vmap`` the game solvers run the games
of the batch one after another (:func:`planners.batching.one_at_a_time`: the fastest batched
form on CPU, docs/performance.md, and the one whose LAPACK calls cannot deadlock a batch
split across CPU devices).

The own-input solvers call no LAPACK routine for ``N m <= 8``: a loop without such a call
can be compiled by XLA:CPU into a single kernel (:mod:`racing_env.xla_setup`), which
removes the fixed cost per operation that otherwise dominates these small recursions.

Only the symmetric parts of ``Q`` and ``R`` enter the costs, so the solvers symmetrise them;
non-symmetric inputs are thus handled consistently with the cost definition.
"""

from __future__ import annotations

from typing import Any, Callable

import jax
import jax.numpy as jnp
import numpy as np

from planners.batching import one_at_a_time

Array = jax.Array

__all__ = [
    "block_solve",
    "closed_loop_values",
    "lq_costs",
    "lq_rollout_feedback",
    "lqr",
    "pivoted_solve",
    "solve_feedback",
    "solve_feedback_own",
    "solve_feedback_own_batched",
    "solve_open_loop",
    "solve_open_loop_own",
    "validate_lq_game",
]


def _sym(M: Array) -> Array:
    """Symmetric part over the last two axes."""
    return 0.5 * (M + jnp.swapaxes(M, -1, -2))


def _own(R: Array) -> Array:
    """Per-player own blocks ``X[..., i, i, ...]`` of an ``(..., N, N, ...)`` array at axes 0, 1.

    Works for ``R (N, N, m, m) -> (N, m, m)`` and ``r (N, N, m) -> (N, m)``.
    """
    idx = jnp.arange(R.shape[0])
    return R[idx, idx]


# --------------------------------------------------------------------------------------
# Validation (NumPy, not jitted).
# --------------------------------------------------------------------------------------


def validate_lq_game(A, B, Q, q, R, r) -> None:
    """Check shapes, finiteness and that every ``R_t^{ii}`` is positive definite.

    Args:
      A: ``(T, n, n)``. B: ``(T, N, n, m)``. Q: ``(T+1, N, n, n)``. q: ``(T+1, N, n)``.
      R: ``(T, N, N, m, m)``. r: ``(T, N, N, m)``.

    Raises:
      ValueError: naming the offending array (and ``t``, ``i`` for a non-PD ``R^{ii}``).
    """
    arrays = {k: np.asarray(v) for k, v in dict(A=A, B=B, Q=Q, q=q, R=R, r=r).items()}
    ndims = dict(A=3, B=4, Q=4, q=3, R=5, r=4)
    for name, nd in ndims.items():
        if arrays[name].ndim != nd:
            raise ValueError(
                f"{name} must have {nd} dimensions, got shape {arrays[name].shape}"
            )
    T, n = arrays["A"].shape[0], arrays["A"].shape[1]
    N, m = arrays["B"].shape[1], arrays["B"].shape[3]
    expected = dict(
        A=(T, n, n),
        B=(T, N, n, m),
        Q=(T + 1, N, n, n),
        q=(T + 1, N, n),
        R=(T, N, N, m, m),
        r=(T, N, N, m),
    )
    for name, shape in expected.items():
        if arrays[name].shape != shape:
            raise ValueError(
                f"shape mismatch: {name} has shape {arrays[name].shape}, expected {shape} "
                f"(T={T}, N={N}, n={n}, m={m} inferred from A and B)"
            )
    if T < 1 or N < 1 or n < 1 or m < 1:
        raise ValueError(f"empty game: T={T}, N={N}, n={n}, m={m}")
    for name, arr in arrays.items():
        if not np.all(np.isfinite(arr)):
            raise ValueError(f"{name} contains non-finite values")
    R_arr = arrays["R"]
    for t in range(T):
        for i in range(N):
            Rii = R_arr[t, i, i]
            # Only the symmetric part enters u' R u; PD <=> its smallest eigenvalue > 0.
            lam_min = float(np.linalg.eigvalsh(0.5 * (Rii + Rii.T)).min())
            scale = max(1.0, float(np.abs(Rii).max()))
            if not lam_min > 1e-12 * scale:
                raise ValueError(
                    f"R[t={t}, i={i}, i={i}] (player {i}'s weight on its own input at "
                    f"stage {t}) is not positive definite: min eigenvalue {lam_min:.3e}"
                )


# --------------------------------------------------------------------------------------
# Feedback Nash equilibrium.
# --------------------------------------------------------------------------------------


@jax.jit
def solve_feedback(
    A: Array, B: Array, Q: Array, q: Array, R: Array, r: Array,
    feedforward_regularization: Array | float | None = None,
) -> tuple[Array, Array]:
    """Feedback Nash equilibrium of an LQ game (under ``jax.vmap``: one game after another).

    Backward recursion on each player's value ``V_t^i(x) = 1/2 x'P_t^i x + p_t^i' x + c``.
    At every stage the players' first-order conditions are coupled; they are stacked into
    one ``(N m) x (N m)`` linear system, row block ``i``::

        (R^{ii} + B^i' P^i B^i) K^i + B^i' P^i sum_{j!=i} B^j K^j = B^i' P^i A
        (R^{ii} + B^i' P^i B^i) k^i + B^i' P^i sum_{j!=i} B^j k^j = B^i' p^i + r^{ii}

    (``P, p`` at ``t+1``). The values are then propagated along the closed loop
    ``F = A - sum_j B^j K^j``, ``beta = -sum_j B^j k^j``::

        P_t^i = Q^i + F' P^i F + sum_j K^j' R^{ij} K^j
        p_t^i = q^i + F' (p^i + P^i beta) + sum_j K^j' (R^{ij} k^j - r^{ij})

    The value recursion evaluates the strategies actually returned (any ``K, k``), which
    lets the feed-forward terms be damped without moving the equilibrium:
    ``feedforward_regularization = lambda > 0`` solves the ``k`` rows with every own block
    ``R^{ii} + B^i' P^i B^i`` raised by ``lambda I`` (``S + lambda I``, ``S`` the stage's
    coupled matrix) and keeps the gains ``K`` of the game itself: a proximal
    (Levenberg-Marquardt) step on the feed-forward of an iterative game. ``k`` vanishes at
    every stage exactly when the equilibrium's does (by backward induction), so an
    iteration's fixed points stay the game's. Where the symmetric part of every ``S`` is
    positive definite (one player: ``S = R + B'PB``), ``S + lambda I`` is regular and each
    stage's ``k`` is no longer than ``S^{-1}`` applied to the same right-hand side. Coupled
    games can have an ``S`` with a negative eigenvalue ``-mu`` (a unique equilibrium all
    the same): there ``lambda < mu`` lengthens the step, ``lambda = mu`` makes ``k``
    non-finite and ``lambda > mu`` reverses it along that direction. On the paper's racing
    scene (at zero inputs and at the feedback equilibrium) the smallest real eigenvalue of
    every stage's ``S`` was that of ``R^{ii}``.

    Args:
      A: ``(T, n, n)``. B: ``(T, N, n, m)``. Q: ``(T+1, N, n, n)``. q: ``(T+1, N, n)``.
      R: ``(T, N, N, m, m)``. r: ``(T, N, N, m)``.
      feedforward_regularization: ``lambda >= 0`` (scalar) or None (the equilibrium).

    Returns:
      ``K (T, N, m, n)`` and ``k (T, N, m)``; equilibrium strategies
      ``u_t^i = -K_t^i x_t - k_t^i``.
    """
    if feedforward_regularization is None:
        return _feedback(A, B, Q, q, R, r)
    return _feedback(A, B, Q, q, R, r, feedforward_regularization)


def _feedback_recursion(A, B, Q, q, R, r, feedforward_regularization=None):
    """The recursion of :func:`solve_feedback` for one game."""
    N, n, m = B.shape[1], B.shape[2], B.shape[3]
    Q, R = _sym(Q), _sym(R)
    # lambda I for the feed-forward rows, made once, in the weights' dtype (a float64 lambda
    # must not promote a float32 recursion)
    lam_I = (None if feedforward_regularization is None
             else jnp.asarray(feedforward_regularization, R.dtype) * jnp.eye(N * m, dtype=R.dtype))

    def step(carry, stage):
        P, p = carry  # (N, n, n), (N, n) at t+1
        A_t, B_t, Q_t, q_t, R_t, r_t = stage
        BtP = jnp.einsum("iam,iab->imb", B_t, P)  # B^i' P^i, (N, m, n)
        # Coupled system S [K; k] = [rhs_K, rhs_k], blocks S_ij = delta_ij R^{ii} + B^i'P^i B^j.
        S = jnp.einsum("imb,jbl->imjl", BtP, B_t)
        S = S + jnp.einsum("ij,iml->imjl", jnp.eye(N, dtype=S.dtype), _own(R_t))
        rhs_K = BtP @ A_t  # (N, m, n)
        rhs_k = jnp.einsum("iam,ia->im", B_t, p) + _own(r_t)  # (N, m)
        S = S.reshape(N * m, N * m)
        if lam_I is None:
            rhs = jnp.concatenate([rhs_K, rhs_k[..., None]], axis=-1).reshape(N * m, n + 1)
            sol = jnp.linalg.solve(S, rhs).reshape(N, m, n + 1)
            K, k = sol[..., :n], sol[..., n]
        else:
            K = jnp.linalg.solve(S, rhs_K.reshape(N * m, n)).reshape(N, m, n)
            k = jnp.linalg.solve(S + lam_I, rhs_k.reshape(N * m)).reshape(N, m)

        return closed_loop_values(A_t, B_t, Q_t, q_t, R_t, r_t, P, p, K, k), (K, k)

    stages = (A, B, Q[:-1], q[:-1], R, r)
    _, (K, k) = jax.lax.scan(step, (Q[-1], q[-1]), stages, reverse=True)
    return K, k


def closed_loop_values(A_t, B_t, Q_t, q_t, R_t, r_t, P, p, K, k) -> tuple[Array, Array]:
    """Every player's value at stage ``t`` when all play ``u^j = -K^j x - k^j`` there.

    With the closed loop ``F = A - sum_j B^j K^j``, ``beta = -sum_j B^j k^j`` and the values
    ``1/2 x'P^i x + p^i'x`` at ``t+1``::

        P_t^i = Q^i + F' P^i F + sum_j K^j' R^{ij} K^j
        p_t^i = q^i + F' (p^i + P^i beta) + sum_j K^j' (R^{ij} k^j - r^{ij})

    Args (one stage): A_t ``(n, n)``, B_t ``(N, n, m)``, Q_t ``(N, n, n)``, q_t ``(N, n)``,
    R_t ``(N, N, m, m)`` (symmetric), r_t ``(N, N, m)``, P ``(N, n, n)``, p ``(N, n)``,
    K ``(N, m, n)``, k ``(N, m)``.

    Returns:
      ``P_t (N, n, n)`` (symmetrised) and ``p_t (N, n)``.
    """
    F = A_t - jnp.einsum("jam,jmb->ab", B_t, K)  # closed-loop dynamics
    beta = -jnp.einsum("jam,jm->a", B_t, k)  # closed-loop drift
    P_new = (
        Q_t
        + jnp.einsum("ab,ibc,cd->iad", F.T, P, F)
        + jnp.einsum("jma,ijml,jlb->iab", K, R_t, K)
    )
    p_new = (
        q_t
        + jnp.einsum("ab,ib->ia", F.T, p + P @ beta)
        + jnp.einsum("jma,ijm->ia", K, jnp.einsum("ijml,jl->ijm", R_t, k) - r_t)
    )
    return _sym(P_new), p_new


# One game at a time under vmap: its pivoting solves then stay single LAPACK calls, which
# a batch split across CPU devices needs (see planners.batching.one_at_a_time).
_feedback = one_at_a_time(_feedback_recursion)


# Products of tiny operands. XLA:CPU emits every dot as a separate library call whose fixed
# cost (about half a microsecond) dominates products of a few hundred multiply-adds, while a
# broadcast multiply followed by a sum is fused with its neighbours into one loop. Inside
# the sequential Riccati recursion this per-operation overhead is most of the run time, so
# products up to _FUSED_PRODUCT_MAX multiply-adds are written element-wise; larger ones
# (e.g. F' P F for three cars) stay dots, which vectorise better.
_FUSED_PRODUCT_MAX = 4096


def _letter_sizes(spec: str, *operands: Array) -> dict[str, int]:
    """The size of every index letter of an einsum ``spec`` with these operands."""
    inputs = spec.split("->")[0].split(",")
    return {c: d for letters, op in zip(inputs, operands) for c, d in zip(letters, op.shape)}


def _is_fused(spec: str, *operands: Array) -> bool:
    """Whether :func:`_contract` evaluates the product as fused element-wise code: its
    multiply-adds (the product of all letter sizes) are at most ``_FUSED_PRODUCT_MAX``."""
    return int(np.prod(list(_letter_sizes(spec, *operands).values()))) <= _FUSED_PRODUCT_MAX


def _contract(spec: str, *operands: Array) -> Array:
    """``jnp.einsum(spec, *operands)`` (explicit output, no repeated output letters).

    Small products are evaluated as one broadcast product summed over the contracted
    letters (the output letters lead, the contracted ones trail), which XLA fuses.
    """
    if not _is_fused(spec, *operands):
        return jnp.einsum(spec, *operands)
    inputs, out = spec.split("->")
    inputs = inputs.split(",")
    sizes = _letter_sizes(spec, *operands)
    order = list(out) + [c for c in dict.fromkeys("".join(inputs)) if c not in out]
    product = None
    for letters, op in zip(inputs, operands):
        perm = sorted(range(len(letters)), key=lambda k: order.index(letters[k]))
        op = jnp.transpose(op, perm)
        present = [letters[k] for k in perm]
        op = op.reshape([sizes[c] if c in present else 1 for c in order])
        product = op if product is None else product * op
    contracted = tuple(range(len(out), len(order)))
    return jnp.sum(product, axis=contracted) if contracted else product


def _sandwich(X: Array, M: Array, Y: Array) -> Array:
    """``X' M^i Y`` for every player: ``X (n, a)``, ``M (N, n, n)``, ``Y (n, d)`` -> ``(N, a, d)``.

    Small products are fused element-wise code (:func:`_contract`). Larger ones (three
    cars: ``n = 18``) are dots, written with the contracted axis of the left operand
    leading: jaxlib 0.10's YNNPACK dot fusion does not take that layout, so XLA emits the
    dots itself and the recursion's loop can still be compiled into one kernel
    (:mod:`racing_env.xla_setup`; a YNNPACK fusion in the loop body prevents that).
    """
    if _is_fused("ibc,cd->ibd", M, Y):
        return _contract("ba,ibd->iad", X, _contract("ibc,cd->ibd", M, Y))
    MY_t = jax.lax.dot_general(Y, M, (((0,), (2,)), ((), ())))  # (d, N, n): (M^i Y)'
    XMY = jax.lax.dot_general(X, MY_t, (((0,), (2,)), ((), ())))  # (a, d, N)
    return jnp.transpose(XMY, (2, 0, 1))


def _inverse_small(M: Array) -> Array:
    """Inverse of ``(..., m, m)`` blocks: closed form (adjugate / determinant) for m <= 2."""
    m = M.shape[-1]
    if m == 1:
        return 1.0 / M
    if m == 2:
        a, b, c, d = M[..., 0, 0], M[..., 0, 1], M[..., 1, 0], M[..., 1, 1]
        adj = jnp.stack([jnp.stack([d, -b], -1), jnp.stack([-c, a], -1)], -2)
        return adj / (a * d - b * c)[..., None, None]
    return jnp.linalg.inv(M)


def block_solve(S: Array, rhs: Array, contract: Callable[..., Array] | None = None) -> Array:
    """Solve ``sum_j S[i, :, j, :] X[j] = rhs[i]`` by block Gauss-Jordan elimination.

    Args:
      S: ``(N, m, N, m)``, the ``(N m) x (N m)`` matrix in ``m x m`` blocks.
      rhs: ``(N, m, k)``.

    Returns:
      ``X (N, m, k)``.

    The pivots are the diagonal blocks in order, inverted in closed form for ``m <= 2``
    (no pivoting within or between blocks). It is meant for the players' coupled
    first-order conditions of a feedback LQ game, whose diagonal blocks
    ``R^{ii} + B^i' P^i B^i`` are positive definite when ``P^i >= 0``: the first pivot is
    then always regular, and for ``N = 2`` the second is the Schur complement, regular
    exactly when ``S`` is. For general matrices use ``jnp.linalg.solve``. ``contract``
    computes its products (default :func:`_contract`, fused element-wise code).
    """
    c = _contract if contract is None else contract
    N, m = S.shape[0], S.shape[1]
    M = jnp.concatenate([S.reshape(N, m, N * m), rhs], axis=-1)  # (N, m, N m + k)
    for b in range(N):
        row = c("ab,bw->aw", _inverse_small(M[b, :, b * m:(b + 1) * m]), M[b])
        M = M - c("iab,bw->iaw", M[:, :, b * m:(b + 1) * m], row)
        M = M.at[b].set(row)
    return M[..., N * m:]


# Above this size a LAPACK solve beats the unrolled elimination even inside a loop kernel.
_PIVOTED_SOLVE_MAX = 8


def pivoted_solve(S: Array, rhs: Array) -> Array:
    """Solve ``S X = rhs`` by Gauss-Jordan elimination with partial (row) pivoting.

    Args:
      S: ``(p, p)``, any regular matrix. rhs: ``(p, k)``.

    Returns:
      ``X (p, k)``.

    The same method as LAPACK's LU solve, written as ``p`` unrolled elimination steps of
    element-wise code for the small systems of the LQ recursions (``p = N m``). A LAPACK
    call is an XLA custom call, and a loop that contains one cannot be compiled into a
    single kernel (:mod:`racing_env.xla_setup`); this elimination can. Systems larger than
    ``_PIVOTED_SOLVE_MAX`` go to ``jnp.linalg.solve``. A singular ``S`` gives non-finite
    entries.
    """
    p = S.shape[-1]
    if p > _PIVOTED_SOLVE_MAX:
        return jnp.linalg.solve(S, rhs)
    M = jnp.concatenate([S, rhs], axis=-1)  # (p, p + k)
    rows = jnp.arange(p)
    for j in range(p):
        # Pivot: the largest |entry| of column j among the rows not yet eliminated; swap
        # it into row j (one-hot arithmetic: no data-dependent indexing).
        candidates = jnp.where(rows >= j, jnp.abs(M[:, j]), -1.0)
        at_pivot = jax.nn.one_hot(jnp.argmax(candidates), p, dtype=M.dtype)[:, None]
        pivot_row = jnp.sum(at_pivot * M, axis=0)
        M = M + at_pivot * (M[j] - pivot_row)[None, :]
        # Eliminate column j from every other row (Gauss-Jordan); the scaled pivot row is row j.
        pivot_row = pivot_row / pivot_row[j]
        M = M - jnp.where(rows == j, 0.0, M[:, j])[:, None] * pivot_row[None, :]
        M = M.at[j].set(pivot_row)
    return M[:, p:]


def _feedback_own_step(N: int, n: int, m: int, dtype: Any, feedforward_regularization: Array | float | None,
                       contract: Callable[..., Array], sandwich: Callable[[Array, Array, Array], Array]) -> Callable:
    """One backward stage of :func:`solve_feedback_own`'s recursion for one game, as a
    ``lax.scan`` body ``((P, p), stage) -> ((P, p), (K, k))``, with its products computed by
    ``contract(spec, *operands)`` and ``X' M^i Y`` by ``sandwich(X, M, Y)``: fused
    element-wise code for one game (:func:`_contract`, :func:`_sandwich`), dots in the batched
    form (:func:`solve_feedback_own_batched`, where ``vmap`` makes them batched products)."""
    eye_N = jnp.eye(N, dtype=dtype)
    c = contract
    # lambda I on the own blocks for the feed-forward rows, made once, in the weights' dtype
    # (a float64 lambda must not promote a float32 recursion)
    lam_I = (None if feedforward_regularization is None
             else jnp.asarray(feedforward_regularization, dtype)
             * eye_N[:, None, :, None] * jnp.eye(m, dtype=dtype)[None, :, None, :])

    def gains(S, rhs_K, rhs_k):
        if lam_I is None:
            sol = block_solve(S, jnp.concatenate([rhs_K, rhs_k[..., None]], axis=-1), contract)
            return sol[..., :n], sol[..., n]
        return block_solve(S, rhs_K, contract), block_solve(S + lam_I, rhs_k[..., None], contract)[..., 0]

    def step(carry, stage):
        P, p = carry  # (N, n, n), (N, n) at t+1
        A_t, B_t, Q_t, q_t, R_t, r_t = stage
        BtP = c("iam,iab->imb", B_t, P)  # B^i' P^i
        S = c("imb,jbl->imjl", BtP, B_t) + eye_N[:, None, :, None] * R_t[:, :, None, :]
        rhs_K = c("imb,bc->imc", BtP, A_t)
        rhs_k = c("iam,ia->im", B_t, p) + r_t
        K, k = gains(S, rhs_K, rhs_k)
        F = A_t - c("jam,jmb->ab", B_t, K)  # closed-loop dynamics
        beta = -c("jam,jm->a", B_t, k)  # closed-loop drift
        P_new = (
            Q_t
            + sandwich(F, P, F)
            + c("ima,imb->iab", K, c("iml,ilb->imb", R_t, K))
        )
        p_new = (
            q_t
            + c("ba,ib->ia", F, p + c("iab,b->ia", P, beta))
            + c("ima,im->ia", K, c("iml,il->im", R_t, k) - r_t)
        )
        return (_sym(P_new), p_new), (K, k)

    return step


def _feedback_own_recursion(A, B, Q, q, Rii, rii, feedforward_regularization=None):
    """The recursion of :func:`solve_feedback_own` for one game: small products as fused
    element-wise code (:func:`_contract`), the coupled gains by :func:`block_solve`."""
    N, n, m = B.shape[1], B.shape[2], B.shape[3]
    Q, Rii = _sym(Q), _sym(Rii)
    step = _feedback_own_step(N, n, m, Rii.dtype, feedforward_regularization, _contract, _sandwich)
    stages = (A, B, Q[:-1], q[:-1], Rii, rii)
    _, (K, k) = jax.lax.scan(step, (Q[-1], q[-1]), stages, reverse=True)
    return K, k


def _dot_sandwich(X: Array, M: Array, Y: Array) -> Array:
    """``X' M^i Y`` for every player as dots (the batched form's :func:`_sandwich`)."""
    return jnp.einsum("ba,ibc,cd->iad", X, M, Y)


@jax.jit
def solve_feedback_own_batched(
    A: Array, B: Array, Q: Array, q: Array, Rii: Array, rii: Array,
    feedforward_regularization: Array | float | None = None,
) -> tuple[Array, Array]:
    """:func:`solve_feedback_own` for a batch of games at once: every array has a leading
    batch axis (``A (Z, T, n, n)``, ``B (Z, T, N, n, m)``, ``Q (Z, T+1, N, n, n)``,
    ``q (Z, T+1, N, n)``, ``Rii (Z, T, N, m, m)``, ``rii (Z, T, N, m)``; returns
    ``K (Z, T, N, m, n)``, ``k (Z, T, N, m)``), ``feedforward_regularization`` shared.

    The layout of the batch: one ``lax.scan`` over the stages whose body works on all ``Z``
    games, every product a batched dot (``dot_general`` with the games as a batch
    dimension) instead of the fused element-wise code one game runs, so that a stage is a
    few batched matrix products rather than ``Z`` small recursions one after another (what
    ``jax.vmap`` of :func:`solve_feedback_own` does). Equal to the per-game form to rounding
    (tests/test_lq_game.py); which is faster is a property of the machine:
    ``racing bench --only solvers`` times both (docs/performance.md).
    """
    N, n, m = B.shape[2], B.shape[3], B.shape[4]
    Q, Rii = _sym(Q), _sym(Rii)
    step = jax.vmap(_feedback_own_step(N, n, m, Rii.dtype, feedforward_regularization, jnp.einsum, _dot_sandwich))
    stages = tuple(jnp.swapaxes(a, 0, 1) for a in (A, B, Q[:, :-1], q[:, :-1], Rii, rii))  # stages leading
    _, (K, k) = jax.lax.scan(step, (Q[:, -1], q[:, -1]), stages, reverse=True)
    return jnp.swapaxes(K, 0, 1), jnp.swapaxes(k, 0, 1)


_feedback_own = one_at_a_time(_feedback_own_recursion)


@jax.jit
def solve_feedback_own(
    A: Array, B: Array, Q: Array, q: Array, Rii: Array, rii: Array,
    feedforward_regularization: Array | float | None = None,
) -> tuple[Array, Array]:
    """Feedback Nash equilibrium of an LQ game whose input costs are on own inputs only.

    The game of :func:`solve_feedback` with ``R^{ij} = 0, r^{ij} = 0`` for ``i != j``
    (player i's cost involves only its own input, as in every iterative LQ game of
    :mod:`planners.ilq`); ``R[t, i, i] = Rii[t, i]``, ``r[t, i, i] = rii[t, i]``. Same
    recursion and result as :func:`solve_feedback`, but the coupled first-order conditions
    are solved by :func:`block_solve` (the players' own blocks
    ``R^{ii} + B^i' P^i B^i`` as pivots) instead of a pivoting LAPACK solve, and small
    products are fused element-wise code: several times faster for the sizes of the
    racing games, where the per-operation overhead of XLA on CPU dominates. Under
    ``jax.vmap`` the games of the batch are solved one after another (``lax.map``), the
    fastest of the batched forms on CPU.

    Requirements: ``Q_t^i >= 0`` and ``R_t^{ii} > 0`` (then every ``P_t^i >= 0`` and the
    pivots ``R^{ii} + B^i' P^i B^i`` are positive definite); a singular Schur complement
    (an LQ game without a unique feedback equilibrium) gives non-finite gains.
    ``feedforward_regularization`` damps the feed-forward terms only, as in
    :func:`solve_feedback`.

    Args:
      A: ``(T, n, n)``. B: ``(T, N, n, m)``. Q: ``(T+1, N, n, n)``. q: ``(T+1, N, n)``.
      Rii: ``(T, N, m, m)``. rii: ``(T, N, m)``.
      feedforward_regularization: ``lambda >= 0`` (scalar) or None (the equilibrium).

    Returns:
      ``K (T, N, m, n)`` and ``k (T, N, m)``; equilibrium strategies
      ``u_t^i = -K_t^i x_t - k_t^i``.
    """
    if feedforward_regularization is None:
        return _feedback_own(A, B, Q, q, Rii, rii)
    return _feedback_own(A, B, Q, q, Rii, rii, feedforward_regularization)


@jax.jit
def lq_rollout_feedback(
    A: Array, B: Array, K: Array, k: Array, x0: Array
) -> tuple[Array, Array]:
    """Roll out the affine feedback strategies ``u_t^i = -K_t^i x_t - k_t^i`` from ``x0``.

    Args:
      A: ``(T, n, n)``. B: ``(T, N, n, m)``. K: ``(T, N, m, n)``. k: ``(T, N, m)``.
      x0: ``(n,)``.

    Returns:
      ``xs (T+1, n)`` and ``us (T, N, m)``.
    """

    def step(x, stage):
        A_t, B_t, K_t, k_t = stage
        u = -(K_t @ x) - k_t  # (N, m)
        x_next = A_t @ x + jnp.einsum("jam,jm->a", B_t, u)
        return x_next, (x, u)

    xT, (xs, us) = jax.lax.scan(step, x0, (A, B, K, k))
    return jnp.concatenate([xs, xT[None]], axis=0), us


# --------------------------------------------------------------------------------------
# Open-loop Nash equilibrium.
# --------------------------------------------------------------------------------------


@jax.jit
def solve_open_loop(
    A: Array, B: Array, Q: Array, q: Array, R: Array, r: Array, x0: Array
) -> tuple[Array, Array]:
    """Open-loop Nash equilibrium of an LQ game from ``x0`` (under ``jax.vmap``: one game after another).

    Player ``i``'s stationarity in its own input, with costate ``lambda_t^i``::

        u_t^i = -(R^{ii})^{-1} (B^i' lambda_{t+1}^i + r^{ii}),
        lambda_t^i = Q_t^i x_t + q_t^i + A_t' lambda_{t+1}^i,  lambda_T^i = Q_T^i x_T + q_T^i.

    With the ansatz ``lambda_t^i = M_t^i x_t + m_t^i`` the dynamics become
    ``Lambda_t x_{t+1} = A_t x_t - c_t`` with::

        Lambda_t = I + sum_j B^j (R^{jj})^{-1} B^j' M_{t+1}^j
        c_t      = sum_j B^j (R^{jj})^{-1} (B^j' m_{t+1}^j + r^{jj})
        M_t^i    = Q_t^i + A' M_{t+1}^i Lambda_t^{-1} A
        m_t^i    = q_t^i + A' (m_{t+1}^i - M_{t+1}^i Lambda_t^{-1} c_t)

    Only ``R^{ii}, r^{ii}`` matter: the cross terms are constants for player ``i``'s own
    decision. Each player's problem is convex if ``Q^i >= 0`` and ``R^{ii} > 0``, so the
    conditions are sufficient; the equilibrium is unique iff every ``Lambda_t`` is invertible.

    Args:
      A: ``(T, n, n)``. B: ``(T, N, n, m)``. Q: ``(T+1, N, n, n)``. q: ``(T+1, N, n)``.
      R: ``(T, N, N, m, m)``. r: ``(T, N, N, m)``. x0: ``(n,)``.

    Returns:
      ``k (T, N, m)`` (equilibrium inputs ``u_t^i = -k_t^i``) and the equilibrium state
      trajectory ``xs (T+1, n)``.
    """
    return _open_loop(A, B, Q, q, R, r, x0)


def _open_loop_recursion(A, B, Q, q, R, r, x0):
    """The recursions of :func:`solve_open_loop` for one game."""
    n = A.shape[-1]
    Q, R = _sym(Q), _sym(R)

    def backward(carry, stage):
        M, mm = carry  # (N, n, n), (N, n) at t+1
        A_t, B_t, Q_t, q_t, R_t, r_t = stage
        # (R^{jj})^{-1} [B^j', r^{jj}] in one batched solve: (N, m, n + 1).
        Rinv = jnp.linalg.solve(
            _own(R_t), jnp.concatenate([jnp.swapaxes(B_t, -1, -2), _own(r_t)[..., None]], -1)
        )
        RinvBt, Rinv_r = Rinv[..., :n], Rinv[..., n]
        Lam = jnp.eye(n, dtype=A_t.dtype) + jnp.einsum("jam,jmb,jbc->ac", B_t, RinvBt, M)
        c = jnp.einsum("jam,jm->a", B_t, jnp.einsum("jmb,jb->jm", RinvBt, mm) + Rinv_r)
        # Lambda may be non-symmetric: solve once for [Lambda^{-1} A, Lambda^{-1} c].
        LinvAc = jnp.linalg.solve(Lam, jnp.concatenate([A_t, c[:, None]], axis=1))
        LinvA, Linvc = LinvAc[:, :n], LinvAc[:, n]
        M_new = Q_t + jnp.einsum("ba,ibc,cd->iad", A_t, M, LinvA)
        m_new = q_t + jnp.einsum("ba,ib->ia", A_t, mm - M @ Linvc)
        return (M_new, m_new), (Lam, c, M, mm, RinvBt, Rinv_r)

    stages = (A, B, Q[:-1], q[:-1], R, r)
    _, (Lam, c, M_next, m_next, RinvBt, Rinv_r) = jax.lax.scan(
        backward, (Q[-1], q[-1]), stages, reverse=True
    )

    def forward(x, stage):
        A_t, Lam_t, c_t, M_t1, m_t1, RinvBt_t, Rinv_r_t = stage
        x_next = jnp.linalg.solve(Lam_t, A_t @ x - c_t)
        lam_next = M_t1 @ x_next + m_t1  # costates lambda_{t+1}^i, (N, n)
        k_t = jnp.einsum("imb,ib->im", RinvBt_t, lam_next) + Rinv_r_t
        return x_next, (x_next, k_t)

    _, (xs_next, k) = jax.lax.scan(forward, x0, (A, Lam, c, M_next, m_next, RinvBt, Rinv_r))
    xs = jnp.concatenate([x0[None], xs_next], axis=0)
    return k, xs


_open_loop = one_at_a_time(_open_loop_recursion)


def _open_loop_own_recursion(A, B, Q, q, Rii, rii, x0):
    """The recursion of :func:`solve_open_loop_own` for one game (see its docstring)."""
    N, n, m = B.shape[1], B.shape[2], B.shape[3]
    Q, Rii = _sym(Q), _sym(Rii)
    eye_Nm = jnp.eye(N * m, dtype=Rii.dtype).reshape(N, m, N, m)
    c = _contract

    def backward(carry, stage):
        M, mm = carry  # (N, n, n), (N, n) at t+1
        A_t, B_t, Q_t, q_t, R_t, r_t = stage
        Rinv = _inverse_small(R_t)  # (N, m, m)
        W = c("iml,ial,iab->imb", Rinv, B_t, M)  # (R^{ii})^{-1} B^i' M^i, (N, m, n)
        g = c("iml,ial,ia->im", Rinv, B_t, mm) + c("iml,il->im", Rinv, r_t)
        # Lambda = I + Bbar W with Bbar = [B^1 .. B^N] (n, N m), W stacked (N m, n), so by
        # the Woodbury identity Lambda^{-1} X = X - Bbar (I + W Bbar)^{-1} W X.
        Ac = jnp.concatenate([A_t, c("jam,jm->a", B_t, g)[:, None]], axis=1)  # [A, c_t]
        S = (eye_Nm + c("imb,jbl->imjl", W, B_t)).reshape(N * m, N * m)
        Y = pivoted_solve(S, c("imb,bw->imw", W, Ac).reshape(N * m, n + 1))
        LinvAc = Ac - c("jam,jmw->aw", B_t, Y.reshape(N, m, n + 1))
        LinvA, Linvc = LinvAc[:, :n], LinvAc[:, n]
        M_new = Q_t + _sandwich(A_t, M, LinvA)
        m_new = q_t + c("ba,ib->ia", A_t, mm - c("iab,b->ia", M, Linvc))
        return (M_new, m_new), (LinvA, Linvc, W, g)

    stages = (A, B, Q[:-1], q[:-1], Rii, rii)
    _, (LinvA, Linvc, W, g) = jax.lax.scan(backward, (Q[-1], q[-1]), stages, reverse=True)

    def forward(x, stage):
        LinvA_t, Linvc_t, W_t, g_t = stage
        x_next = c("ab,b->a", LinvA_t, x) - Linvc_t
        # k_t^i = R^{-1} (B^i' lambda_{t+1}^i + r^i), lambda_{t+1}^i = M^i x_{t+1} + m^i.
        return x_next, (x_next, c("imb,b->im", W_t, x_next) + g_t)

    _, (xs_next, k) = jax.lax.scan(forward, x0, (LinvA, Linvc, W, g))
    return k, jnp.concatenate([x0[None], xs_next], axis=0)


_open_loop_own = one_at_a_time(_open_loop_own_recursion)


@jax.jit
def solve_open_loop_own(
    A: Array, B: Array, Q: Array, q: Array, Rii: Array, rii: Array, x0: Array
) -> tuple[Array, Array]:
    """Open-loop Nash equilibrium of an LQ game whose input costs are on own inputs only.

    The game of :func:`solve_open_loop` with ``R[t, i, i] = Rii[t, i]``,
    ``r[t, i, i] = rii[t, i]`` (the cross terms do not enter an open-loop equilibrium
    anyway). The same conditions and result, computed without ``n x n`` solves:

    * ``Lambda_t = I + sum_j B^j (R^{jj})^{-1} B^j' M_{t+1}^j = I + Bbar W`` with
      ``Bbar = [B^1 .. B^N]`` and ``W^j = (R^{jj})^{-1} B^j' M_{t+1}^j`` stacked, so the
      Woodbury identity gives ``Lambda^{-1} X = X - Bbar (I + W Bbar)^{-1} W X``: one
      ``(N m) x (N m)`` solve per stage instead of an ``n x n`` one (``Lambda`` and
      ``I + W Bbar`` are regular together, by Sylvester's determinant identity), by
      :func:`pivoted_solve` (no LAPACK call: the recursion compiles into one loop kernel);
    * the ``m x m`` blocks ``R^{jj}`` are inverted in closed form for ``m <= 2``;
    * the forward pass reuses ``Lambda^{-1} A``, ``Lambda^{-1} c`` and
      ``k_t^i = W^i x_{t+1} + (R^{ii})^{-1} (B^i' m_{t+1}^i + r^{ii})``: no solves at all.

    Small products are fused element-wise code, as in :func:`solve_feedback_own`; under
    ``jax.vmap`` the games are solved one after another.

    Args:
      A: ``(T, n, n)``. B: ``(T, N, n, m)``. Q: ``(T+1, N, n, n)``. q: ``(T+1, N, n)``.
      Rii: ``(T, N, m, m)``. rii: ``(T, N, m)``. x0: ``(n,)``.

    Returns:
      ``k (T, N, m)`` (equilibrium inputs ``u_t^i = -k_t^i``) and the equilibrium state
      trajectory ``xs (T+1, n)``.
    """
    return _open_loop_own(A, B, Q, q, Rii, rii, x0)


# --------------------------------------------------------------------------------------
# Costs and single-player LQR.
# --------------------------------------------------------------------------------------


@jax.jit
def lq_costs(
    A: Array, B: Array, Q: Array, q: Array, R: Array, r: Array, xs: Array, us: Array
) -> Array:
    """Total cost of every player along a trajectory.

    ``A`` and ``B`` are not used (the trajectory is taken as given); they are accepted so
    that the game tuple can be passed whole.

    Args:
      A: ``(T, n, n)``. B: ``(T, N, n, m)``. Q: ``(T+1, N, n, n)``. q: ``(T+1, N, n)``.
      R: ``(T, N, N, m, m)``. r: ``(T, N, N, m)``. xs: ``(T+1, n)``. us: ``(T, N, m)``.

    Returns:
      ``(N,)`` costs ``J^i`` as defined in the module docstring.
    """
    del A, B
    state = 0.5 * jnp.einsum("ta,tiab,tb->i", xs, Q, xs) + jnp.einsum("tia,ta->i", q, xs)
    inputs = 0.5 * jnp.einsum("tjm,tijml,tjl->i", us, R, us) + jnp.einsum(
        "tijm,tjm->i", r, us
    )
    return state + inputs


@jax.jit
def lqr(A: Array, B: Array, Q: Array, q: Array, R: Array, r: Array) -> tuple[Array, Array]:
    """Single-player finite-horizon discrete LQR with linear cost terms.

    Minimises ``1/2 sum_t [x'Qx + 2q'x + u'Ru + 2r'u] + 1/2 x_T'Q_T x_T + q_T'x_T`` subject to
    ``x_{t+1} = A x + B u`` by the standard difference Riccati equation::

        H = R + B'PB,  K = H^{-1} B'PA,  k = H^{-1} (B'p + r)
        P_t = Q + A'PA - K'HK,           p_t = q + A'p - K'(B'p + r)

    Args:
      A: ``(T, n, n)``. B: ``(T, n, m)``. Q: ``(T+1, n, n)``. q: ``(T+1, n)``.
      R: ``(T, m, m)``. r: ``(T, m)``.

    Returns:
      ``K (T, m, n)`` and ``k (T, m)``; optimal policy ``u_t = -K_t x_t - k_t``.
    """
    n = A.shape[-1]
    Q, R = _sym(Q), _sym(R)

    def step(carry, stage):
        P, p = carry
        A_t, B_t, Q_t, q_t, R_t, r_t = stage
        H = R_t + B_t.T @ P @ B_t
        g = B_t.T @ p + r_t
        sol = jnp.linalg.solve(H, jnp.concatenate([B_t.T @ P @ A_t, g[:, None]], axis=1))
        K, k = sol[:, :n], sol[:, n]
        P_new = Q_t + A_t.T @ P @ A_t - K.T @ H @ K
        p_new = q_t + A_t.T @ p - K.T @ g
        return (_sym(P_new), p_new), (K, k)

    _, (K, k) = jax.lax.scan(step, (Q[-1], q[-1]), (A, B, Q[:-1], q[:-1], R, r), reverse=True)
    return K, k
