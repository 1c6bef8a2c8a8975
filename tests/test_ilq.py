"""Tests of the iterative LQ game solver (planners.ilq) and the iLQR baseline (planners.ilqr).

The paper's scenario is built here: a 300 m straight, 6 m wide on each side, dt = 0.1 s,
horizon 50; ego car 0 (v_max 20 m/s) at s = 10 m, V = 20 m/s on the centre line; opponent
car 1 (v_max 25 m/s) at s = 0, V = 23 m/s, 2 m to the left.

Weights: ``WEIGHTS`` pins the jerk weights r_jx = r_jy = 1 (the defaults) so the tests
do not move if the defaults change. With r = 0.01 the jerk is almost free and, without the
progress curvature (``dynamics_curvature=False``), the problem is so flat laterally that
neither iLQGame variant converges within 100 iterations; the step-rule tests use that
(and r = 0.1) as their hard case.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import racing_env  # noqa: F401  (float64: tests/conftest.py)
from planners import ilq, ilq_batch, local_game, lq_game, nash, race_problem
from planners.ilqr import ego_problem, predict_constant_velocity, solve_ilqr
from racing_env import CostWeights, RaceGame, VehicleParams
from racing_env.track import straight

from lq_games import random_lq_game

WEIGHTS = CostWeights(r_jx=1.0, r_jy=1.0)
X0 = np.array(
    [
        [10.0, 20.0, 0.0, 0.0, 0.0, 0.0],  # ego: ahead, centre line
        [0.0, 23.0, 2.0, 0.0, 0.0, 0.0],  # opponent: behind, 2 m to the left, faster
    ]
)


def paper_game(weights: CostWeights | list[CostWeights] = WEIGHTS) -> RaceGame:
    track = straight(length=300.0, width_left=6.0, width_right=6.0, ds=1.0)
    vehicles = [VehicleParams(v_max=20.0), VehicleParams(v_max=25.0)]
    return RaceGame.create(track, vehicles, weights, dt=0.1, horizon=50)


@pytest.fixture(scope="module")
def game() -> RaceGame:
    return paper_game()


@pytest.fixture(scope="module")
def open_loop(game) -> ilq.SolverResult:
    return ilq.solve(game, X0, mode="open_loop")


@pytest.fixture(scope="module")
def feedback(game) -> ilq.SolverResult:
    return ilq.solve(game, X0, mode="feedback")


@pytest.mark.parametrize("mode", ["feedback", "open_loop"])
def test_one_full_step_lands_on_the_lq_solution(mode):
    problem, p, x0, us0 = random_lq_game(seed=1)
    args = (p["A"], p["B"], p["Q"], p["q"], p["R"], p["r"])
    if mode == "feedback":
        K, k = lq_game.solve_feedback(*args)
        xs_ref, us_ref = lq_game.lq_rollout_feedback(p["A"], p["B"], K, k, x0)
    else:
        k, xs_ref = lq_game.solve_open_loop(*args, x0)
        us_ref = -k
    res = ilq.solve(problem, x0, us0, mode=mode, step_control="none", max_iterations=2)
    assert bool(res.converged) and int(res.iterations) == 2
    assert float(res.history[0]) > 1e-1  # the first step moved far ...
    assert float(res.history[1]) < 1e-9  # ... straight onto the equilibrium
    np.testing.assert_allclose(res.xs, xs_ref, atol=1e-9)
    np.testing.assert_allclose(res.us, us_ref, atol=1e-9)
    if mode == "open_loop":  # the LQ open-loop equilibrium is first-order Nash
        assert np.all(np.asarray(nash.nash_residual(problem, x0, res.us)) < 1e-9)


def test_refuses_non_positive_definite_input_weight():
    problem, p, x0, _ = random_lq_game(seed=2)
    R = np.array(p["R"])
    R[:, 1, 1] = np.diag([1.0, -0.5])  # player 1's own-input Hessian is indefinite
    bad = problem.replace(params={**p, "R": jnp.asarray(R)})
    with pytest.raises(ValueError, match=r"player 1 .*not positive definite"):
        ilq.solve(bad, x0, mode="feedback")
    with pytest.raises(ValueError, match="not positive definite"):
        ilq.validate_problem(bad, x0)


def test_validation_counts_only_the_regularization_that_every_step_adds():
    """A singular R^ii is accepted with a fixed lambda_u on it, which every LQ step adds;
    not when lambda_u is adapted (it drops to 0) or on the feed-forward terms only."""
    problem, p, x0, _ = random_lq_game(seed=2)
    R = np.array(p["R"])
    R[:, 1, 1] = np.diag([1.0, 0.0])
    singular = problem.replace(params={**p, "R": jnp.asarray(R)})
    ilq.solve(singular, x0, mode="feedback", control_regularization=0.3, max_iterations=1)
    for mode, options in (("open_loop", ADAPTIVE), ("feedback", FEEDFORWARD)):
        with pytest.raises(ValueError, match=r"player 1 .*not positive definite"):
            ilq.solve(singular, x0, mode=mode, **options)
        with pytest.raises(ValueError, match=r"player 1 .*not positive definite"):
            ilq_batch.solve_batch(singular, jnp.stack([x0, x0]), mode=mode, **options)


# --------------------------------------------------------------------------------------
# Failures are reported, not returned as NaN.
# --------------------------------------------------------------------------------------


def _cliff_dynamics(p, t, x, u):
    del p, t
    return x + u[0] + jnp.where(x > 2.0, jnp.nan, 0.0)  # undefined beyond x = 2


def _cliff_stage_cost(p, t, i, x, u_i):
    del p, t, i
    return 0.5 * jnp.sum(u_i**2) + 0.5 * jnp.sum((x - 10.0) ** 2)


def _cliff_terminal_cost(p, i, x):
    del p, i
    return 0.5 * jnp.sum((x - 10.0) ** 2)


CLIFF = ilq.GameProblem(_cliff_dynamics, _cliff_stage_cost, _cliff_terminal_cost, 1, 1, 1, 5)


def test_non_finite_rollout_is_reported_with_the_last_finite_iterate():
    x0 = jnp.zeros(1)
    full = ilq.solve(CLIFF, x0, step_control="none")  # the full step jumps off the cliff
    assert int(full.status) == ilq.NON_FINITE and not bool(full.converged)
    assert int(full.iterations) == 0
    assert np.all(np.isfinite(np.asarray(full.xs))) and np.all(np.isfinite(np.asarray(full.us)))
    guarded = ilq.solve(CLIFF, x0)  # the trust region refuses non-finite rollouts
    assert np.all(np.isfinite(np.asarray(guarded.xs)))
    assert float(jnp.max(guarded.xs[:-1])) <= 2.0  # never stepped from beyond the cliff
    assert not bool(guarded.converged)
    assert ilq.status_message(full.status).startswith("non-finite")


def test_iteration_cap_reports_non_convergence(game):
    res = ilq.solve(game, X0, mode="feedback", max_iterations=1)
    assert not bool(res.converged)
    assert int(res.status) == ilq.MAX_ITERATIONS and int(res.iterations) == 1
    for leaf in (res.xs, res.us, res.costs, res.K, res.k):
        assert np.all(np.isfinite(np.asarray(leaf)))


def _walk_dynamics(p, t, x, u):
    del p, t
    return x + u[0]


WALK = ilq.GameProblem(_walk_dynamics, _cliff_stage_cost, _cliff_terminal_cost, 1, 1, 1, 5)  # 0 -> 10, no cliff


@functools.partial(jax.jit, static_argnums=3)
def _solve_with_constant_numbers(problem, x0, us0, options):
    """The whole solve compiled with ``options``' numbers as constants of the program."""
    c = ilq.initial_carry(problem, x0, us0, options)
    return ilq.result(problem, ilq.finish(problem, ilq.iterate_while_running(problem, c, options), options), x0.shape)


