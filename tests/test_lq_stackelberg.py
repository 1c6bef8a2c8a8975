"""Leader-follower (Stackelberg) solutions of two-player LQ games, checked independently of
their recursions (float64).

* The follower's strategy is its best response to the leader's: an independent NumPy
  Riccati (feedback) or dense least-squares solve (open loop) from ``test_lq_game``.
* Stage-wise leader optimality (feedback): at every stage the leader's input solves the
  leader's stage problem, written here as an equality-constrained QP over both stage inputs
  (the follower's stationarity the constraint) with both players' continuation values
  measured by rollouts of the returned strategies, not taken from the recursion.
* A leader's deviation at one stage, with the follower re-optimising that stage by
  rollouts, raises the leader's cost by exactly ``1/2 d' H_leader d``.
* The comparison with Nash: what is a theorem is tested exactly (one-stage games, every
  stage against the stage Nash point with the same continuation, open-loop Stackelberg
  against open-loop Nash); that a feedback Stackelberg leader can do worse than in the
  feedback Nash equilibrium is shown on one game (docs/solvers.md).
"""

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402

from planners.lq_game import (  # noqa: E402
    lq_costs,
    lq_rollout_feedback,
    solve_feedback,
    solve_open_loop,
)
from planners.lq_stackelberg import (  # noqa: E402
    feedback_stackelberg_stages,
    solve_feedback_stackelberg,
    solve_open_loop_stackelberg,
    validate_stackelberg_game,
)
from test_lq_game import (  # noqa: E402
    feedback_best_response,
    open_loop_best_response,
    random_game,
    rel_gap,
    riccati_affine,
)

TOL = 1e-8
T, n, m = 6, 4, 2


def stackelberg_game(seed: int, T: int = T, cross: float = 0.5, linear: bool = True):
    """A random two-player LQ game with PSD ``Q^i`` and ``R^{ij}`` (``R^{ii}`` PD): every
    stage problem of both solutions is then strictly convex."""
    rng = np.random.default_rng(seed)
    A = 0.95 * np.eye(n) + 0.15 * rng.standard_normal((T, n, n))
    B = 0.5 * rng.standard_normal((T, 2, n, m))
    L = rng.standard_normal((T + 1, 2, n, n))
    Q = np.einsum("tiab,ticb->tiac", L, L) / n
    G = rng.standard_normal((T, 2, 2, m, m))
    R = np.einsum("tijab,tijcb->tijac", G, G) / m
    R *= np.where(np.eye(2, dtype=bool), 1.0, cross)[None, :, :, None, None]
    R += 0.5 * np.eye(2)[None, :, :, None, None] * np.eye(m)
    scale = 1.0 if linear else 0.0
    q = scale * 0.5 * rng.standard_normal((T + 1, 2, n))
    r = scale * 0.3 * rng.standard_normal((T, 2, 2, m))
    return A, B, Q, q, R, r


def cost_to_go(game, K, k, i, t0, x, u_first=None):
    """Player i's cost from stage t0 at state x when everyone follows ``u = -K x - k``
    (NumPy rollout); ``u_first (2, m)`` replaces the strategies' inputs at stage t0."""
    A, B, Q, q, R, r = game
    total = 0.0
    for t in range(t0, A.shape[0]):
        u = -(K[t] @ x) - k[t] if (t > t0 or u_first is None) else u_first
        total += 0.5 * x @ Q[t, i] @ x + q[t, i] @ x
        total += sum(0.5 * u[j] @ R[t, i, j] @ u[j] + r[t, i, j] @ u[j] for j in range(2))
        x = A[t] @ x + B[t, 0] @ u[0] + B[t, 1] @ u[1]
    return total + 0.5 * x @ Q[-1, i] @ x + q[-1, i] @ x


def quadratic_fit(f, dim):
    """``(H, g, c)`` with ``f(z) = 1/2 z'Hz + g'z + c`` for a quadratic ``f`` on R^dim,
    from its values at 0, the unit vectors and their pairwise sums (exact up to rounding)."""
    e = np.eye(dim)
    f0 = f(np.zeros(dim))
    fa = np.array([f(e[a]) for a in range(dim)])
    H = np.array([[f(e[a] + e[b]) - fa[a] - fa[b] + f0 for b in range(dim)] for a in range(dim)])
    return H, fa - f0 - 0.5 * np.diag(H), f0


