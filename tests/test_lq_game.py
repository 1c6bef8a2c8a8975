"""Exact-identity tests for the LQ game solvers (float64, 1e-8).

Nash equilibria are checked by best responses: fixing the other players' equilibrium
strategies leaves player ``i`` a single-player LQ problem, solved here by oracles written
independently in NumPy (an affine-drift Riccati recursion for feedback, a dense
normal-equation solve over the stacked inputs for open loop).
"""

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402

from planners.lq_game import (  # noqa: E402
    lq_costs,
    lq_rollout_feedback,
    lqr,
    solve_feedback,
    solve_open_loop,
    validate_lq_game,
)

TOL = 1e-8


def rel_gap(a, b) -> float:
    a, b = np.asarray(a), np.asarray(b)
    return float(np.max(np.abs(a - b)) / max(1.0, float(np.max(np.abs(b)))))


def random_game(seed: int, N: int, T: int = 8, n: int = 4, m: int = 2, linear: bool = True):
    """A random, time-varying, well-posed LQ game as NumPy arrays (A, B, Q, q, R, r)."""
    rng = np.random.default_rng(seed)
    A = 0.95 * np.eye(n) + 0.15 * rng.standard_normal((T, n, n))
    B = 0.5 * rng.standard_normal((T, N, n, m))
    L = rng.standard_normal((T + 1, N, n, n))
    Q = np.einsum("tiab,ticb->tiac", L, L) / n  # PSD
    R = np.zeros((T, N, N, m, m))
    for t in range(T):
        for i in range(N):
            for j in range(N):
                G = rng.standard_normal((m, m))
                if i == j:
                    R[t, i, j] = G @ G.T / m + 0.5 * np.eye(m)  # PD
                else:
                    R[t, i, j] = 0.1 * (G + G.T)  # symmetric, possibly indefinite
    if linear:
        q = 0.5 * rng.standard_normal((T + 1, N, n))
        r = 0.3 * rng.standard_normal((T, N, N, m))
    else:
        q = np.zeros((T + 1, N, n))
        r = np.zeros((T, N, N, m))
    return A, B, Q, q, R, r


def random_x0(seed: int, n: int = 4) -> np.ndarray:
    return np.random.default_rng(seed + 1000).standard_normal(n)


# ------------------------------------------------------------------------------------
# NumPy oracles.
# ------------------------------------------------------------------------------------


def riccati_affine(A, B, c, Q, q, R, r):
    """min 1/2 sum [x'Qx + 2q'x + u'Ru + 2r'u] + terminal, x+ = A x + B u + c.

    A (T,n,n), B (T,n,m), c (T,n), Q (T+1,n,n), q (T+1,n), R (T,m,m), r (T,m).
    Returns K (T,m,n), k (T,m) with u = -K x - k.
    """
    T = A.shape[0]
    P, p = Q[T], q[T]
    Ks, ks = [], []
    for t in reversed(range(T)):
        H = R[t] + B[t].T @ P @ B[t]
        g = B[t].T @ (P @ c[t] + p) + r[t]
        K = np.linalg.solve(H, B[t].T @ P @ A[t])
        k = np.linalg.solve(H, g)
        p = q[t] + A[t].T @ (p + P @ c[t]) - K.T @ g
        P = Q[t] + A[t].T @ P @ A[t] - K.T @ H @ K
        P = 0.5 * (P + P.T)
        Ks.append(K)
        ks.append(k)
    return np.array(Ks[::-1]), np.array(ks[::-1])


def feedback_best_response(game, K, k, i):
    """Player i's optimal affine policy against the others' feedback laws."""
    A, B, Q, q, R, r = game
    T, N = B.shape[0], B.shape[1]
    others = [j for j in range(N) if j != i]
    A_cl = A - sum((B[:, j] @ K[:, j] for j in others), np.zeros_like(A))
    c = -sum((np.einsum("tam,tm->ta", B[:, j], k[:, j]) for j in others), np.zeros(A.shape[:2]))
    Qi, qi = Q[:, i].copy(), q[:, i].copy()
    for j in others:
        # u^j = -(K^j x + k^j): 1/2 u'R u + r'u = 1/2 x'K'RKx + x'(K'Rk - K'r) + const.
        Kj, kj, Rij, rij = K[:, j], k[:, j], R[:, i, j], r[:, i, j]
        Qi[:T] += np.einsum("tma,tml,tlb->tab", Kj, Rij, Kj)
        qi[:T] += np.einsum("tma,tml,tl->ta", Kj, Rij, kj) - np.einsum("tma,tm->ta", Kj, rij)
    return riccati_affine(A_cl, B[:, i], c, Qi, qi, R[:, i, i], r[:, i, i])