def test_options_that_differ_only_in_numbers_share_one_compiled_solver():
    """The numbers of SolverOptions (here tolerance and trust radius) are traced arguments of
    the jitted solver: two options that differ only in them compile one solver between them,
    and each gives the result of a solver compiled with its numbers as constants."""
    x0 = jnp.zeros(1)
    wide = ilq.SolverOptions(tolerance=1e-6, trust_radius=20.0)
    narrow = ilq.SolverOptions(tolerance=1e-3, trust_radius=1.5)
    assert wide.split()[0] == narrow.split()[0] and wide.split()[1] != narrow.split()[1]
    compiled = ilq._solve_compiled._cache_size()
    results = {}
    for options in (wide, narrow):
        results[options] = ilq.solve(WALK, x0, options=options)
        assert ilq._solve_compiled._cache_size() == compiled + 1  # the first solve compiles, the second not
    # the numbers reach the solver: the narrow trust region cuts the walk to x = 10 into short steps
    assert int(results[wide].iterations) < int(results[narrow].iterations)
    assert float(np.nanmax(results[narrow].history * results[narrow].step_history)) <= 1.5
    for options, shared in results.items():
        assert bool(shared.converged), ilq.status_message(shared.status)
        alone = _solve_with_constant_numbers(WALK, x0, jnp.zeros((5, 1, 1)), options)
        for name, a, b in zip(shared._fields, shared, alone):
            np.testing.assert_array_equal(np.asarray(a), np.asarray(b), err_msg=name)


# --------------------------------------------------------------------------------------
# The paper's scenario.
# --------------------------------------------------------------------------------------


def test_open_loop_solution_is_first_order_nash(game, open_loop):
    assert bool(open_loop.converged), ilq.status_message(open_loop.status)
    assert np.all(np.isfinite(np.asarray(open_loop.xs)))
    assert open_loop.xs.shape == (51, 2, 6) and open_loop.us.shape == (50, 2, 2)
    zero = np.asarray(nash.nash_residual(game, X0, jnp.zeros((50, 2, 2))))
    res = np.asarray(nash.nash_residual(game, X0, open_loop.us))
    assert np.all(res <= 1e-4 * zero), (res, zero)
    np.testing.assert_allclose(open_loop.costs, game.costs(open_loop.xs, open_loop.us))
    np.testing.assert_allclose(open_loop.xs, game.rollout(jnp.asarray(X0), open_loop.us))
    assert np.all(np.asarray(open_loop.K) == 0.0)


def test_feedback_solution_has_vanishing_feedforward_and_is_not_open_loop_nash(
    game, feedback, open_loop
):
    assert bool(feedback.converged), ilq.status_message(feedback.status)
    it = int(feedback.iterations)
    k_first = float(feedback.k_history[0])
    assert float(jnp.max(jnp.abs(feedback.k))) <= 1e-5 * k_first
    assert float(feedback.k_history[it - 1]) <= 1e-5 * k_first
    assert np.all(np.isnan(np.asarray(feedback.history[it:])))
    res_fb = np.asarray(nash.nash_residual(game, X0, feedback.us))
    res_ol = np.asarray(nash.nash_residual(game, X0, open_loop.us))
    # The players interact: the feedback equilibrium violates the open-loop condition.
    assert res_fb.max() > 1e-2 and res_fb.max() > 1e3 * res_ol.max(), (res_fb, res_ol)
    np.testing.assert_allclose(feedback.xs, game.rollout(jnp.asarray(X0), feedback.us))


# open loop (the same masks, the other LQ solve) with the slow tests
@pytest.mark.parametrize("mode", ["feedback", pytest.param("open_loop", marks=pytest.mark.slow)])
def test_with_the_opponent_out_of_the_race_each_car_plans_as_if_alone(game, mode, request):
    """The paper scene with car 1 out of the race decouples into two one-car problems: the
    game's solution is each car's own optimum. Checked against one-car solves of the same
    track and cars, and by the first-order condition of each car's one-car problem."""
    ghost = game.with_racing((True, False))
    tight = dict(tolerance=1e-10)  # within the default cap of 100 iterations: the scene's compiled solver serves
    res = ilq.solve(ghost, X0, mode=mode, **tight)
    assert bool(res.converged), ilq.status_message(res.status)
    for i in range(2):
        alone = RaceGame.create(game.track, [game.vehicles.car(i)], WEIGHTS, dt=game.dt, horizon=game.horizon)
        own = ilq.solve(alone, X0[i : i + 1], mode=mode, **tight)
        assert bool(own.converged), ilq.status_message(own.status)
        # Both stop once a full step moves the states by <= 1e-10; near a fixed point the
        # iterates contract, so they are within a few 1e-10 of it. 1e-7 leaves a wide margin.
        np.testing.assert_allclose(res.xs[:, i], own.xs[:, 0], atol=1e-7)
        np.testing.assert_allclose(res.us[:, i], own.us[:, 0], atol=1e-6)
        # independently of the solver: the game's inputs are a stationary point of the car's own cost
        grad = jax.grad(lambda u: alone.costs(alone.rollout(jnp.asarray(X0[i : i + 1]), u), u)[0])
        start = float(jnp.max(jnp.abs(grad(jnp.zeros_like(own.us)))))
        assert float(jnp.max(jnp.abs(grad(res.us[:, i : i + 1])))) <= 1e-8 * start
    if mode == "feedback":  # neither car's law reacts to the other car's state
        K = np.asarray(res.K)  # (T, N, 2, 2 * 6)
        assert np.abs(K[:, 0, :, 6:]).max() <= 1e-12 and np.abs(K[:, 1, :, :6]).max() <= 1e-12
    # with both cars racing, the ego swerves for the opponent: the mask changed the game
    both = request.getfixturevalue(mode)  # the paper scene's solution, both racing
    assert float(jnp.max(jnp.abs(both.xs[:, 0, 2] - res.xs[:, 0, 2]))) > 0.1


def test_single_car_feedback_and_open_loop_coincide():
    track = straight(length=300.0, width_left=6.0, width_right=6.0, ds=1.0)
    game1 = RaceGame.create(track, [VehicleParams(v_max=20.0)], WEIGHTS, dt=0.1, horizon=50)
    x0 = np.array([[10.0, 15.0, 5.5, 0.0, 0.0, 0.0]])  # slow and over the left boundary
    fb = ilq.solve(game1, x0, mode="feedback")
    ol = ilq.solve(game1, x0, mode="open_loop")
    assert bool(fb.converged) and bool(ol.converged)
    np.testing.assert_allclose(fb.xs, ol.xs, atol=1e-6)
    np.testing.assert_allclose(fb.us, ol.us, atol=1e-5)
    assert float(fb.xs[-1, 0, 1]) > 17.0 and float(fb.xs[-1, 0, 2]) < 5.0  # sped up, back in


# The step rules are compared where the iteration is hard: at small jerk weights without the
# progress curvature (dynamics_curvature=False), under which the scenes below cycle. With it,
# the plain iterations converge there too (test_dynamics_curvature_*).
PLAIN = dict(dynamics_curvature=False)


def test_step_control_converges_where_the_fixed_full_step_cycles():
    game = paper_game(CostWeights(r_jx=0.1, r_jy=0.1))
    fixed = ilq.solve(game, X0, mode="feedback", step_control="none", **PLAIN)
    controlled = ilq.solve(game, X0, mode="feedback", **PLAIN)
    assert not bool(fixed.converged) and int(fixed.status) == ilq.MAX_ITERATIONS
    assert np.nanmin(np.asarray(fixed.history[-20:])) > 1e-2  # still jumping around
    assert bool(controlled.converged), ilq.status_message(controlled.status)
    assert float(jnp.nanmin(controlled.step_history)) < 1.0  # the control did intervene