def continuation_values(game, K, k, t):
    """``(P, p)`` of both players' costs-to-go from stage ``t`` under the strategies, as
    quadratics in the state, measured by rollouts."""
    fits = [quadratic_fit(lambda x: cost_to_go(game, K, k, i, t, x), n) for i in range(2)]
    return np.array([P for P, _, _ in fits]), np.array([p for _, p, _ in fits])


def as_np(*arrays):
    return tuple(np.asarray(a) for a in arrays)


# ------------------------------------------------------------------------------------
# Feedback Stackelberg.
# ------------------------------------------------------------------------------------


@pytest.mark.parametrize("leader", [0, 1])
@pytest.mark.parametrize("kind", ["psd", "indefinite cross weights", "no linear terms"])
def test_feedback_follower_is_a_best_response(leader, kind):
    """Fixing the leader's affine feedback law, the follower's single-player LQ problem on
    the closed loop (an independent NumPy Riccati) gives back the follower's strategy."""
    game = {"psd": lambda: stackelberg_game(1),
            "indefinite cross weights": lambda: random_game(2, N=2, T=T),  # R^{ij} indefinite
            "no linear terms": lambda: stackelberg_game(3, linear=False)}[kind]()
    K, k = as_np(*solve_feedback_stackelberg(*game, leader=leader))
    assert K.shape == (T, 2, m, n) and k.shape == (T, 2, m)
    f = 1 - leader
    K_br, k_br = feedback_best_response(game, K, k, f)
    assert rel_gap(K[:, f], K_br) < TOL and rel_gap(k[:, f], k_br) < TOL
    H_f, H_l = as_np(*feedback_stackelberg_stages(*game, leader=leader)[3:])
    assert np.linalg.eigvalsh(H_f).min() > 0 and np.linalg.eigvalsh(H_l).min() > 0
    if kind == "no linear terms":
        assert np.max(np.abs(k)) == 0.0


@pytest.mark.parametrize("leader", [0, 1])
def test_feedback_leader_solves_each_stage_problem(leader):
    """At every stage, with both continuation values measured by rollouts of the returned
    strategies: the leader's stage problem (minimise its cost-to-go over both stage inputs
    subject to the follower's stationarity) is solved by the returned strategies, for every
    state (the affine map of x), and its reduced Hessian is ``H_leader``, positive definite;
    the follower's stage Hessian is ``H_follower`` and its reaction ``reaction``."""
    game = stackelberg_game(10 + leader)
    A, B, Q, q, R, r = game
    K, k = as_np(*solve_feedback_stackelberg(*game, leader=leader))
    stages = feedback_stackelberg_stages(*game, leader=leader)
    G, H_f, H_l = as_np(*stages[2:])
    assert rel_gap(stages.K, K) == 0.0 and rel_gap(stages.k, k) == 0.0
    l, f = leader, 1 - leader
    for t in range(T):
        if t + 1 < T:
            P, p = continuation_values(game, K, k, t + 1)
        else:
            P, p = Q[T], q[T]
        Bz = np.concatenate([B[t, l], B[t, f]], axis=1)  # x+ = A x + Bz z, z = (u^l, u^f)
        # the leader's stage cost in z: 1/2 z'Hz + (E x + e)'z + ...
        H = Bz.T @ P[l] @ Bz
        H[:m, :m] += R[t, l, l]
        H[m:, m:] += R[t, l, f]
        E, e = Bz.T @ P[l] @ A[t], Bz.T @ p[l] + np.concatenate([r[t, l, l], r[t, l, f]])
        # the follower's stationarity in u^f: C z + D x + d = 0
        C = B[t, f].T @ P[f] @ Bz
        C[:, m:] += R[t, f, f]
        D, d = B[t, f].T @ P[f] @ A[t], B[t, f].T @ p[f] + r[t, f, f]
        kkt = np.block([[H, C.T], [C, np.zeros((m, m))]])
        sol = np.linalg.solve(kkt, -np.concatenate([np.concatenate([E, e[:, None]], 1),
                                                     np.concatenate([D, d[:, None]], 1)]))
        z_gain, z_offset = -sol[:2 * m, :n], -sol[:2 * m, n]  # z = -z_gain x - z_offset
        assert rel_gap(K[t, l], z_gain[:m]) < TOL and rel_gap(K[t, f], z_gain[m:]) < TOL, t
        assert rel_gap(k[t, l], z_offset[:m]) < TOL and rel_gap(k[t, f], z_offset[m:]) < TOL, t
        # second order: the follower's Hessian, and the leader's on the constraint's null space
        assert rel_gap(H_f[t], C[:, m:]) < TOL
        reaction = np.linalg.solve(C[:, m:], C[:, :m])  # u^f moves by -reaction du^l
        assert rel_gap(G[t], reaction) < TOL
        Z = np.concatenate([np.eye(m), -reaction])
        assert rel_gap(H_l[t], Z.T @ H @ Z) < TOL
        assert np.linalg.eigvalsh(H_l[t]).min() > 0 and np.linalg.eigvalsh(H_f[t]).min() > 0