def stacked_dynamics(A, B):
    """x = Phi x0 + sum_j Gamma[j] U_j with x ((T+1) n,), U_j (T m,) time-major."""
    T, N, n, m = B.shape
    Phi = np.zeros(((T + 1) * n, n))
    Gam = np.zeros((N, (T + 1) * n, T * m))
    Phi[:n] = np.eye(n)
    for t in range(T):
        rows, nxt = slice(t * n, (t + 1) * n), slice((t + 1) * n, (t + 2) * n)
        Phi[nxt] = A[t] @ Phi[rows]
        Gam[:, nxt] = np.einsum("ab,jbc->jac", A[t], Gam[:, rows])
        Gam[:, nxt, t * m : (t + 1) * m] = B[t]
    return Phi, Gam


def block_diag(blocks):
    k, a, b = blocks.shape
    out = np.zeros((k * a, k * b))
    for s in range(k):
        out[s * a : (s + 1) * a, s * b : (s + 1) * b] = blocks[s]
    return out


def open_loop_best_response(game, x0, k, i):
    """Player i's optimal input sequence (T, m) against the others' fixed u^j = -k^j.

    Also returns the Hessian of J^i in U_i (to check convexity and second-order identities).
    """
    A, B, Q, q, R, r = game
    T, N, n, m = B.shape
    Phi, Gam = stacked_dynamics(A, B)
    Qbd, qbd = block_diag(Q[:, i]), q[:, i].reshape(-1)
    Rbd, rbd = block_diag(R[:, i, i]), r[:, i, i].reshape(-1)
    x_fixed = Phi @ x0 + sum(Gam[j] @ (-k[:, j].reshape(-1)) for j in range(N) if j != i)
    H = Gam[i].T @ Qbd @ Gam[i] + Rbd
    g = Gam[i].T @ (Qbd @ x_fixed + qbd) + rbd
    return -np.linalg.solve(H, g).reshape(T, m), H


def as_np(*arrays):
    return tuple(np.asarray(a) for a in arrays)


CASES = [(N, linear) for N in (1, 2, 3) for linear in (True, False)]


# ------------------------------------------------------------------------------------
# Nash conditions.
# ------------------------------------------------------------------------------------


@pytest.mark.parametrize("N,linear", CASES)
def test_feedback_is_best_response(N, linear):
    game = random_game(seed=10 * N + linear, N=N, T=7, linear=linear)
    K, k = as_np(*solve_feedback(*game))
    T, _, n, m = game[1].shape
    assert K.shape == (T, N, m, n) and k.shape == (T, N, m)
    for i in range(N):
        K_br, k_br = feedback_best_response(game, K, k, i)
        assert rel_gap(K[:, i], K_br) < TOL, (i, rel_gap(K[:, i], K_br))
        assert rel_gap(k[:, i], k_br) < TOL, (i, rel_gap(k[:, i], k_br))
    if not linear:
        assert np.max(np.abs(k)) == 0.0


@pytest.mark.parametrize("N,linear", CASES)
def test_open_loop_is_best_response(N, linear):
    game = random_game(seed=100 + 10 * N + linear, N=N, T=9, linear=linear)
    x0 = random_x0(N)
    k, xs = as_np(*solve_open_loop(*game, jnp.asarray(x0)))
    T, _, n, m = game[1].shape
    assert k.shape == (T, N, m) and xs.shape == (T + 1, n)
    for i in range(N):
        u_br, H = open_loop_best_response(game, x0, k, i)
        assert np.linalg.eigvalsh(H).min() > 0  # player i's problem is strictly convex
        assert rel_gap(-k[:, i], u_br) < TOL, (i, rel_gap(-k[:, i], u_br))
    # xs is the trajectory generated by the equilibrium inputs.
    A, B = game[0], game[1]
    x = x0
    for t in range(T):
        assert rel_gap(xs[t], x) < TOL
        x = A[t] @ x - np.einsum("jam,jm->a", B[t], k[t])
    assert rel_gap(xs[T], x) < TOL


def test_open_loop_ignores_cross_input_weights():
    game = random_game(seed=7, N=3)
    A, B, Q, q, R, r = game
    eye = np.eye(3, dtype=bool)[None, :, :, None, None]
    R2 = np.where(eye, R, 5.0 * R)
    r2 = np.where(eye[..., 0], r, -3.0 * r)
    x0 = jnp.asarray(random_x0(7))
    k1, xs1 = solve_open_loop(*game, x0)
    k2, xs2 = solve_open_loop(A, B, Q, q, R2, r2, x0)
    assert rel_gap(k1, k2) < TOL and rel_gap(xs1, xs2) < TOL