def _merits_per_iteration(game, options):
    """``sum_i |dJ^i/du^i|^2`` after every iteration of a cold solve, from the public
    :func:`ilq.nash_residual` (through ``RaceGame.rollout``/``costs``, not the solver's
    own merit), and the accepted step sizes."""
    problem = race_problem.problem_from_race_game(game)
    iterate = jax.jit(lambda c: ilq.iterate(problem, c, options))
    c = ilq.initial_carry(problem, jnp.asarray(X0).reshape(-1), jnp.zeros((50, 2, 2)), options)
    merits = [float(np.sum(np.asarray(nash.nash_residual(game, X0, c.us)) ** 2))]
    carried = [float(c.merit)]
    while int(c.status) == ilq.RUNNING:
        c = iterate(c)
        merits.append(float(np.sum(np.asarray(nash.nash_residual(game, X0, c.us)) ** 2)))
        carried.append(float(c.merit))
    # The rule carries each accepted point's residual into the next iteration's test
    # instead of recomputing it: the carried value is that point's (also after the
    # fallback step), up to the rounding of two evaluations of one sum of squares.
    np.testing.assert_allclose(carried, merits, rtol=1e-9)
    return np.array(merits), np.asarray(c.step_history)[: int(c.it)], c


# slow (the default run's budget): an option off by default
@pytest.mark.slow
def test_residual_step_control_decreases_the_open_loop_residual(game, open_loop):
    options = ilq.SolverOptions(mode="open_loop", step_control="residual")
    merits, etas, last = _merits_per_iteration(game, options)
    assert int(last.status) == ilq.CONVERGED
    # From zero inputs the LQ game's step raises the residual at every step size (the
    # Gauss-Newton model is far off there): the rule falls back to the trust region's
    # step, from the same LQ solution at the same step size.
    assert merits[1] > merits[0]
    assert etas[0] == float(open_loop.step_history[0]) < 1.0
    # Every later step satisfies the rule's sufficient decrease 1 - 2e-4 eta (a relative
    # 1e-12 for the rounding of a sum of squares).
    bound = (1.0 - 2e-4 * etas[1:]) * merits[1:-1] * (1 + 1e-12)
    assert np.all(merits[2:] <= bound), (merits, etas)
    # The same open-loop equilibrium as the trust region's (both stop at full steps of
    # at most 1e-6).
    np.testing.assert_allclose(np.asarray(last.xs).reshape(open_loop.xs.shape), np.asarray(open_loop.xs),
                               atol=1e-5)


@pytest.mark.slow  # the rule's per-step decrease is checked by the test above, by default
def test_residual_step_control_converges_where_the_trust_region_cycles():
    game = paper_game(CostWeights(r_jx=0.01, r_jy=0.01))  # the tournaments' jerk weight
    trust_region = ilq.solve(game, X0, mode="open_loop", **PLAIN)
    residual = ilq.solve(game, X0, mode="open_loop", step_control="residual", **PLAIN)
    assert int(trust_region.status) == ilq.MAX_ITERATIONS
    assert np.nanmin(np.asarray(trust_region.history[-20:])) > 1e-3  # still moving by millimetres
    assert bool(residual.converged), ilq.status_message(residual.status)
    zero = np.asarray(nash.nash_residual(game, X0, jnp.zeros((50, 2, 2))))
    assert np.all(np.asarray(nash.nash_residual(game, X0, residual.us)) <= 1e-4 * zero)


ADAPTIVE = dict(control_regularization=0.3, adaptive_regularization=True, regularization_factor=1.5)


def test_adaptive_regularization_ends_near_the_equilibrium_where_the_trust_region_cycles():
    game = paper_game(CostWeights(r_jx=0.01, r_jy=0.01))  # the tournaments' jerk weight
    trust_region = ilq.solve(game, X0, mode="open_loop", **PLAIN)
    adaptive = ilq.solve(game, X0, mode="open_loop", **ADAPTIVE, **PLAIN)
    zero = np.asarray(nash.nash_residual(game, X0, jnp.zeros((50, 2, 2))))
    cycling = np.asarray(nash.nash_residual(game, X0, trust_region.us))
    near = np.asarray(nash.nash_residual(game, X0, adaptive.us))
    assert int(trust_region.status) == ilq.MAX_ITERATIONS
    assert np.all(near <= 1e-4 * zero)
    assert near.max() < 1e-3 * cycling.max()  # measured: 2.8e-7 against 0.085
    # Not certified at the 1e-6 m tolerance: near the limits' kinks an undamped step
    # still moves the states by about 1e-5 m (only undamped steps certify).
    assert int(adaptive.status) == ilq.MAX_ITERATIONS


def test_adaptive_regularization_follows_its_rule_and_keeps_the_equilibrium(game, open_loop):
    """lambda_u is divided by the factor after every step that keeps the direction of travel,
    raised to max(factor lambda_u, its start) after a reversal and set to 0 after a step
    within the tolerance, which only an undamped step may certify; it shortens steps but
    does not move the open-loop fixed point."""
    options = ilq.SolverOptions(mode="open_loop", **ADAPTIVE)
    problem = race_problem.problem_from_race_game(game)
    iterate = jax.jit(lambda c: ilq.iterate(problem, c, options))
    c = ilq.initial_carry(problem, jnp.asarray(X0).reshape(-1), jnp.zeros((50, 2, 2)), options)
    lams, direction = [float(c.control_regularization)], np.zeros(c.xs.size)
    reversals = []
    while int(c.status) == ilq.RUNNING:
        xs_before = np.asarray(c.xs).ravel()
        c = iterate(c)
        step = np.asarray(c.xs).ravel() - xs_before
        reversals.append(float(step @ direction) < 0)
        direction = 0.8 * direction + step / np.linalg.norm(step)  # damping_memory = 0.8
        lams.append(float(c.control_regularization))
    assert int(c.status) == ilq.CONVERGED
    lams, reversals = np.array(lams), np.array(reversals)
    small = np.asarray(c.history)[: len(reversals)] <= options.tolerance
    expected = np.where(small, 0.0, np.where(reversals, np.maximum(1.5 * lams[:-1], 0.3), lams[:-1] / 1.5))
    np.testing.assert_allclose(lams[1:], expected, rtol=1e-12)
    assert reversals.any() and not reversals.all()  # both branches were taken
    assert lams[-2] == 0.0  # the certifying step was undamped
    # the same open-loop equilibrium as the unregularised solve (both stop at full steps
    # of at most 1e-6)
    np.testing.assert_allclose(np.asarray(c.xs).reshape(open_loop.xs.shape), np.asarray(open_loop.xs), atol=1e-5)


def test_adaptive_regularization_is_refused_where_it_would_move_the_equilibrium(game):
    with pytest.raises(ValueError, match="open-loop games and one-player problems"):
        ilq.solve(game, X0, mode="feedback", **ADAPTIVE)
    with pytest.raises(ValueError, match="needs control_regularization > 0"):
        ilq.SolverOptions(mode="open_loop", adaptive_regularization=True)
    with pytest.raises(ValueError, match="regularization_factor must be > 1"):
        ilq.SolverOptions(regularization_factor=1.0)


FEEDFORWARD = dict(ADAPTIVE, feedforward_regularization=True)


