"""Tests of the equilibrium certificates (planners.certificates) and landscapes (planners.landscape).

The small nonlinear game ``double_well`` has its stationary points in closed form. Player 0
moves ``a`` and player 1 moves ``b`` (``x_{t+1} = x_t + u_t``, one stage, from the origin):

    J^0 = (a_1^2 - 1)^2 + r u_0^2 / 2          J^1 = (b_1 - a_1)^2 + r u_1^2 / 2

With ``r = 0.4``, player 0's stationarity ``4 a (a^2 - 1) + r a = 0`` gives ``a = 0`` (its
cost has a maximum there, ``J^0'' = -4 + r < 0``: a saddle of the game) and
``a = +-sqrt(1 - r/4)`` (minima, ``J^0'' = 8 - 2 r > 0``: local Nash equilibria), and
player 1 answers ``u_1 = 2 a / (2 + r)``.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from lq_games import random_lq_game
from planners import ilq, lq_game
from planners.certificates import (
    _lanczos_extremes,
    _local_numbers,
    LOCAL_NASH,
    NOT_STATIONARY,
    SADDLE,
    CertificateTolerances,
    certify,
    deviation_cost,
)
from planners.game_problem import GameProblem, rollout
from planners.landscape import cluster_trajectories, find_equilibria, initial_guesses

R = 0.4
MINIMA = np.sqrt(1.0 - R / 4.0)  # player 0's a at the two local Nash equilibria
PRINTED = dict(convexify="none", step_control="none", initial_step=0.1, dynamics_curvature=False,
               max_iterations=1000)  # the paper's algorithm as printed: exact Hessians, fixed step


def _dw_dynamics(p, t, x, u):
    return x + u[:, 0]


def _dw_stage_cost(p, t, i, x, u_i):
    return 0.5 * p["r"] * u_i @ u_i


def _dw_terminal_cost(p, i, x):
    a, b = x
    return jnp.where(i == 0, (a ** 2 - 1.0) ** 2, (b - a) ** 2)


def double_well(horizon: int = 1) -> GameProblem:
    return GameProblem(_dw_dynamics, _dw_stage_cost, _dw_terminal_cost, num_players=2, state_dim=2, input_dim=1,
                       horizon=horizon, params={"r": jnp.asarray(R)})


def _point(a: float) -> np.ndarray:
    """The stationary point with player 0 at ``a``: inputs ``(1, 2, 1)``."""
    return np.array([[[a], [2.0 * a / (2.0 + R)]]])


X0 = np.zeros(2)


# ---------------------------------------------------------------- LQ games: always equilibria


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_lq_games_are_certified_as_strict_local_nash_equilibria(seed):
    problem, p, x0, _ = random_lq_game(seed)
    R_, r_ = p["R"], p["r"]
    Q, q = p["Q"], p["q"]
    A, B = p["A"], p["B"]
    # the exact LQ solutions, from planners.lq_game: as solver results with the gains
    K, k = lq_game.solve_feedback(A, B, Q, q, R_, r_)[:2]
    us_fb = lq_game.lq_rollout_feedback(A, B, K, k, x0)[1]
    us_ol = -lq_game.solve_open_loop(A, B, Q, q, R_, r_, x0)[0]
    for mode, us, gains in (("feedback", us_fb, K), ("open_loop", us_ol, jnp.zeros_like(K))):
        xs = rollout(problem, x0, us)
        solution = ilq.SolverResult(xs, us, True, 0, 1, None, 1.0, gains, jnp.zeros_like(us), None, None, None)
        c = certify(problem, x0, solution, mode)
        assert c.verdict == LOCAL_NASH and c.strict, c.reasons
        # exact LQ identities: only round-off is left of the gradient and of a best response's gain
        assert np.all(c.stationarity < 1e-8)
        assert np.all(np.abs(c.best_response_gain) <= 1e-8 * (1.0 + np.abs(c.numbers.cost)))
        assert np.all(c.numbers.min_eigenvalue > 0)
        if mode == "feedback":
            assert np.all(c.numbers.stage_min_eigenvalue > 0)


def test_a_perturbed_lq_solution_is_not_stationary_and_its_best_response_gains():
    problem, p, x0, _ = random_lq_game(3)
    us = -lq_game.solve_open_loop(p["A"], p["B"], p["Q"], p["q"], p["R"], p["r"], x0)[0]
    perturbed = us.at[2, 0, 1].add(0.5)
    c = certify(problem, x0, perturbed, "open_loop")
    assert c.verdict == NOT_STATIONARY
    assert c.stationarity[0] > 1e-2
    # player 0's cost is quadratic in its inputs: its best response recovers exactly the
    # decrease g' H^-1 g / 2 of Newton's step
    cost = deviation_cost(problem, jnp.asarray(x0), rollout(problem, x0, perturbed), perturbed,
                          jnp.zeros((problem.horizon, 2, 2, 4)), 0)
    u0 = perturbed[:, 0]
    g = jax.grad(cost)(u0).reshape(-1)
    H = jax.hessian(cost)(u0).reshape(g.size, g.size)
    newton = 0.5 * g @ jnp.linalg.solve(H, g)
    np.testing.assert_allclose(c.best_response_gain[0], newton, rtol=1e-8)


# ---------------------------------------------------------------- a game with a known saddle


@pytest.mark.parametrize("mode", ["open_loop", "feedback"])
def test_the_known_saddle_and_the_known_equilibria_are_told_apart(mode):
    problem = double_well()
    for a, verdict in ((0.0, SADDLE), (MINIMA, LOCAL_NASH), (-MINIMA, LOCAL_NASH)):
        solution = ilq.solve(problem, X0, _point(a), mode=mode, convexify="none")
        np.testing.assert_allclose(np.asarray(solution.us), _point(a), atol=1e-12)
        c = certify(problem, X0, solution, mode)
        assert c.verdict == verdict, (a, c.reasons)
        np.testing.assert_allclose(c.numbers.min_eigenvalue[0], (-4.0 + R) if a == 0 else (8.0 - 2 * R), rtol=1e-10)
    # at the saddle player 0 gains by deviating alone: from J^0 = 1 down to its minimum
    c = certify(problem, X0, ilq.solve(problem, X0, _point(0.0), mode=mode, convexify="none"), mode)
    best = (MINIMA ** 2 - 1.0) ** 2 + 0.5 * R * MINIMA ** 2
    np.testing.assert_allclose(c.best_response_gain[0], 1.0 - best, rtol=1e-6)


def test_the_exact_hessian_fixed_step_solve_lands_on_the_saddle_and_is_flagged():
    problem = double_well()
    start = _point(0.3)
    printed = ilq.solve(problem, X0, start, mode="open_loop", **PRINTED)
    assert bool(printed.converged)
    np.testing.assert_allclose(np.asarray(printed.us)[0, 0, 0], 0.0, atol=1e-5)
    assert certify(problem, X0, printed, "open_loop").verdict == SADDLE
    default = ilq.solve(problem, X0, start, mode="open_loop")
    np.testing.assert_allclose(np.asarray(default.us)[0, 0, 0], MINIMA, atol=1e-5)
    assert certify(problem, X0, default, "open_loop").verdict == LOCAL_NASH


def test_the_deviation_cost_derivatives_match_finite_differences():
    problem = double_well(horizon=3)
    rng = np.random.default_rng(0)
    us = jnp.asarray(0.3 * rng.standard_normal((3, 2, 1)))
    K = jnp.asarray(0.2 * rng.standard_normal((3, 2, 1, 2)))  # feedback laws of both players
    xs = rollout(problem, jnp.asarray(X0), us)
    x0 = jnp.asarray(X0) + jnp.array([0.1, -0.2])  # off the nominal start: the laws act
    cost = deviation_cost(problem, x0, xs, us, K, 1)
    u = us[:, 1]
    g, H = jax.grad(cost)(u).reshape(-1), jax.hessian(cost)(u).reshape(3, 3)
    h = 1e-5
    basis = np.eye(3).reshape(3, 3, 1)
    fd_g = np.array([(cost(u + h * e) - cost(u - h * e)) / (2 * h) for e in basis])
    fd_H = np.array([[(cost(u + h * e + h * f) - cost(u + h * e - h * f) - cost(u - h * e + h * f)
                       + cost(u - h * e - h * f)) / (4 * h * h) for f in basis] for e in basis])
    np.testing.assert_allclose(g, fd_g, rtol=1e-7, atol=1e-9)  # central differences: O(h^2) ~ 1e-10
    np.testing.assert_allclose(H, fd_H, rtol=1e-4, atol=1e-5)  # O(h^2) truncation plus eps / h^2 ~ 1e-6 round-off


def test_lanczos_on_hessian_vector_products_matches_the_dense_eigenvalues():
    """The matrix-free path (for long horizons) against the dense one, on a small game."""
    problem = double_well(horizon=8)
    rng = np.random.default_rng(1)
    us = jnp.asarray(0.5 * rng.standard_normal((8, 2, 1)))
    K = jnp.asarray(0.3 * rng.standard_normal((8, 2, 1, 2)))
    x0 = jnp.asarray(X0)
    xs = rollout(problem, x0, us)
    _, _, lo, hi, _, _, _ = _local_numbers(problem, x0, xs, us, K, dense_hessian=True, stagewise=False)
    lanczos_lo, lanczos_hi, lanczos_v = _lanczos_extremes(problem, x0, xs, us, K)
    np.testing.assert_allclose(lanczos_lo, lo, rtol=1e-8)  # eigsh's tolerance 1e-10, relative
    np.testing.assert_allclose(lanczos_hi, hi, rtol=1e-8)
    for i in range(2):  # an eigenvector of the smallest eigenvalue (player 1's is repeated: any in its space)
        H = jax.hessian(deviation_cost(problem, x0, xs, us, K, i))(us[:, i]).reshape(8, 8)
        w = lanczos_v[i].reshape(-1)
        np.testing.assert_allclose(np.linalg.norm(w), 1.0, rtol=1e-12)
        np.testing.assert_allclose(H @ w, lanczos_lo[i] * w, atol=1e-6 * np.abs(hi[i]))


def test_refuses_bad_input():
    problem = double_well()
    with pytest.raises(ValueError, match="shape"):
        certify(problem, X0, np.zeros((2, 2, 1)), "open_loop")
    with pytest.raises(ValueError, match="gains"):
        certify(problem, X0, _point(MINIMA), "feedback")
    with pytest.raises(ValueError, match="non-finite"):
        certify(problem, X0, np.full((1, 2, 1), np.nan), "open_loop")
    with pytest.raises(ValueError, match="checks"):
        certify(problem, X0, _point(MINIMA), "open_loop", checks="some")
    with pytest.raises(ValueError, match="tolerance"):
        CertificateTolerances(curvature=-1.0)


# ---------------------------------------------------------------- landscapes


def test_initial_guesses_are_zero_then_pulses_then_seeded_random():
    guesses, kinds = initial_guesses(10, 2, 2, starts=20, seed=3)
    assert kinds[:1] == ("zero",) and kinds[1:17] == ("pulse",) * 16 and kinds[17:] == ("random",) * 3
    assert not guesses[0].any() and np.all(guesses[1:17].sum(axis=1) == 0)  # pulses shift and straighten
    np.testing.assert_array_equal(guesses, initial_guesses(10, 2, 2, starts=20, seed=3)[0])
    assert not np.array_equal(guesses[17:], initial_guesses(10, 2, 2, starts=20, seed=4)[0][17:])


def test_clustering_groups_within_the_tolerance_in_order_of_first_members():
    xs = np.array([0.0, 1.0, 0.04, 5.0, 1.03, 9.0])[:, None]
    labels = cluster_trajectories(xs, np.array([True, True, True, True, True, False]), 0.05)
    np.testing.assert_array_equal(labels, [0, 1, 0, 2, 1, -1])


def test_find_equilibria_finds_every_stationary_point_of_the_known_game_deterministically():
    problem = double_well()
    landscape = find_equilibria(problem, X0, "open_loop", starts=24, seed=0, random_scale=1.0, **PRINTED)
    again = find_equilibria(problem, X0, "open_loop", starts=24, seed=0, random_scale=1.0, **PRINTED)
    np.testing.assert_array_equal(landscape.labels, again.labels)
    for e, f in zip(landscape.equilibria, again.equilibria):
        np.testing.assert_array_equal(e.us, f.us)
    found = sorted((float(e.us[0, 0, 0]), e.certificate.verdict) for e in landscape.equilibria)
    assert [v for _, v in found] == [LOCAL_NASH, SADDLE, LOCAL_NASH]
    np.testing.assert_allclose([a for a, _ in found], [-MINIMA, 0.0, MINIMA], atol=1e-5)
    for e in landscape.equilibria:  # player 1's best answer, 2 a / (2 + r)
        np.testing.assert_allclose(e.us[0, 1, 0], 2 * e.us[0, 0, 0] / (2 + R), atol=1e-5)
    assert sum(e.count for e in landscape.equilibria) == int(landscape.converged.sum())
    guesses = initial_guesses(1, 2, 1, starts=24, seed=0, random_scale=1.0)[0]
    saddle_starts = [b for e in landscape.equilibria if e.certificate.verdict == SADDLE for b in e.starts]
    assert any(guesses[b, 0, 0, 0] != 0 for b in saddle_starts)  # exact Hessians pull starts onto the saddle
    # the default solver (PSD curvature) stays on the saddle only from starts already on it
    # (player 0 at a = 0, where its gradient vanishes)
    default = find_equilibria(problem, X0, "open_loop", starts=24, seed=0, random_scale=1.0)
    for e in default.equilibria:
        if e.certificate.verdict != LOCAL_NASH:
            assert e.certificate.verdict == SADDLE and all(guesses[b, 0, 0, 0] == 0 for b in e.starts)
    assert default.share_with_verdict(LOCAL_NASH) > landscape.share_with_verdict(LOCAL_NASH)