@pytest.mark.parametrize("N", [2, 3])
def test_lq_costs_second_order_identity(N):
    """J^i(U* + d) - J^i(U*) = 1/2 d'H d at an open-loop Nash point: checks lq_costs and
    first-order optimality together (no linear term in d)."""
    game = random_game(seed=300 + N, N=N)
    x0 = random_x0(300 + N)
    k, _ = solve_open_loop(*game, jnp.asarray(x0))
    A, B = game[0], game[1]
    K0 = jnp.zeros(k.shape + (A.shape[-1],))
    xs, us = lq_rollout_feedback(A, B, K0, k, jnp.asarray(x0))
    J = np.asarray(lq_costs(*game, xs, us))
    rng = np.random.default_rng(N)
    for i in range(N):
        _, H = open_loop_best_response(game, x0, np.asarray(k), i)
        d = rng.standard_normal((k.shape[0], k.shape[2]))
        kp = np.asarray(k).copy()
        kp[:, i] -= d  # u^i = -k^i + d
        xs_p, us_p = lq_rollout_feedback(A, B, K0, jnp.asarray(kp), jnp.asarray(x0))
        Jp = np.asarray(lq_costs(*game, xs_p, us_p))
        expected = 0.5 * d.reshape(-1) @ H @ d.reshape(-1)
        assert abs((Jp[i] - J[i]) - expected) < TOL * max(1.0, abs(expected), abs(J[i]))


def test_feedback_rollout_and_costs_match_dense():
    game = random_game(seed=42, N=2)
    A, B, Q, q, R, r = game
    K, k = solve_feedback(*game)
    x0 = random_x0(42)
    xs, us = as_np(*lq_rollout_feedback(A, B, K, k, jnp.asarray(x0)))
    T, N = B.shape[:2]
    Phi, Gam = stacked_dynamics(A, B)
    x_dense = Phi @ x0 + sum(Gam[j] @ us[:, j].reshape(-1) for j in range(N))
    assert rel_gap(xs.reshape(-1), x_dense) < TOL
    J = np.asarray(lq_costs(*game, jnp.asarray(xs), jnp.asarray(us)))
    for i in range(N):
        Ji = sum(
            0.5 * xs[t] @ Q[t, i] @ xs[t] + q[t, i] @ xs[t]
            + sum(0.5 * us[t, j] @ R[t, i, j] @ us[t, j] + r[t, i, j] @ us[t, j] for j in range(N))
            for t in range(T)
        ) + 0.5 * xs[T] @ Q[T, i] @ xs[T] + q[T, i] @ xs[T]
        assert abs(J[i] - Ji) < TOL * max(1.0, abs(Ji))


# ------------------------------------------------------------------------------------
# Single player: all three solvers agree.
# ------------------------------------------------------------------------------------


@pytest.mark.parametrize("linear", [True, False])
def test_single_player_solvers_agree(linear):
    A, B, Q, q, R, r = random_game(seed=5 + linear, N=1, T=10, linear=linear)
    x0 = jnp.asarray(random_x0(5))
    K_lqr, k_lqr = lqr(A, B[:, 0], Q[:, 0], q[:, 0], R[:, 0, 0], r[:, 0, 0])
    K_fb, k_fb = solve_feedback(A, B, Q, q, R, r)
    assert rel_gap(K_fb[:, 0], K_lqr) < TOL and rel_gap(k_fb[:, 0], k_lqr) < TOL

    xs_lqr, us_lqr = lq_rollout_feedback(A, B, K_lqr[:, None], k_lqr[:, None], x0)
    xs_fb, us_fb = lq_rollout_feedback(A, B, K_fb, k_fb, x0)
    k_ol, xs_ol = solve_open_loop(A, B, Q, q, R, r, x0)
    assert rel_gap(xs_fb, xs_lqr) < TOL and rel_gap(xs_ol, xs_lqr) < TOL
    assert rel_gap(us_fb, us_lqr) < TOL and rel_gap(-k_ol, us_lqr) < TOL


def test_lqr_matches_affine_oracle():
    A, B, Q, q, R, r = random_game(seed=9, N=1, T=6)
    K, k = as_np(*lqr(A, B[:, 0], Q[:, 0], q[:, 0], R[:, 0, 0], r[:, 0, 0]))
    c = np.zeros(A.shape[:2])
    K_o, k_o = riccati_affine(A, B[:, 0], c, Q[:, 0], q[:, 0], R[:, 0, 0], r[:, 0, 0])
    assert rel_gap(K, K_o) < TOL and rel_gap(k, k_o) < TOL


def test_only_symmetric_parts_matter():
    game = random_game(seed=11, N=2)
    A, B, Q, q, R, r = game
    rng = np.random.default_rng(0)
    S = rng.standard_normal(Q.shape)
    W = rng.standard_normal(R.shape)
    Qs = Q + (S - np.swapaxes(S, -1, -2))
    Rs = R + (W - np.swapaxes(W, -1, -2))
    x0 = jnp.asarray(random_x0(11))
    for a, b in zip(solve_feedback(*game), solve_feedback(A, B, Qs, q, Rs, r)):
        assert rel_gap(a, b) < TOL
    for a, b in zip(solve_open_loop(*game, x0), solve_open_loop(A, B, Qs, q, Rs, r, x0)):
        assert rel_gap(a, b) < TOL