def test_feedforward_regularization_keeps_the_feedback_equilibrium(game, feedback):
    """lambda_u on the feed-forward terms only, adapted by the rule, ends at the default's
    feedback equilibrium (both stop at full steps of at most 1e-6); lambda_u on R^ii moves
    it, because the gains, and with them the players' values, see it."""
    damped = ilq.solve(game, X0, mode="feedback", **FEEDFORWARD)
    assert bool(damped.converged), ilq.status_message(damped.status)
    np.testing.assert_allclose(np.asarray(damped.xs), np.asarray(feedback.xs), atol=1e-5)
    np.testing.assert_allclose(np.asarray(damped.K), np.asarray(feedback.K), atol=1e-4)
    moved = ilq.solve(game, X0, mode="feedback", control_regularization=0.1)
    assert bool(moved.converged)
    assert np.max(np.abs(np.asarray(moved.xs) - np.asarray(feedback.xs))) > 1e-4  # measured: 4.9e-4 m



# own-input / general LQ solver; the general one in the slow run: its damped feed-forward is
# checked stage by stage in test_lq_game.py (own=False), and the option reaches the LQ solve here
@pytest.mark.parametrize("convexify", ["gauss_newton", pytest.param("none", marks=pytest.mark.slow)])
def test_feedforward_regularization_damps_the_first_step_but_not_its_gains(game, convexify):
    first = {name: ilq.solve(game, X0, mode="feedback", convexify=convexify, max_iterations=1, **options)
             for name, options in {"plain": {}, "damped": FEEDFORWARD}.items()}
    K, k = (np.asarray(first["damped"].K), np.asarray(first["damped"].k))
    np.testing.assert_allclose(K, np.asarray(first["plain"].K), rtol=1e-10, atol=1e-12)
    # lambda_u reached the LQ solve (the stage-wise identity of the damped k is checked in
    # test_lq_game.py)
    assert np.max(np.abs(k - np.asarray(first["plain"].k))) > 1e-3 * np.max(np.abs(k))


def test_a_non_finite_feedforward_step_is_reported():
    """The LQ game of test_lq_game's indefinite coupled matrix, as a GameProblem: with
    lambda_u at the magnitude of that matrix's negative eigenvalue the damped feed-forward
    is not finite, and the solver says so instead of returning NaN."""
    b = jnp.array([[1.0, 2.0], [2.0, 1.0]])  # rows: B^1', B^2'
    Q_T = jnp.stack([jnp.diag(jnp.array([1.0, 0.0])), jnp.diag(jnp.array([0.0, 1.0]))])
    q_T = jnp.array([[1.0, 0.0], [0.0, -1.0]])
    problem = ilq.GameProblem(
        dynamics=lambda p, t, x, u: x + b[0] * u[0, 0] + b[1] * u[1, 0],
        stage_cost=lambda p, t, i, x, u_i: 0.05 * jnp.sum(u_i ** 2),
        terminal_cost=lambda p, i, x: 0.5 * x @ Q_T[i] @ x + q_T[i] @ x,
        num_players=2, state_dim=2, input_dim=1, horizon=1)
    x0 = np.zeros(2)
    plain = ilq.solve(problem, x0, mode="feedback", max_iterations=3)
    assert bool(plain.converged)
    damped = ilq.solve(problem, x0, mode="feedback", max_iterations=3, control_regularization=0.9,
                       feedforward_regularization=True)
    assert int(damped.status) == ilq.NON_FINITE
    assert np.all(np.isfinite(np.asarray(damped.us))) and np.all(np.isfinite(np.asarray(damped.xs)))


def test_feedforward_regularization_is_for_feedback_games_with_a_lambda(game):
    with pytest.raises(ValueError, match="add feedforward_regularization=true"):
        ilq.solve(game, X0, mode="feedback", **ADAPTIVE)
    with pytest.raises(ValueError, match="feedforward_regularization is for feedback games"):
        ilq.SolverOptions(mode="open_loop", control_regularization=0.3, feedforward_regularization=True)
    with pytest.raises(ValueError, match="feedforward_regularization needs control_regularization > 0"):
        ilq.SolverOptions(feedforward_regularization=True)
    for name in ("oscillation_damping", "adaptive_regularization", "feedforward_regularization",
                 "dynamics_curvature"):
        with pytest.raises(ValueError, match=f"SolverOptions.{name} must be True or False"):
            ilq.SolverOptions(control_regularization=0.3, **{name: "false"})


def test_residual_step_control_is_refused_for_feedback(game):
    with pytest.raises(ValueError, match="needs mode='open_loop'"):
        ilq.SolverOptions(step_control="residual")
    with pytest.raises(ValueError, match="needs mode='open_loop'"):
        ilq.solve(game, X0, mode="feedback", step_control="residual")


def test_ilqr_ego_swerves_right_of_the_predicted_opponent(game):
    res = solve_ilqr(game, X0, ego=0)
    assert bool(res.converged), ilq.status_message(res.status)
    assert res.xs.shape == (51, 2, 6) and res.us.shape == (50, 2, 2)
    pred = np.asarray(predict_constant_velocity(game, X0))
    np.testing.assert_allclose(pred[:, 1, 0], 0.0 + 23.0 * 0.1 * np.arange(51))
    np.testing.assert_allclose(res.xs[:, 1], pred[:, 1])  # opponent = its prediction
    np.testing.assert_allclose(res.us[:, 1], 0.0)
    ego_n = np.asarray(res.xs[:, 0, 2])
    assert ego_n.min() < -1.0 and ego_n.max() <= 1e-6  # to the right, never to the left
    # The plan is the ego's best response to the prediction: zero gradient of its cost.
    ego = ego_problem(game, X0, 0)
    grad = jax.jit(jax.grad(lambda u: ilq.total_costs(ego, ilq.rollout(ego, X0[0], u), u)[0]))
    assert float(jnp.linalg.norm(grad(res.plan.us))) < 1e-6
    # One player: an adaptive lambda_u does not move the fixed point either.
    adaptive = solve_ilqr(game, X0, ego=0, **ADAPTIVE)
    assert bool(adaptive.converged), ilq.status_message(adaptive.status)
    assert float(jnp.linalg.norm(grad(adaptive.plan.us))) < 1e-6


def _assert_same_solution(batch, b, single):
    """Member b of a batched result is the single solve (the same arithmetic, compiled
    in another program: equal up to rounding)."""
    assert bool(single.converged) and bool(batch.converged[b])
    assert int(single.iterations) == int(batch.iterations[b])
    np.testing.assert_allclose(batch.xs[b], single.xs, atol=1e-10)
    np.testing.assert_allclose(batch.us[b], single.us, atol=1e-10)


@pytest.mark.parametrize("mode,where,batching", [  # the one-device splits with the slow tests
    ("feedback", "all devices", "auto"), ("open_loop", "all devices", "auto"), ("feedback", "all devices", "vmap"),
    pytest.param("feedback", "one device", "auto", marks=pytest.mark.slow),
    pytest.param("open_loop", "one device", "vmap", marks=pytest.mark.slow),
])
def test_batch_matches_individual_solves(game, mode, where, batching, monkeypatch):
    assert len(jax.local_devices()) == 2  # conftest: the split path is exercised
    x0s = np.stack([X0, X0, X0])  # three members on two devices: one padded slot
    x0s[1, 1, 2] = 1.0  # opponent closer to the centre line
    x0s[2, 1, 1] = 24.0  # faster opponent
    devices = jax.local_devices()[:1] if where == "one device" else None
    batch = ilq_batch.solve_batch(game, x0s, mode=mode, devices=devices, batching=batching)
    assert batch.xs.shape == (3, 51, 2, 6) and batch.us.shape == (3, 50, 2, 2)
    for b in range(3):
        _assert_same_solution(batch, b, ilq.solve(game, x0s[b], mode=mode))
    if batching == "auto":  # "map" on this CPU: members never wait, regroup_every is ignored
        def no_regrouping(*args, **kwargs):
            raise AssertionError("a mapped batch was regrouped")

        monkeypatch.setattr(ilq_batch, "_solve_regrouped", no_regrouping)
        regrouped = ilq_batch.solve_batch(game, x0s, mode=mode, devices=devices, regroup_every=2)
        np.testing.assert_array_equal(regrouped.xs, batch.xs)