def test_a_leader_deviation_costs_the_leader_its_quadratic_form():
    """At stage t from a random state, the leader plays ``u^l + d`` and the follower
    re-optimises its own stage input (its cost-to-go measured by rollouts), everyone
    following the solution afterwards: the leader's cost rises by exactly
    ``1/2 d' H_leader d`` (no first-order term: stage-wise stationarity; a positive
    definite second-order term: a minimum)."""
    game = stackelberg_game(20)
    K, k = as_np(*solve_feedback_stackelberg(*game, leader=0))
    _, H_l = as_np(*feedback_stackelberg_stages(*game, leader=0)[3:])
    rng = np.random.default_rng(21)
    for t in (0, T // 2, T - 1):
        x = rng.standard_normal(n)
        u_star = -(K[t] @ x) - k[t]

        def leader_cost(d):
            def follower_cost(u_f):
                return cost_to_go(game, K, k, 1, t, x, np.stack([u_star[0] + d, u_f]))
            H, g, _ = quadratic_fit(follower_cost, m)
            u_f = -np.linalg.solve(H, g)  # the follower's reaction, by rollouts
            return cost_to_go(game, K, k, 0, t, x, np.stack([u_star[0] + d, u_f]))

        J0 = leader_cost(np.zeros(m))
        assert abs(J0 - cost_to_go(game, K, k, 0, t, x)) < TOL * max(1.0, abs(J0))
        for _ in range(3):
            d = rng.standard_normal(m)
            rise = leader_cost(d) - J0
            expected = 0.5 * d @ H_l[t] @ d
            assert expected > 0 and abs(rise - expected) < TOL * max(1.0, abs(J0)), (t, rise, expected)


def test_one_stage_game_leader_gains_exactly_its_quadratic_form_over_nash():
    """A one-stage game is its own last stage: the leader's cost under feedback Nash minus
    under feedback Stackelberg equals ``1/2 du' H_leader du`` (``du`` the difference of the
    leader's inputs), >= 0, at every start state: leading never hurts in a one-stage game."""
    rng = np.random.default_rng(30)
    for seed in range(5):
        game = stackelberg_game(30 + seed, T=1)
        A, B = game[0], game[1]
        K_s, k_s = solve_feedback_stackelberg(*game, leader=0)
        K_n, k_n = solve_feedback(*game)
        _, H_l = as_np(*feedback_stackelberg_stages(*game, leader=0)[3:])
        for _ in range(3):
            x0 = jnp.asarray(rng.standard_normal(n))
            xs, us = lq_rollout_feedback(A, B, K_s, k_s, x0)
            J_s = float(lq_costs(*game, xs, us)[0])
            xs, us_n = lq_rollout_feedback(A, B, K_n, k_n, x0)
            J_n = float(lq_costs(*game, xs, us_n)[0])
            du = np.asarray(us_n[0, 0] - us[0, 0])
            assert abs((J_n - J_s) - 0.5 * du @ H_l[0] @ du) < TOL * max(1.0, abs(J_n))


@pytest.mark.parametrize("leader", [0, 1])
def test_every_stage_leader_does_no_worse_than_the_stage_nash_point(leader):
    """At every stage, against the stage game with the Stackelberg continuation values
    (measured by rollouts), the stage Nash point lies on the follower's reaction, so the
    leader's stage cost-to-go there exceeds its Stackelberg one by ``1/2 du' H_leader du``."""
    game = stackelberg_game(40 + leader)
    A, B, Q, q, R, r = game
    K, k = as_np(*solve_feedback_stackelberg(*game, leader=leader))
    _, H_l = as_np(*feedback_stackelberg_stages(*game, leader=leader)[3:])
    l, f = leader, 1 - leader
    rng = np.random.default_rng(41)
    for t in range(T):
        x = rng.standard_normal(n)

        def stage_cost(i, u):  # player i's cost-to-go from stage t with stage inputs u (2, m)
            return cost_to_go(game, K, k, i, t, x, u)

        def joint(z):
            u = np.zeros((2, m))
            u[l], u[f] = z[:m], z[m:]
            return u

        H_lz, g_lz, _ = quadratic_fit(lambda z: stage_cost(l, joint(z)), 2 * m)
        H_fz, g_fz, _ = quadratic_fit(lambda z: stage_cost(f, joint(z)), 2 * m)
        # Nash: each player stationary in its own input
        z_nash = np.linalg.solve(np.concatenate([H_lz[:m], H_fz[m:]]), -np.concatenate([g_lz[:m], g_fz[m:]]))
        u_star = -(K[t] @ x) - k[t]
        z_star = np.concatenate([u_star[l], u_star[f]])
        gap = stage_cost(l, joint(z_nash)) - stage_cost(l, joint(z_star))
        du = z_nash[:m] - z_star[:m]
        assert abs(gap - 0.5 * du @ H_l[t] @ du) < TOL * max(1.0, abs(stage_cost(l, joint(z_star)))), t


def test_feedback_stackelberg_leader_can_do_worse_than_in_feedback_nash():
    """Not a theorem for more than one stage: in this game (found by a search over random
    games, docs/solvers.md) leading costs the leader more than the feedback Nash equilibrium
    from this start state, by far more than rounding."""
    game = stackelberg_game(WORSE_SEED)
    A, B = game[0], game[1]
    x0 = jnp.asarray(np.random.default_rng(WORSE_SEED).standard_normal(n))
    costs = []
    for K, k in (solve_feedback_stackelberg(*game, leader=0), solve_feedback(*game)):
        xs, us = lq_rollout_feedback(A, B, K, k, x0)
        costs.append(float(lq_costs(*game, xs, us)[0]))
    J_stackelberg, J_nash = costs
    assert J_stackelberg - J_nash > 1e-3 * max(1.0, abs(J_nash)), costs


WORSE_SEED = 21  # the first of 60 seeds (0-59) where it happens; docs/solvers.md


@pytest.mark.parametrize("leader", [0, 1])
def test_follower_that_ignores_everything_leaves_the_nash_solution(leader):
    """A follower that weighs no state and no leader input (``Q^f = q^f = 0``,
    ``R^{fl} = r^{fl} = 0``) has a reaction that does not depend on the leader's input
    (``G = 0``): the Stackelberg solution is then the feedback Nash equilibrium."""
    A, B, Q, q, R, r = (a.copy() for a in stackelberg_game(50 + leader))
    f = 1 - leader
    Q[:, f], q[:, f], R[:, f, leader], r[:, f, leader] = 0.0, 0.0, 0.0, 0.0
    K_s, k_s = solve_feedback_stackelberg(A, B, Q, q, R, r, leader=leader)
    K_n, k_n = solve_feedback(A, B, Q, q, R, r)
    assert rel_gap(K_s, K_n) < 1e-10 and rel_gap(k_s, k_n) < 1e-10


def test_swapping_the_players_swaps_the_solution():
    game = stackelberg_game(60)
    A, B, Q, q, R, r = game
    swapped = (A, B[:, ::-1], Q[:, ::-1], q[:, ::-1], R[:, ::-1, ::-1], r[:, ::-1, ::-1])
    x0 = jnp.asarray(np.random.default_rng(60).standard_normal(n))
    K, k = solve_feedback_stackelberg(*game, leader=0)
    K2, k2 = solve_feedback_stackelberg(*swapped, leader=1)
    assert rel_gap(K, K2[:, ::-1]) < 1e-12 and rel_gap(k, k2[:, ::-1]) < 1e-12
    k_ol, xs = solve_open_loop_stackelberg(*game, x0, leader=0)
    k_ol2, xs2 = solve_open_loop_stackelberg(*swapped, x0, leader=1)
    assert rel_gap(k_ol, k_ol2[:, ::-1]) < 1e-10 and rel_gap(xs, xs2) < 1e-10


@pytest.mark.slow
def test_vmap_matches_one_by_one():
    games = [stackelberg_game(70 + s) for s in range(3)]
    batch = [jnp.asarray(np.stack(a)) for a in zip(*games)]
    x0 = jnp.asarray(np.random.default_rng(70).standard_normal(n))
    K_b, k_b = jax.vmap(lambda *g: solve_feedback_stackelberg(*g, leader=1))(*batch)
    kol_b, xs_b = jax.vmap(lambda *g: solve_open_loop_stackelberg(*g, x0, leader=0))(*batch)
    for s, game in enumerate(games):
        K, k = solve_feedback_stackelberg(*game, leader=1)
        assert rel_gap(K_b[s], K) < 1e-12 and rel_gap(k_b[s], k) < 1e-12
        kol, xs = solve_open_loop_stackelberg(*game, x0, leader=0)
        assert rel_gap(kol_b[s], kol) < 1e-12 and rel_gap(xs_b[s], xs) < 1e-12


# ------------------------------------------------------------------------------------
# Open-loop Stackelberg.
# ------------------------------------------------------------------------------------


def leader_cost_along_reaction(game, x0, leader):
    """The leader's total cost as a function of its input sequence ``U^l (T, m)``, the
    follower answering with its best response by an independent NumPy Riccati (the
    leader's inputs a known drift of the follower's dynamics), rolled out: a path through a
    recursion, not through the dense system of the solver."""
    A, B, Q, q, R, r = game
    l, f = leader, 1 - leader

    def cost(U_l):
        U_l = U_l.reshape(T, m)
        K_f, k_f = riccati_affine(A, B[:, f], np.einsum("tam,tm->ta", B[:, l], U_l),
                                  Q[:, f], q[:, f], R[:, f, f], r[:, f, f])
        x, J = x0, 0.0
        for t in range(T):
            u = np.zeros((2, m))
            u[l], u[f] = U_l[t], -(K_f[t] @ x) - k_f[t]
            J += 0.5 * x @ Q[t, l] @ x + q[t, l] @ x
            J += sum(0.5 * u[j] @ R[t, l, j] @ u[j] + r[t, l, j] @ u[j] for j in range(2))
            x = A[t] @ x + B[t, 0] @ u[0] + B[t, 1] @ u[1]
        return J + 0.5 * x @ Q[T, l] @ x + q[T, l] @ x

    return cost


@pytest.mark.parametrize("leader", [0, 1])
def test_open_loop_stackelberg_follower_and_leader_conditions(leader):
    """The follower's inputs are its best response to the leader's sequence (a dense NumPy
    least-squares oracle); the leader's sequence is stationary, with a positive definite
    Hessian, for its cost along the follower's best response computed by a Riccati path
    (NumPy Riccati, the quadratic measured by evaluations); the trajectory is the inputs' rollout."""
    game = stackelberg_game(80 + leader)
    x0 = np.random.default_rng(80).standard_normal(n)
    k, xs = as_np(*solve_open_loop_stackelberg(*game, jnp.asarray(x0), leader=leader))
    assert k.shape == (T, 2, m) and xs.shape == (T + 1, n)
    f = 1 - leader
    u_br, _ = open_loop_best_response(game, x0, k, f)
    assert rel_gap(-k[:, f], u_br) < TOL
    cost = leader_cost_along_reaction(game, x0, leader)
    U_l = -k[:, leader].reshape(-1)
    hess, grad, J = quadratic_fit(lambda z: cost(U_l + z), T * m)  # around the solution
    assert np.max(np.abs(grad)) < TOL * max(1.0, abs(J))
    assert np.linalg.eigvalsh(hess).min() > 0
    xs_roll, _ = lq_rollout_feedback(game[0], game[1], np.zeros((T, 2, m, n)), k, jnp.asarray(x0))
    assert rel_gap(xs, xs_roll) < TOL


def test_open_loop_leader_does_no_worse_than_open_loop_nash():
    """The open-loop Nash point lies on the follower's open-loop reaction, over which the
    open-loop Stackelberg leader minimises: its cost is no higher (a theorem), on 20 random
    games and both leaders, up to rounding."""
    rng = np.random.default_rng(90)
    for seed in range(10):
        game = stackelberg_game(90 + seed)
        x0 = jnp.asarray(rng.standard_normal(n))
        k_n, xs_n = solve_open_loop(*game, x0)
        J_n = np.asarray(lq_costs(*game, xs_n, -k_n))
        for leader in (0, 1):
            k_s, xs_s = solve_open_loop_stackelberg(*game, x0, leader=leader)
            J_s = np.asarray(lq_costs(*game, xs_s, -k_s))
            assert J_s[leader] <= J_n[leader] + TOL * max(1.0, abs(J_n[leader])), (seed, leader, J_s, J_n)


# ------------------------------------------------------------------------------------
# Bad input.
# ------------------------------------------------------------------------------------


def test_validation_refuses_what_the_solvers_are_not_for():
    game = stackelberg_game(100)
    validate_stackelberg_game(*game, leader=1)
    three = random_game(101, N=3, T=T)
    with pytest.raises(ValueError, match=r"exactly 2 players.*N=3"):
        validate_stackelberg_game(*three)
    for bad in (2, -1, True, "0"):
        with pytest.raises(ValueError, match=r"leader must be one of \(0, 1\)"):
            validate_stackelberg_game(*game, leader=bad)
    with pytest.raises(ValueError, match=r"leader must be one of \(0, 1\)"):
        solve_feedback_stackelberg(*game, leader=2)
    A, B, Q, q, R, r = (a.copy() for a in game)
    R[3, 0, 0] = np.diag([1.0, -0.5])  # player 0 follows when player 1 leads
    with pytest.raises(ValueError, match=r"follower's \(player 0\) weight on its own input R\[t=3, i=0, i=0\] "
                                         r"is not positive definite"):
        validate_stackelberg_game(A, B, Q, q, R, r, leader=1)
    with pytest.raises(ValueError, match=r"R\[t=3, i=0, i=0\].*not positive definite"):  # as a leader's
        validate_stackelberg_game(A, B, Q, q, R, r, leader=0)
    with pytest.raises(ValueError, match=r"shape mismatch: Q"):
        validate_stackelberg_game(A, B, Q[:-1], q, game[4], r)


# ------------------------------------------------------------------------------------
# The comparison with Nash on many random games (the table of docs/solvers.md).
# ------------------------------------------------------------------------------------


def _leader_costs(A, B, Q, q, R, r, x0):
    """Both leaders' costs (2, 3): feedback Stackelberg, feedback Nash, open-loop
    Stackelberg minus open-loop Nash, from x0."""
    game = (A, B, Q, q, R, r)

    def total(K, k):
        xs, us = lq_rollout_feedback(A, B, K, k, x0)
        return lq_costs(*game, xs, us)

    J_nash = total(*solve_feedback(*game))
    k_ol, xs_ol = solve_open_loop(*game, x0)
    J_ol_nash = lq_costs(*game, xs_ol, -k_ol)
    rows = []
    for leader in (0, 1):
        J_s = total(*solve_feedback_stackelberg(*game, leader=leader))
        k_s, xs_s = solve_open_loop_stackelberg(*game, x0, leader=leader)
        J_ol = lq_costs(*game, xs_s, -k_s)
        rows.append(jnp.stack([J_s[leader], J_nash[leader], J_ol[leader] - J_ol_nash[leader]]))
    return jnp.stack(rows)


@pytest.mark.slow
@pytest.mark.parametrize("horizon,linear,worse", [(1, True, (0, 0)), (1, False, (0, 0)),
                                                  (6, True, (67, 64)), (6, False, (116, 91))])
def test_nash_comparison_on_a_thousand_random_games(horizon, linear, worse):
    """The rows of docs/solvers.md's table: on 1,000 random games (seeds 10000-10999, one
    random start each) how often the feedback Stackelberg leader does worse than in the
    feedback Nash equilibrium (never for one stage: a theorem; the documented counts
    otherwise), and that the open-loop Stackelberg leader never does worse than in the
    open-loop Nash equilibrium (a theorem)."""
    games = [stackelberg_game(10000 + s, T=horizon, linear=linear) for s in range(1000)]
    batch = [jnp.asarray(np.stack(a)) for a in zip(*games)]
    x0s = jnp.asarray(np.random.default_rng(horizon).standard_normal((1000, n)))
    costs = np.asarray(jax.jit(jax.vmap(_leader_costs))(*batch, x0s))  # (1000, 2, 3)
    J_s, J_n, ol_gap = costs[..., 0], costs[..., 1], costs[..., 2]
    scale = np.maximum(1.0, np.abs(J_n))
    assert tuple(np.sum((J_s - J_n) / scale > 1e-9, axis=0)) == worse
    assert np.all(ol_gap <= TOL * scale)