# ------------------------------------------------------------------------------------
# Validation.
# ------------------------------------------------------------------------------------


def test_validate_accepts_valid_game():
    validate_lq_game(*random_game(seed=1, N=3))


def test_validate_rejects_non_pd_own_weight():
    A, B, Q, q, R, r = random_game(seed=2, N=3)
    R = R.copy()
    R[4, 1, 1] = np.diag([1.0, -0.5])
    with pytest.raises(ValueError, match=r"R\[t=4, i=1, i=1\].*not positive definite"):
        validate_lq_game(A, B, Q, q, R, r)
    R[4, 1, 1] = np.zeros((2, 2))  # PSD but singular is rejected too
    with pytest.raises(ValueError, match=r"t=4, i=1"):
        validate_lq_game(A, B, Q, q, R, r)


def test_validate_rejects_shape_mismatch():
    A, B, Q, q, R, r = random_game(seed=3, N=2, T=5)
    with pytest.raises(ValueError, match=r"shape mismatch: Q has shape \(5, 2, 4, 4\)"):
        validate_lq_game(A, B, Q[:-1], q, R, r)
    with pytest.raises(ValueError, match=r"shape mismatch: r"):
        validate_lq_game(A, B, Q, q, R, r[:, :1])
    with pytest.raises(ValueError, match=r"R must have 5 dimensions"):
        validate_lq_game(A, B, Q, q, R[:, 0], r)
    with pytest.raises(ValueError, match=r"non-finite"):
        validate_lq_game(A * np.nan, B, Q, q, R, r)


# ------------------------------------------------------------------------------------
# jit / vmap.
# ------------------------------------------------------------------------------------


def test_jit_matches_eager():
    """The (jitted) public functions equal their un-jitted bodies and survive nested jit."""
    game = tuple(jnp.asarray(a) for a in random_game(seed=21, N=3, T=5))
    A, B, Q, q, R, r = game
    x0 = jnp.asarray(random_x0(21))
    lqr_args = (A, B[:, 0], Q[:, 0], q[:, 0], R[:, 0, 0], r[:, 0, 0])

    def run_all(raw: bool):
        f = (lambda fn: fn.__wrapped__) if raw else (lambda fn: fn)  # __wrapped__: no jit
        K, k = f(solve_feedback)(*game)
        xs, us = f(lq_rollout_feedback)(A, B, K, k, x0)
        J = f(lq_costs)(*game, xs, us)
        return (K, k, xs, us, J, *f(solve_open_loop)(*game, x0), *f(lqr)(*lqr_args))

    eager = run_all(raw=True)
    for jitted in (run_all(raw=False), jax.jit(run_all, static_argnums=0)(False)):
        for a, b in zip(eager, jitted):
            assert rel_gap(b, a) < TOL


def test_vmap_over_initial_states():
    game = tuple(jnp.asarray(a) for a in random_game(seed=22, N=2))
    A, B = game[0], game[1]
    x0s = jnp.asarray(np.random.default_rng(22).standard_normal((5, 4)))
    k_b, xs_b = jax.jit(jax.vmap(solve_open_loop, in_axes=(None,) * 6 + (0,)))(*game, x0s)
    K, k = solve_feedback(*game)
    roll = jax.vmap(lq_rollout_feedback, in_axes=(None, None, None, None, 0))
    xs_fb, us_fb = roll(A, B, K, k, x0s)
    costs = jax.vmap(lq_costs, in_axes=(None,) * 6 + (0, 0))(*game, xs_fb, us_fb)
    assert k_b.shape == (5,) + game[1].shape[:2] + (2,) and costs.shape == (5, 2)
    for b in range(5):
        k1, xs1 = solve_open_loop(*game, x0s[b])
        assert rel_gap(k_b[b], k1) < TOL and rel_gap(xs_b[b], xs1) < TOL
        xs2, us2 = lq_rollout_feedback(A, B, K, k, x0s[b])
        assert rel_gap(xs_fb[b], xs2) < TOL and rel_gap(us_fb[b], us2) < TOL
        assert rel_gap(costs[b], lq_costs(*game, xs2, us2)) < TOL