# A batch with one member per CPU core, each on its own CPU device (as many devices as
# XLA's intra-op threads), solved with the eigen-projection. jaxlib 0.10's batched LAPACK
# eigh hands parts of its batch to those threads and waits for them; once every thread
# runs such a call, the process used to hang.
_EIG_BATCH_CHILD = """
import json
from racing_env.xla_setup import configure_for_racing
configure_for_racing()  # float64 for the solver, as the racing commands run
from planners.devices import use_cpu_cores
devices = use_cpu_cores()
import numpy as np
from experiments.paper import paper_game
from planners import ilq, ilq_batch
game, x0 = paper_game()
x0s = np.repeat(x0[None], devices, axis=0)
x0s[:, 1, 1] += 0.5 * np.arange(devices)  # a different opponent speed per member
options = dict(mode="open_loop", convexify="eig", max_iterations=3)
singles = [np.asarray(ilq.solve(game, x0s[b], **options).xs) for b in range(devices)]
gaps = []
for batching in ("vmap", "map"):
    batch = ilq_batch.solve_batch(game, x0s, batching=batching, **options)
    gaps += [float(np.max(np.abs(np.asarray(batch.xs[b]) - singles[b]))) for b in range(devices)]
print(json.dumps({"devices": devices, "gaps": gaps}))
"""