def test_vmap_over_games():
    games = [random_game(seed=30 + s, N=2, T=6) for s in range(4)]
    batch = tuple(jnp.asarray(np.stack(parts)) for parts in zip(*games))
    x0 = jnp.asarray(random_x0(30))
    K_b, k_b = jax.jit(jax.vmap(solve_feedback))(*batch)
    kol_b, xs_b = jax.vmap(solve_open_loop, in_axes=(0,) * 6 + (None,))(*batch, x0)
    A, B, Q, q, R, r = batch
    K_l, k_l = jax.vmap(lqr)(A, B[:, :, 0], Q[:, :, 0], q[:, :, 0], R[:, :, 0, 0], r[:, :, 0, 0])
    for s, game in enumerate(games):
        K, k = solve_feedback(*game)
        assert rel_gap(K_b[s], K) < TOL and rel_gap(k_b[s], k) < TOL
        kol, xs = solve_open_loop(*game, x0)
        assert rel_gap(kol_b[s], kol) < TOL and rel_gap(xs_b[s], xs) < TOL
        A_, B_, Q_, q_, R_, r_ = game
        K1, k1 = lqr(A_, B_[:, 0], Q_[:, 0], q_[:, 0], R_[:, 0, 0], r_[:, 0, 0])
        assert rel_gap(K_l[s], K1) < TOL and rel_gap(k_l[s], k1) < TOL


# ------------------------------------------------------------------------------------
# The own-input solver (planners.ilq's structure: R^{ij} = 0 for i != j) and its helpers.
# ------------------------------------------------------------------------------------

from planners.lq_game import (  # noqa: E402
    _PIVOTED_SOLVE_MAX,
    _contract,
    _sandwich,
    block_solve,
    pivoted_solve,
    solve_feedback_own,
    solve_open_loop_own,
)


@pytest.mark.parametrize("N,m", [(1, 2), (2, 1), (2, 2), (3, 2), (2, 3)])
def test_block_solve_matches_linalg_solve(N, m):
    rng = np.random.default_rng(N * 10 + m)
    S = rng.standard_normal((N, m, N, m))
    for i in range(N):  # PD diagonal blocks, as in the feedback first-order conditions
        G = rng.standard_normal((m, m))
        S[i, :, i, :] = G @ G.T + m * np.eye(m)
    rhs = rng.standard_normal((N, m, 7))
    X = np.asarray(block_solve(jnp.asarray(S), jnp.asarray(rhs)))
    ref = np.linalg.solve(S.reshape(N * m, N * m), rhs.reshape(N * m, 7)).reshape(N, m, 7)
    assert np.max(np.abs(X - ref)) < 1e-10


@pytest.mark.parametrize("p", [1, 2, 4, 6, _PIVOTED_SOLVE_MAX])
def test_pivoted_solve_is_backward_stable_where_elimination_needs_row_swaps(p):
    rng = np.random.default_rng(p)
    eps = np.finfo(float).eps
    for trial in range(50):
        S = rng.standard_normal((p, p))
        if p > 1 and trial % 2 == 0:
            S[0, 0] = 0.0  # elimination without row swaps would divide by zero here
        rhs = rng.standard_normal((p, 5))
        X = np.asarray(pivoted_solve(jnp.asarray(S), jnp.asarray(rhs)))
        # Partial pivoting is backward stable with growth factor <= 2^(p-1): the residual
        # is at most about p 2^(p-1) eps relative to |S| |X| + |rhs|.
        residual = np.max(np.abs(S @ X - rhs)) / (np.max(np.abs(S)) * np.max(np.abs(X)) + np.max(np.abs(rhs)))
        assert residual <= p * 2 ** (p - 1) * eps


def test_pivoted_solve_of_a_singular_system_is_not_finite_and_large_ones_use_lapack():
    X = pivoted_solve(jnp.asarray([[1.0, 2.0], [2.0, 4.0]]), jnp.ones((2, 1)))
    assert not np.all(np.isfinite(np.asarray(X)))
    rng = np.random.default_rng(0)
    p = _PIVOTED_SOLVE_MAX + 1
    S, rhs = rng.standard_normal((p, p)), rng.standard_normal((p, 2))
    np.testing.assert_array_equal(pivoted_solve(jnp.asarray(S), jnp.asarray(rhs)), jnp.linalg.solve(S, rhs))


@pytest.mark.parametrize("spec,shapes", [
    ("iam,iab->imb", [(2, 12, 2), (2, 12, 12)]),
    ("ba,ibd->iad", [(12, 12), (2, 12, 12)]),
    ("ba,ibd->iad", [(18, 18), (3, 18, 18)]),  # above the fused-product size: a dot
    ("ima,iml,ilb->iab", [(2, 2, 5), (2, 2, 2), (2, 2, 5)]),
    ("jam,jm->a", [(3, 4, 2), (3, 2)]),
])
def test_contract_matches_einsum(spec, shapes):
    rng = np.random.default_rng(len(spec))
    ops = [jnp.asarray(rng.standard_normal(s)) for s in shapes]
    np.testing.assert_allclose(_contract(spec, *ops), jnp.einsum(spec, *ops), rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("N, n", [(2, 12), (3, 18)])  # element-wise; dots in the loop-kernel layout
def test_sandwich_matches_einsum(N, n):
    rng = np.random.default_rng(n)
    X, Y = rng.standard_normal((n, n)), rng.standard_normal((n, n))
    M = rng.standard_normal((N, n, n))  # not symmetric: no symmetry may be assumed
    want = np.einsum("ba,ibc,cd->iad", X, M, Y)
    got = jax.jit(_sandwich)(jnp.asarray(X), jnp.asarray(M), jnp.asarray(Y))
    # float64 sums of n products of O(1) terms: rounding ~ n * eps * |terms|
    np.testing.assert_allclose(got, want, rtol=0, atol=n * 1e-14 * np.abs(want).max())


def own_input_game(seed: int, N: int, T: int = 8, n: int = 4, m: int = 2):
    A, B, Q, q, R, r = random_game(seed, N=N, T=T, n=n, m=m)
    eye = np.eye(N, dtype=bool)[None, :, :, None, None]
    R = np.where(eye, R, 0.0)  # no cross-input weights
    r = np.where(eye[..., 0], r, 0.0)
    idx = np.arange(N)
    return (A, B, Q, q, R, r), (A, B, Q, q, R[:, idx, idx], r[:, idx, idx])


# n = 18 with three players: the recursion's largest products are dots (_sandwich).
@pytest.mark.parametrize("N, n", [(1, 4), (2, 4), (3, 4), (3, 18)])
def test_own_input_solver_matches_the_general_one(N, n):
    full, own = own_input_game(seed=40 + N, N=N, n=n)
    K_ref, k_ref = solve_feedback(*full)
    K, k = solve_feedback_own(*own)
    assert rel_gap(K, K_ref) < 1e-10 and rel_gap(k, k_ref) < 1e-10
    # ... and it is the feedback Nash equilibrium (best responses, as above).
    K, k = as_np(K, k)
    for i in range(N):
        K_br, k_br = feedback_best_response(full, K, k, i)
        assert rel_gap(K[:, i], K_br) < TOL and rel_gap(k[:, i], k_br) < TOL


@pytest.mark.parametrize("N, n", [(1, 4), (2, 4), (3, 4), (3, 18)])
def test_open_loop_own_input_solver_matches_the_general_one(N, n):
    full, own = own_input_game(seed=70 + N, N=N, n=n)
    x0 = random_x0(N, n=n)
    k_ref, xs_ref = solve_open_loop(*full, jnp.asarray(x0))
    k, xs = solve_open_loop_own(*own, jnp.asarray(x0))
    assert rel_gap(k, k_ref) < 1e-10 and rel_gap(xs, xs_ref) < 1e-10
    # ... and it is the open-loop Nash equilibrium: every player's best response (a dense
    # least-squares oracle, no Woodbury identity) to the others' inputs is its own.
    k = np.asarray(k)
    for i in range(N):
        u_br, _ = open_loop_best_response(full, x0, k, i)
        assert rel_gap(-k[:, i], u_br) < TOL, (i, rel_gap(-k[:, i], u_br))


def test_open_loop_own_input_solver_with_inputs_of_three():
    """m = 3: the own-input weights are inverted by LAPACK, not in closed form."""
    full, own = own_input_game(seed=80, N=2, m=3)
    x0 = jnp.asarray(random_x0(2))
    k_ref, _ = solve_open_loop(*full, x0)
    k, _ = solve_open_loop_own(*own, x0)
    assert rel_gap(k, k_ref) < 1e-10


@pytest.mark.parametrize("solver", ["feedback", "open_loop"])
def test_own_input_solvers_under_vmap_match_one_by_one(solver):
    """Under vmap the games are solved one after another; unbatched arguments are shared."""
    games = [own_input_game(seed=90 + s, N=2)[1] for s in range(3)]
    if solver == "feedback":
        fn = solve_feedback_own
    else:
        x0 = jnp.asarray(random_x0(2))
        fn = lambda *a: solve_open_loop_own(*a, x0)  # noqa: E731
    stacked = [jnp.asarray(np.stack(a)) for a in zip(*games)]
    batched = jax.vmap(fn)(*stacked)
    shared_A = jax.vmap(fn, in_axes=(None, 0, 0, 0, 0, 0))(stacked[0][1], *stacked[1:])
    for b, game in enumerate(games):
        for got, want in zip(batched, fn(*game)):
            assert rel_gap(got[b], want) < 1e-12
        for got, want in zip(shared_A, fn(stacked[0][1], *game[1:])):
            assert rel_gap(got[b], want) < 1e-12


# ------------------------------------------------------------------------------------
# Derivatives through the solvers (their batching rule must not block differentiation).
# ------------------------------------------------------------------------------------


# name -> (which game it takes: the general arrays or own_input_game's own blocks, solver)
_SOLVERS = {
    "feedback": ("general", lambda g, x0: solve_feedback(*g)),
    "open_loop": ("general", lambda g, x0: solve_open_loop(*g, x0)),
    "feedback_own": ("own", lambda g, x0: solve_feedback_own(*g)),
    "open_loop_own": ("own", lambda g, x0: solve_open_loop_own(*g, x0)),
}


@pytest.mark.parametrize("name", sorted(_SOLVERS))
def test_gradients_match_central_differences(name):
    """d/deps of a fixed linear functional of the solver's outputs along a random direction
    of (A, q), by jax.grad (also vmapped) and by a central difference. With step h = 1e-5
    the difference's truncation error is O(h^2) ~ 1e-10 and its rounding error
    ~ 1e-16 / h ~ 1e-11 (relative), so the two agree to 1e-6 unless a derivative is wrong."""
    kind, solver = _SOLVERS[name]
    arrays = random_game(seed=70, N=2, T=5, n=3, m=2) if kind == "general" else own_input_game(seed=70, N=2, T=5, n=3, m=2)[1]
    game = tuple(jnp.asarray(a) for a in arrays)  # A, B, Q, q, then the input weights
    x0 = jnp.asarray(random_x0(70, n=3))
    rng = np.random.default_rng(71)
    weights = [jnp.asarray(rng.standard_normal(o.shape)) for o in solver(game, x0)]
    dA, dq = (jnp.asarray(rng.standard_normal(game[i].shape)) for i in (0, 3))

    def functional(eps):
        A, B, Q, q, *input_weights = game
        outputs = solver((A + eps * dA, B, Q, q + eps * dq, *input_weights), x0)
        return sum(jnp.sum(w * o) for w, o in zip(weights, outputs))

    h = 1e-5
    derivative = jax.grad(functional)
    # one compilation: the central difference, the gradient, and vmapped gradients (the
    # batching rule's path), whose members must all equal the single one
    central, by_grad, by_vmap = jax.jit(lambda e: (
        (functional(h) - functional(-h)) / (2 * h), derivative(0.0), jax.vmap(derivative)(e)))(jnp.zeros(3))
    assert abs(by_grad - central) <= 1e-6 * max(1.0, abs(central))
    np.testing.assert_allclose(np.asarray(by_vmap), float(by_grad), rtol=1e-12)


# ------------------------------------------------------------------------------------
# Feed-forward regularization: the gains of the game, damped feed-forward terms.
# ------------------------------------------------------------------------------------


def policy_value(game, K, k, i, t0):
    """Player i's cost-to-go from stage ``t0`` when every player follows ``u^j = -K^j x - k^j``,
    as a function of the state: its gradient and Hessian at ``x = 0`` (by autodiff of a
    plain rollout, not by a value recursion)."""
    A, B, Q, q, R, r = (jnp.asarray(a) for a in game)
    T, N = B.shape[0], B.shape[1]

    def cost(x):
        total = 0.0
        for t in range(t0, T):
            us = [-(K[t, j] @ x) - k[t, j] for j in range(N)]
            total += 0.5 * x @ Q[t, i] @ x + q[t, i] @ x
            total += sum(0.5 * us[j] @ R[t, i, j] @ us[j] + r[t, i, j] @ us[j] for j in range(N))
            x = A[t] @ x + sum(B[t, j] @ us[j] for j in range(N))
        return total + 0.5 * x @ Q[T, i] @ x + q[T, i] @ x

    x = jnp.zeros(A.shape[1])
    return np.asarray(jax.grad(cost)(x)), np.asarray(jax.hessian(cost)(x))


@pytest.mark.parametrize("N, own", [(2, False),  # one player, the own-input solver and three: the slow tests
                                    pytest.param(1, False, marks=pytest.mark.slow),
                                    pytest.param(2, True, marks=pytest.mark.slow),
                                    pytest.param(3, False, marks=pytest.mark.slow),
                                    pytest.param(3, True, marks=pytest.mark.slow)])
def test_feedforward_regularization_keeps_the_gains_and_damps_the_feedforward(N, own):
    """With lambda > 0 the gains are the equilibrium's, and at every stage the feed-forward
    terms solve the coupled first-order conditions with every own block raised by lambda I,
    where each player's value is that of the strategies returned (checked against the
    cost-to-go of those strategies, differentiated through a rollout)."""
    full, own_arrays = own_input_game(seed=120 + N, N=N) if own else (random_game(seed=120 + N, N=N), None)
    solver = (lambda *a: solve_feedback_own(*own_arrays, *a)) if own else (lambda *a: solve_feedback(*full, *a))
    lam = 0.7
    K_eq, k_eq = as_np(*solver())
    K, k = as_np(*solver(lam))
    assert rel_gap(K, K_eq) < 1e-10
    assert rel_gap(k, k_eq) > 1e-3  # damped: not the equilibrium's feed-forward
    A, B, Q, q, R, r = full
    T, _, n, m = B.shape
    for t in range(T):
        values = [policy_value(full, K, k, i, t + 1) for i in range(N)]
        S = np.zeros((N * m, N * m))
        rhs = np.zeros(N * m)
        for i, (p_next, P_next) in enumerate(values):
            rows = slice(i * m, (i + 1) * m)
            for j in range(N):
                S[rows, j * m:(j + 1) * m] = B[t, i].T @ P_next @ B[t, j] + (i == j) * (R[t, i, i] + lam * np.eye(m))
            rhs[rows] = B[t, i].T @ p_next + r[t, i, i]
        assert rel_gap(np.linalg.solve(S, rhs), k[t].reshape(-1)) < TOL, t
    # lambda = 0 is the equilibrium, by either path
    K0, k0 = as_np(*solver(0.0))
    assert rel_gap(K0, K_eq) < 1e-10 and rel_gap(k0, k_eq) < 1e-10


def _game_with_an_indefinite_coupled_matrix():
    """One stage, two players, two states, scalar inputs that move both states: player 1
    weighs x1 at the end, player 2 x2 (``q`` pushes them apart). Its coupled matrix
    ``S = [[1.1, 2], [2, 1.1]]`` has the eigenvalues 3.1 and -0.9, and yet the game has a
    unique feedback equilibrium (S is regular)."""
    A = np.eye(2)[None]
    B = np.array([[[[1.0], [2.0]], [[2.0], [1.0]]]])  # B^1 = (1, 2)', B^2 = (2, 1)'
    Q = np.zeros((2, 2, 2, 2))
    Q[1, 0], Q[1, 1] = np.diag([1.0, 0.0]), np.diag([0.0, 1.0])
    q = np.zeros((2, 2, 2))
    q[1, 0], q[1, 1] = [1.0, 0.0], [0.0, -1.0]
    return A, B, Q, q, np.full((1, 2, 1, 1), 0.1), np.zeros((1, 2, 1))


def test_feedforward_regularization_where_the_coupled_matrix_is_indefinite():
    """What the docstring says of such games: S + lambda I for lambda below the negative
    eigenvalue's magnitude lengthens the step by (-0.9) / (lambda - 0.9) along its
    eigenvector, at it the step is not finite, above it the step is reversed."""
    game = _game_with_an_indefinite_coupled_matrix()
    _, k_eq = as_np(*solve_feedback_own(*game))
    v = np.array([1.0, -1.0]) / np.sqrt(2.0)  # the eigenvector of -0.9; k_eq lies along it
    assert rel_gap(k_eq.ravel(), (k_eq.ravel() @ v) * v) < 1e-12
    for lam in (0.3, 2.0):
        _, k = as_np(*solve_feedback_own(*game, lam))
        assert rel_gap(k, k_eq * (-0.9) / (lam - 0.9)) < 1e-12
    _, k = as_np(*solve_feedback_own(*game, 0.9))
    assert not np.all(np.isfinite(k))


def test_feedforward_regularization_keeps_the_dtype_of_the_game():
    """A float64 lambda (e.g. a NumPy scalar) does not promote a float32 recursion."""
    full, own = own_input_game(seed=3, N=2)
    for solver, game in ((solve_feedback_own, own), (solve_feedback, full)):
        game32 = [np.asarray(a, np.float32) for a in game]
        K, k = solver(*game32, np.float64(0.3))
        assert K.dtype == k.dtype == np.float32
        _, k64 = solver(*game, 0.3)
        assert rel_gap(k, k64) < 1e-4  # float32 rounding


@pytest.mark.parametrize("N, feedforward", [(2, None), (2, 0.7), (3, None)])
def test_batched_feedback_recursion_equals_the_per_game_one(N, feedforward):
    """The races as a batch dimension of the products (solve_feedback_own_batched) against
    the per-game recursion under vmap: the same arithmetic in another order, so equal to
    rounding (1e-12 on gains and feed-forward terms of order 1)."""
    from planners.lq_game import solve_feedback_own_batched

    games = [random_game(seed=70 + s, N=N, T=6) for s in range(3)]
    own = [(A, B, Q, q, np.stack([R[:, i, i] for i in range(N)], 1), np.stack([r[:, i, i] for i in range(N)], 1))
           for A, B, Q, q, R, r in games]
    batch = tuple(jnp.asarray(np.stack(parts)) for parts in zip(*own))
    extra = () if feedforward is None else (feedforward,)
    K_b, k_b = solve_feedback_own_batched(*batch, *extra)
    K_v, k_v = jax.vmap(lambda *game: solve_feedback_own(*game, *extra))(*batch)
    assert K_b.shape == K_v.shape and k_b.shape == k_v.shape
    assert rel_gap(K_b, K_v) < 1e-12 and rel_gap(k_b, k_v) < 1e-12
    assert float(np.max(np.abs(np.asarray(K_v)))) > 0.1  # the gains are not trivially zero