@pytest.mark.slow  # a fresh process on every core; the projection itself: the default run's tests above
def test_eig_projection_in_a_batch_on_every_core_does_not_hang():
    import json
    import subprocess
    import sys

    done = subprocess.run([sys.executable, "-c", _EIG_BATCH_CHILD], capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    report = json.loads(done.stdout.strip().splitlines()[-1])
    assert report["devices"] >= 1 and len(report["gaps"]) == 2 * report["devices"]
    assert max(report["gaps"]) < 1e-10  # each member is its single solve


def _collision_weight_batch(game):
    """The opponent's collision weight c_c^2 = 1, 10, 100 (the paper's Figure 2 variation):
    the three games, one game with the weights stacked, and its ``params_axes``."""
    games = [paper_game([WEIGHTS, WEIGHTS.replace(c_collision=c)]) for c in (1.0, 10.0, 100.0)]
    stacked = jax.tree_util.tree_map(lambda *leaves: np.stack(leaves), *[g.weights for g in games])
    return games, game.replace(weights=stacked), game.replace(track=None, vehicles=None, weights=0)


def test_regrouped_batch_matches_individual_solves(game):
    """regroup_every: blocks of 4 iterations, the members still running (and their own
    cost weights, params_axes) gathered into a smaller batch in between. The members finish
    in different blocks (checked), and each result is its single solve."""
    games, batched_game, params_axes = _collision_weight_batch(game)
    x0s = np.stack([X0, X0, X0])
    x0s[0, 1, 2] += 1.0  # the opponent 1 m further left
    x0s[1, 1, 2] -= 0.5
    x0s[2, 1, 1] += 1.0  # a faster opponent
    # Measured: 13, 27 and 24 iterations: three different blocks.
    batch = ilq_batch.solve_batch(batched_game, x0s, mode="feedback", batching="vmap", regroup_every=4,
                            params_axes=params_axes)
    singles = [ilq.solve(g, x, mode="feedback") for g, x in zip(games, x0s)]
    blocks = {(int(s.iterations) - 1) // 4 for s in singles}
    assert len(blocks) == 3, [int(s.iterations) for s in singles]
    for b in range(3):
        _assert_same_solution(batch, b, singles[b])
        np.testing.assert_allclose(batch.costs[b], singles[b].costs, rtol=1e-10)


@pytest.mark.parametrize("batching", ["map", "vmap"])
def test_batch_over_cost_weights_and_warm_starts(game, batching):
    """params_axes: the opponent's collision weight (the paper's Figure 2 variation) differs
    per member, the weights stacked along their second axis (``(N, B)``); batched initial
    inputs. Split across the two devices."""
    games, batched_game, params_axes = _collision_weight_batch(game)
    second_axis = jax.tree_util.tree_map(lambda w: np.moveaxis(w, 0, 1), batched_game.weights)
    batched_game = batched_game.replace(weights=second_axis)
    params_axes = params_axes.replace(weights=1)
    inits = np.random.default_rng(5).normal(scale=0.5, size=(3, 50, 2, 2))  # warm starts [m/s^3]
    batch = ilq_batch.solve_batch(batched_game, np.stack([X0] * 3), inits, mode="feedback", params_axes=params_axes,
                            batching=batching)
    for b, g in enumerate(games):
        _assert_same_solution(batch, b, ilq.solve(g, X0, inits[b], mode="feedback"))
    # Each member used its own weight (shared weights would give three equal solutions):
    # measured, the opponent's largest offset is 2.8 m with c_c = 1 and 5.1 m with c_c = 10.
    widest = np.asarray(batch.xs[:, :, 1, 2]).max(axis=1)
    assert widest[1] - widest[0] > 1.0


def test_batch_refuses_malformed_inputs(game):
    with pytest.raises(ValueError, match="batch"):
        ilq_batch.solve_batch(game, X0)  # one state, not a batch
    with pytest.raises(ValueError, match="init must have shape"):
        ilq_batch.solve_batch(game, np.stack([X0, X0]), np.zeros((3, 50, 2, 2)))
    for bad in (0, 2.5, True):
        with pytest.raises(ValueError, match="regroup_every"):
            ilq_batch.solve_batch(game, np.stack([X0, X0]), regroup_every=bad)
    with pytest.raises(ValueError, match="batching must be one of"):
        ilq_batch.solve_batch(game, np.stack([X0, X0]), batching="lockstep")


def test_auto_batching_maps_on_cpu_and_vmaps_elsewhere():
    class Device:
        def __init__(self, platform):
            self.platform = platform

    assert ilq_batch.resolve_batching("auto", jax.local_devices()) == "map"  # this machine's CPUs
    assert ilq_batch.resolve_batching("auto", [Device("gpu")]) == "vmap"
    assert ilq_batch.resolve_batching("auto", [Device("cpu"), Device("gpu")]) == "vmap"
    assert ilq_batch.resolve_batching("vmap", jax.local_devices()) == "vmap"


# --------------------------------------------------------------------------------------
# Gauss-Newton quadratisation (the default for a RaceGame) and the race adapter's hooks.
# --------------------------------------------------------------------------------------


def _random_states(game, rng, count):
    """Joint states around X0 with constraints active: cars close, off the track, over
    the ax and gg limits; every other state has slow cars (-2 to 6 m/s) over the turn
    limit or planned in reverse."""
    scale = np.array([3.0, 4.0, 5.0, 0.2, 8.0, 12.0])
    states = [X0 + rng.normal(size=X0.shape) * scale for _ in range(count)]
    for k, X in enumerate(states[::2]):
        X[:, 1] = rng.uniform(0.5, 6.0, X.shape[0])
        X[k % X.shape[0], 1] *= -0.4  # one car planned in reverse (-2.4 to -0.2 m/s)
    return states


@pytest.mark.parametrize("racing", [None, (True, False)], ids=["all_racing", "car_1_out"])
def test_gauss_newton_hooks_give_exact_gradients_and_psd_hessians(game, racing):
    game = game.with_racing(racing)
    problem = race_problem.problem_from_race_game(game)
    n = problem.state_dim
    rng = np.random.default_rng(3)

    @jax.jit  # one compilation for all states and players (eager tracing took ~10 s)
    def terms_and_exact(z, i):
        fun = lambda z: race_problem.race_stage_gauss_newton(game, 0, i, z[:n], z[n:])
        H, g = local_game.gauss_newton_terms(fun, z)
        exact = jax.grad(lambda z: problem.stage_cost(game, 0, i, z[:n], z[n:]))(z)
        x = z[:n]
        HT, gT = local_game.gauss_newton_terms(lambda x: race_problem.race_terminal_gauss_newton(game, i, x), x)
        exact_T = jax.grad(lambda x: problem.terminal_cost(game, i, x))(x)
        return H, g, exact, HT, gT, exact_T

    states = _random_states(game, rng, 10)
    ay_turn = game.vehicles.ay_turn_max(jnp.asarray(np.stack(states))[..., 1])
    over_turn_limit = np.abs(np.stack(states)[..., 5]) > np.asarray(ay_turn)
    assert over_turn_limit.sum() >= 3  # the turn-limit residual is exercised, not just defined
    assert (np.stack(states)[..., 1] < 0).sum() >= 3  # and so is the reversing one
    for X in states:
        x = jnp.asarray(X).reshape(-1)
        for i in range(2):
            u_i = jnp.asarray(rng.normal(size=2))
            H, g, exact, HT, gT, exact_T = terms_and_exact(jnp.concatenate([x, u_i]), i)
            np.testing.assert_allclose(g, exact, rtol=1e-12, atol=1e-12)
            H = np.asarray(H)
            assert np.max(np.abs(H - H.T)) < 1e-12
            assert np.linalg.eigvalsh(H).min() >= -1e-10 * max(1.0, np.abs(H).max())
            np.testing.assert_allclose(gT, exact_T)
            assert np.all(np.asarray(HT) == 0.0)  # the terminal cost is linear


@pytest.mark.parametrize("racing", [(True, False, True), (False, True, True), (False, False, True)])
def test_gauss_newton_hooks_mask_a_ghost_among_three_cars(racing):
    """With three cars the mask keeps some pairs and drops others (with two, one ghost drops
    the only pair): the hooks' gradients equal autodiff of the masked costs for every player."""
    game, base = _three_cars_on_the_trefoil()
    game = game.with_racing(racing)
    problem = race_problem.problem_from_race_game(game)
    n = problem.state_dim

    @jax.jit
    def gradients(z, i):
        fun = lambda z: race_problem.race_stage_gauss_newton(game, 0, i, z[:n], z[n:])
        _, g = local_game.gauss_newton_terms(fun, z)
        exact = jax.grad(lambda z: problem.stage_cost(game, 0, i, z[:n], z[n:]))(z)
        _, gT = local_game.gauss_newton_terms(lambda x: race_problem.race_terminal_gauss_newton(game, i, x), z[:n])
        exact_T = jax.grad(lambda x: problem.terminal_cost(game, i, x))(z[:n])
        return g, exact, gT, exact_T

    rng = np.random.default_rng(11)
    collision_gradients = 0
    for _ in range(4):
        X = base + rng.normal(size=base.shape) * np.array([1.5, 2.0, 1.0, 0.1, 2.0, 2.0])
        X[2, 0] = X[1, 0] + 3.0  # all three within a few metres: every pair's collision term is alive
        for i in range(3):
            z = jnp.concatenate([jnp.asarray(X).reshape(-1), jnp.asarray(rng.normal(size=2))])
            g, exact, gT, exact_T = gradients(z, i)
            np.testing.assert_allclose(g, exact, rtol=1e-12, atol=1e-12)
            np.testing.assert_array_equal(gT, exact_T)  # linear: the same few products
            others = [j for j in range(3) if j != i]
            # the collision term moves the other cars' arc lengths only for racing pairs
            s_grad = np.abs(np.asarray(exact)[[6 * j for j in others]])
            paired = [racing[i] and racing[j] for j in others]
            assert np.all(s_grad[~np.array(paired)] == 0.0)
            collision_gradients += int(np.sum(s_grad[np.array(paired)] > 1e-6))
    if sum(racing) >= 2:  # some pair races: its terms were exercised, not only the zeros
        assert collision_gradients > 0


def test_gauss_newton_hessian_is_exact_for_the_track_term(game):
    # Cars far apart (no collision curvature), ax = ay = 0 (limits inactive), the ego over
    # the left boundary: the only curvature is the track term's, which Gauss-Newton keeps.
    X = X0.copy()
    X[1, 0] = 150.0
    X[0, 1] = 15.0  # below v_max: the ax limit ax_max(V) > 0 = ax is inactive
    X[0, 2] = 6.5
    problem = race_problem.problem_from_race_game(game)
    n = problem.state_dim
    z = jnp.concatenate([jnp.asarray(X).reshape(-1), jnp.array([0.3, -0.2])])
    fun = lambda z: race_problem.race_stage_gauss_newton(game, 0, 0, z[:n], z[n:])
    H, _ = jax.jit(lambda z: local_game.gauss_newton_terms(fun, z))(z)
    exact = jax.jit(jax.hessian(lambda z: problem.stage_cost(game, 0, 0, z[:n], z[n:])))(z)
    np.testing.assert_allclose(H, exact, atol=1e-10)
    assert float(exact[2, 2]) > 0  # the track term is active


@pytest.mark.parametrize("scene", ["paper", "three_cars_trefoil"])
def test_quadratization_matches_the_gauss_newton_products_of_each_stage(game, scene):
    """The stage-wise products inside ``_quadratize`` (fused code for two cars, XLA dots for
    three) equal ``J' diag(h) J`` and ``J' g`` formed in NumPy from each stage's factors."""
    game, problem, xs, us = _random_trajectory(game, scene, 8, np.array([3.0, 4.0, 5.0, 0.2, 8.0, 12.0]))
    n, N, T = problem.state_dim, game.num_players, game.horizon
    Q, q, Rii, rii = jax.jit(lambda xs, us: local_game.quadratize(problem, xs, us, gauss_newton=True))(xs, us)

    def factors(t, i):
        fun = lambda z: race_problem.race_stage_gauss_newton(game, t, i, z[:n], z[n:])
        return local_game.gauss_newton_factors(fun, jnp.concatenate([xs[t], us[t, i]]))

    factors = jax.jit(factors)
    for t in sorted({0, T // 2, T - 1}):
        for i in range(N):
            J, g, h = (np.asarray(a) for a in factors(t, i))
            assert np.any(h > 0)  # some curvature at these states
            H = np.einsum("ka,k,kb->ab", J, h, J)
            grad = J.T @ g
            scale_H = max(1.0, np.abs(H).max())
            np.testing.assert_allclose(Q[t, i], H[:n, :n], rtol=0, atol=1e-12 * scale_H)
            np.testing.assert_allclose(Rii[t, i], H[n:, n:], rtol=0, atol=1e-12 * scale_H)
            np.testing.assert_allclose(q[t, i], grad[:n], rtol=0, atol=1e-12 * max(1.0, np.abs(grad).max()))
            np.testing.assert_allclose(rii[t, i], grad[n:], rtol=0, atol=1e-12 * max(1.0, np.abs(grad).max()))


def _scene(game, scene: str) -> tuple[RaceGame, np.ndarray]:
    """The scene's game and joint start state: ``"paper"`` (the fixture ``game``, ``X0``) or
    ``"three_cars_trefoil"``."""
    if scene == "three_cars_trefoil":
        return _three_cars_on_the_trefoil()
    return game, X0


def _random_trajectory(game, scene: str, seed: int, scale: np.ndarray):
    """The scene's game (``"paper"``: ``game``; ``"three_cars_trefoil"``), its problem, and
    random states ``xs (T+1, 6 N)`` around its start (``scale`` per state entry) with
    random inputs ``us (T, N, 2)``."""
    game, base = _scene(game, scene)
    rng = np.random.default_rng(seed)
    xs = np.stack([(base + rng.normal(size=base.shape) * scale).reshape(-1) for _ in range(game.horizon + 1)])
    us = rng.normal(size=(game.horizon, game.num_players, 2))
    return game, race_problem.problem_from_race_game(game), jnp.asarray(xs), jnp.asarray(us)


def _three_cars_on_the_trefoil() -> tuple[RaceGame, np.ndarray]:
    """Three cars on a curved, closed track (the straight has kappa = 0 everywhere)."""
    from racing_env.track import trefoil

    game = RaceGame.create(trefoil(), [VehicleParams()] * 3, CostWeights(), dt=0.1, horizon=5)
    grid = np.array([[10.0, 15.0, 1.0, 0.05, 1.0, 2.0], [14.0, 16.0, -1.0, -0.1, 0.0, -3.0],
                     [30.0, 14.0, 0.0, 0.2, -2.0, 4.0]])
    return game, grid


@pytest.mark.parametrize("scene", ["paper", "three_cars_trefoil"])
def test_race_dynamics_jacobians_match_jacfwd(game, scene):
    """The per-car hook assembles the joint block-diagonal A and per-player B exactly."""
    game, base = _scene(game, scene)
    problem = race_problem.problem_from_race_game(game)
    rng = np.random.default_rng(4)
    scale = np.array([3.0, 4.0, 1.0, 0.2, 8.0, 12.0])
    hook = jax.jit(lambda x, u: race_problem.race_dynamics_jacobians(game, 0, x, u))
    joint = jax.jit(jax.jacfwd(lambda x, u: problem.dynamics(game, 0, x, u), argnums=(0, 1)))
    for _ in range(3):
        X = base + rng.normal(size=base.shape) * scale
        x, u = jnp.asarray(X).reshape(-1), jnp.asarray(rng.normal(size=(game.num_players, 2)))
        A, B = hook(x, u)
        A0, B0 = joint(x, u)
        np.testing.assert_allclose(A, A0, atol=1e-14)
        np.testing.assert_allclose(B, B0, atol=1e-14)


def test_gauss_newton_keeps_the_open_loop_fixed_point(game, open_loop):
    # open_loop uses the default (Gauss-Newton for a RaceGame); the exact-Hessian eig
    # projection converges to the same first-order Nash point.
    assert ilq.SolverOptions().convexify == "auto"
    eig = ilq.solve(game, X0, mode="open_loop", convexify="eig")
    assert bool(eig.converged) and bool(open_loop.converged)
    np.testing.assert_allclose(open_loop.xs, eig.xs, atol=1e-5)
    zero = np.asarray(nash.nash_residual(game, X0, jnp.zeros((50, 2, 2))))
    for res in (open_loop, eig):
        assert np.all(np.asarray(nash.nash_residual(game, X0, res.us)) <= 1e-4 * zero)


def test_feedback_with_gauss_newton_and_eig_projection_agree_closely(game, feedback):
    eig = ilq.solve(game, X0, mode="feedback", convexify="eig")
    assert bool(eig.converged) and bool(feedback.converged)
    # Different PSD curvatures give (slightly) different feedback equilibria.
    assert float(jnp.max(jnp.abs(feedback.xs - eig.xs))) < 0.2


def test_gauss_newton_needs_the_hooks():
    problem, p, x0, us0 = random_lq_game(seed=5)
    with pytest.raises(ValueError, match="gauss_newton"):
        ilq.solve(problem, x0, us0, convexify="gauss_newton")
    auto = ilq.solve(problem, x0, us0, mode="feedback", step_control="none", max_iterations=2)
    eig = ilq.solve(problem, x0, us0, mode="feedback", step_control="none", max_iterations=2, convexify="eig")
    np.testing.assert_array_equal(auto.xs, eig.xs)  # "auto" falls back to eig projection


def test_ilqr_gauss_newton_hooks_match_the_ego_costs(game):
    """iLQR's ego problem: exact gradients, PSD curvature, and the same plan as eig projection."""
    problem = ego_problem(game, X0, ego=0)
    assert problem.has_gauss_newton
    params = problem.params
    rng = np.random.default_rng(6)

    @jax.jit  # one compilation for all states and stages
    def terms_and_exact(z, t):
        fun = lambda z: problem.stage_gauss_newton(params, t, 0, z[:6], z[6:])
        H, g = local_game.gauss_newton_terms(fun, z)
        exact = jax.grad(lambda z: problem.stage_cost(params, t, 0, z[:6], z[6:]))(z)
        gT = local_game.gauss_newton_terms(lambda x: problem.terminal_gauss_newton(params, 0, x), z[:6])[1]
        return H, g, exact, gT, jax.grad(lambda x: problem.terminal_cost(params, 0, x))(z[:6])

    for X in _random_states(game, rng, 5):
        z = jnp.concatenate([jnp.asarray(X[0]), jnp.asarray(rng.normal(size=2))])
        for t in (0, 17):
            H, g, exact, gT, exact_T = terms_and_exact(z, t)
            np.testing.assert_allclose(g, exact, rtol=1e-12, atol=1e-12)
            assert np.linalg.eigvalsh(np.asarray(H)).min() >= -1e-10 * max(1.0, float(np.abs(H).max()))
        np.testing.assert_allclose(gT, exact_T)
    gauss_newton = solve_ilqr(game, X0, ego=0)
    eig = solve_ilqr(game, X0, ego=0, convexify="eig")
    assert bool(gauss_newton.converged) and bool(eig.converged)
    # one player: both are stationary points of the same cost; here they are the same one
    np.testing.assert_allclose(gauss_newton.xs, eig.xs, atol=1e-4)


# --------------------------------------------------------------------------------------
# The progress curvature the local games would otherwise miss (SolverOptions.dynamics_curvature).
# --------------------------------------------------------------------------------------


@pytest.mark.parametrize("scene", ["paper", "three_cars_trefoil"])
def test_stage_curvature_is_the_heading_curvature_of_each_cars_progress(game, scene):
    """Player i's entry is ``-d^2/dchi_i^2`` of its progress ``dt * ds/dt`` over the stage
    (autodiff of the car model), on its own heading only; the paper's scene is a straight and
    the trefoil is curved, so ``1 / (1 - n kappa)`` is exercised too."""
    from racing_env.dynamics import CHI, car_derivative

    game, base = _scene(game, scene)
    N = game.num_players
    curvature = jax.jit(lambda x, i: race_problem.race_stage_curvature(game, 0, i, x))

    @jax.jit
    def exact(car):
        progress = lambda chi: game.dt * car_derivative(car.at[CHI].set(chi), jnp.zeros(2), game.track.kappa_at)[0]
        return -jax.grad(jax.grad(progress))(car[CHI])

    rng = np.random.default_rng(12)
    curved = 0
    for _ in range(4):
        X = base + rng.normal(size=base.shape) * np.array([30.0, 3.0, 2.0, 0.2, 2.0, 2.0])
        x = jnp.asarray(X).reshape(-1)
        for i in range(N):
            d = np.asarray(curvature(x, i))
            h = float(exact(jnp.asarray(X[i])))
            assert h > 0  # forward at |chi| < pi / 2: progress is concave in the heading
            np.testing.assert_allclose(d[6 * i + CHI], h, rtol=1e-12)
            assert np.count_nonzero(d) == 1
            curved += abs(float(game.track.kappa_at(X[i, 0]) * X[i, 2])) > 1e-3
    assert (curved > 0) == (scene == "three_cars_trefoil")


def test_stage_curvature_is_the_progress_curvature_of_the_rk4_step_on_a_straight(game):
    """On a straight at constant speed and heading the RK4 step's progress is exactly
    ``dt V cos(chi)``, so the hook's curvature is the model's own, by central differences
    (step 1e-4 rad: truncation ~1e-9 relative, rounding ~1e-8)."""
    from racing_env.dynamics import CHI, S, rk4_step

    car = np.array([20.0, 17.0, 1.5, 0.3, 0.0, 0.0])
    step = lambda chi: float(rk4_step(jnp.asarray(car).at[CHI].set(chi), jnp.zeros(2), game.dt,
                                      game.track.kappa_at)[S])
    e = 1e-4
    finite_difference = -(step(car[CHI] + e) - 2 * step(car[CHI]) + step(car[CHI] - e)) / e**2
    X = X0.copy()
    X[0] = car
    d = race_problem.race_stage_curvature(game, 0, 0, jnp.asarray(X).reshape(-1))
    np.testing.assert_allclose(float(d[CHI]), finite_difference, rtol=1e-6)


@pytest.mark.parametrize("scene, gauss_newton", [
    ("paper", True), ("paper", False), ("three_cars_trefoil", False),
    pytest.param("three_cars_trefoil", True, marks=pytest.mark.slow),  # three cars: exact Hessians by default
], ids=["paper-gauss_newton", "paper-exact_hessians", "three_cars_trefoil-exact_hessians",
        "three_cars_trefoil-gauss_newton"])
def test_dynamics_curvature_adds_only_the_heading_diagonal_and_keeps_the_gradients(game, scene, gauss_newton):
    game, problem, xs, us = _random_trajectory(game, scene, 9, np.array([3.0, 2.0, 1.0, 0.1, 1.0, 1.0]))
    n, N, T = problem.state_dim, game.num_players, game.horizon
    quadratize = jax.jit(lambda xs, us, on: local_game.quadratize(problem, xs, us, gauss_newton, on), static_argnums=2)
    plain, curved = quadratize(xs, us, False), quadratize(xs, us, True)
    for a, b in zip(plain[1:], curved[1:]):  # q, Rii, rii: bit for bit
        np.testing.assert_array_equal(a, b)
    added = np.asarray(curved[0] - plain[0])
    h = jax.vmap(lambda x: jax.vmap(lambda i: race_problem.race_stage_curvature(game, 0, i, x))(jnp.arange(N)))(xs[:-1])
    expected = np.zeros_like(added)
    for i in range(N):
        expected[:T, i, 6 * i + 3, 6 * i + 3] = np.asarray(h)[:, i, 6 * i + 3]
    assert np.all(expected[:T, np.arange(N), 6 * np.arange(N) + 3, 6 * np.arange(N) + 3] > 0)
    np.testing.assert_allclose(added, expected, rtol=0, atol=1e-12 * float(np.abs(plain[0]).max()))


@pytest.mark.slow  # the default run's budget: the curvature's form and fixed point are tested by default above and below
def test_dynamics_curvature_converges_the_straight_at_the_racing_jerk_weight():
    """One car on a straight at r = 0.01 with a small lateral acceleration: without the
    progress curvature only the jerk weight curves the lateral states of the local LQ
    games, and the iterations cycle laterally to the cap (docs/solvers.md, Progress curvature)."""
    track = straight(length=2000.0, width_left=6.0, width_right=6.0, ds=1.0)
    game = RaceGame.create(track, [VehicleParams(v_max=25.0)], CostWeights(r_jx=0.01, r_jy=0.01),
                           dt=0.1, horizon=50)
    x0 = np.array([[100.0, 24.965, 0.0, 0.0, 0.0, 0.02]])
    for mode in ("feedback", "open_loop"):
        kwargs = dict(mode=mode, tolerance=1e-3, max_iterations=60)
        with_curvature = ilq.solve(game, x0, **kwargs)
        without = ilq.solve(game, x0, dynamics_curvature=False, **kwargs)
        assert bool(with_curvature.converged) and int(with_curvature.iterations) <= 10, mode
        assert int(without.status) == ilq.MAX_ITERATIONS, mode


def test_dynamics_curvature_keeps_the_open_loop_fixed_point(game, open_loop):
    without = ilq.solve(game, X0, mode="open_loop", dynamics_curvature=False)
    assert bool(without.converged) and bool(open_loop.converged)
    np.testing.assert_allclose(open_loop.xs, without.xs, atol=1e-5)
    zero = np.asarray(nash.nash_residual(game, X0, jnp.zeros((50, 2, 2))))
    assert np.all(np.asarray(nash.nash_residual(game, X0, without.us)) <= 1e-4 * zero)


# three cars (the same hook, more rows) with the slow tests
@pytest.mark.parametrize("scene", ["paper", pytest.param("three_cars_trefoil", marks=pytest.mark.slow)])
def test_ilqr_ego_problem_has_the_games_own_heading_curvature(game, scene):
    """Every ego's curvature is its block of the game's, at the joint state with the
    others at their prediction, and iLQR's local problem gets it."""
    game, base = _scene(game, scene)
    for ego in range(game.num_players):
        problem = ego_problem(game, base, ego=ego)
        x_ego = jnp.asarray(base[ego] + np.array([0.0, 0.0, 0.5, 0.1, 0.0, 0.0]))
        t = 3
        joint = problem.params.predicted[t].at[ego].set(x_ego).reshape(-1)
        d = problem.stage_curvature(problem.params, t, 0, x_ego)
        np.testing.assert_array_equal(d, race_problem.race_stage_curvature(game, t, ego, joint)[6 * ego:6 * ego + 6])
        assert float(d[3]) > 0
        xs = jnp.tile(x_ego, (game.horizon + 1, 1))
        us = jnp.zeros((game.horizon, 1, 2))
        Q_on = local_game.quadratize(problem, xs, us, True, True)[0]
        Q_off = local_game.quadratize(problem, xs, us, True, False)[0]
        added = np.asarray(Q_on - Q_off)[:, 0]
        assert np.count_nonzero(added[:-1, 3, 3]) == game.horizon and np.count_nonzero(added) == game.horizon


def test_cpu_device_count_is_fixed_once_jax_runs():
    from planners.devices import use_cpu_cores

    assert use_cpu_cores(2) == 2  # what conftest asked for: accepted again
    with pytest.raises(RuntimeError, match="before the first JAX computation"):
        use_cpu_cores(3)
    with pytest.raises(ValueError, match=">= 1"):
        use_cpu_cores(0)


def test_the_generic_solver_imports_nothing_of_the_racing_game():
    """ilq, ilq_batch, nash and the game protocol know only GameProblem; a RaceGame reaches
    them through the game type that planners.race_problem registers."""
    import ast
    import inspect

    from planners import game_problem

    for module in (ilq, local_game, ilq_batch, nash, game_problem):
        tree = ast.parse(inspect.getsource(module))
        imported = [alias.name for node in ast.walk(tree) if isinstance(node, ast.Import) for alias in node.names]
        imported += [node.module or "" for node in ast.walk(tree) if isinstance(node, ast.ImportFrom)]
        assert not any(name.startswith("racing_env") for name in imported), module.__name__
    assert game_problem.game_type_of(paper_game()) is not None
    # The names that moved out of planners.ilq stay reachable there.
    assert ilq.solve_batch is ilq_batch.solve_batch
    assert ilq.nash_residual is nash.nash_residual
    assert ilq.problem_from_race_game is race_problem.problem_from_race_game
