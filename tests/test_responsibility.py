"""Collision weights that follow responsibility (``responsibility=R``): the car behind carries R
times the collision weight it carries towards a car behind it, judged from the state a plan
starts from, so that the cost, the solvers' Gauss-Newton form and the Nash certificates
(``jax.grad`` of the cost) see the same constant weights."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import racing_env
from planners import certify, ilq, make_agent, rival_game
from planners.agents.receding_horizon import DEFAULT_RESPONSIBILITY
from planners.certificates import LOCAL_NASH
from planners.nash import nash_residual
from planners.race_problem import race_stage_gauss_newton
from racing_env.costs import responsibility_scale, state_cost_terms
from racing_env.game import RaceGame
from racing_env.scenarios import paper_game
from racing_env.track import straight, trefoil
from racing_env.vehicle import VehicleParams


def _state(s, n=None) -> np.ndarray:
    x = np.zeros((len(s), 6))
    x[:, 0], x[:, 1] = s, 20.0
    if n is not None:
        x[:, 2] = n
    return x


def _collision(game: RaceGame, x: np.ndarray) -> np.ndarray:
    terms = state_cost_terms(jnp.asarray(x), game.vehicles, game.weights, game.track, game.racing,
                             game.collision_scale)
    return np.asarray(terms["collision"])


def test_the_car_behind_carries_r_times_the_collision_cost():
    """Car 0 10 m (two lengths) behind car 1, 1 m to its right: with R = 3 car 0's collision
    cost is 3 times the symmetric one, car 1's unchanged; alongside, both carry (1 + R) / 2.
    On a closed track the gap is wrapped: a car just past the line is ahead of one just
    before it."""
    game = RaceGame.create(straight(length=300.0), [VehicleParams()] * 2)
    x = _state([100.0, 110.0], n=[0.0, 1.0])
    plain, judged = _collision(game, x), _collision(game.with_responsibility(x, 3.0), x)
    assert plain[0] > 0 and plain[0] == pytest.approx(plain[1], rel=1e-12)  # the paper's cost is symmetric
    np.testing.assert_allclose(judged, [3.0 * plain[0], plain[1]], rtol=1e-12)

    alongside = _state([100.0, 100.0], n=[0.0, 2.5])
    np.testing.assert_allclose(_collision(game.with_responsibility(alongside, 3.0), alongside),
                               2.0 * _collision(game, alongside), rtol=1e-12)

    loop = RaceGame.create(trefoil(), [VehicleParams()] * 2)
    around = _state([loop.track.length - 5.0, 5.0])  # car 1 10 m ahead, across the line
    scale = loop.with_responsibility(around, 3.0).collision_scale
    assert scale[0, 1] == 3.0 and scale[1, 0] == 1.0


def test_the_scale_is_smooth_between_behind_and_ahead_and_one_is_the_symmetric_cost():
    """The factor of car 0 towards car 1 rises monotonically and continuously from 1 (one length
    behind) to R (one length ahead); R = 1 is no scale at all (the game unchanged)."""
    track = straight(length=300.0)
    gaps = np.linspace(-8.0, 8.0, 161)
    s = np.stack([np.full_like(gaps, 100.0), 100.0 + gaps], axis=1)
    factor = responsibility_scale(track, s, 4.7, 4.0)[:, 0, 1]
    assert np.all(np.diff(factor) >= 0) and np.max(np.abs(np.diff(factor))) < 0.15
    np.testing.assert_array_equal(factor[gaps <= -4.7], 1.0)
    np.testing.assert_array_equal(factor[gaps >= 4.7], 4.0)
    game = RaceGame.create(track, [VehicleParams()] * 2)
    assert game.with_responsibility(_state([0.0, 10.0]), 1.0).collision_scale is None
    # the compiled planners' (traced) form: the same operations, to the last bits
    np.testing.assert_allclose(jax.jit(lambda s_: responsibility_scale(track, s_, 4.7, 4.0, xp=jnp))(s),
                               responsibility_scale(track, s, 4.7, 4.0), rtol=1e-14)


def test_the_gauss_newton_gradient_is_the_costs_gradient_with_the_scale():
    """The solvers' residual form carries the same per-pair weights as the cost: its exact
    gradient ``J' g`` equals ``jax.grad`` of player i's stage cost."""
    game, x0 = paper_game()
    game = game.with_responsibility(x0, 3.0)
    x = np.asarray(x0, dtype=np.float64).copy()
    x[1, 0] = x[0, 0] - 3.0  # the opponent close behind, so the collision terms count
    z = jnp.concatenate([jnp.asarray(x).reshape(-1), jnp.array([0.3, -0.2])])
    n = x.size

    def both(i):
        def outer(z_):
            r, g, h = race_stage_gauss_newton(game, 0, i, z_[:n], z_[n:])
            return r, g

        J, g = jax.jacfwd(outer, has_aux=True)(z)
        return J.T @ g, jax.grad(lambda z_: game.stage_cost(i, z_[:n].reshape(2, 6), z_[n:]))(z)

    residual_form, exact = jax.jit(jax.vmap(both))(jnp.arange(2))
    assert np.abs(np.asarray(exact)[1, :n]).max() > 1.0  # the collision term is felt
    np.testing.assert_allclose(residual_form, exact, rtol=1e-10, atol=1e-10)


@pytest.fixture(scope="module")
def judged_solve():
    """The paper's scene (the faster opponent 10 m behind, 2 m to the left) with R = 3, and
    its converged open-loop solution."""
    game, x0 = paper_game()
    judged = game.with_responsibility(x0, 3.0)
    return judged, x0, ilq.solve(judged, x0, mode="open_loop", max_iterations=100)


def test_a_converged_solve_with_responsibility_weights_passes_the_first_order_nash_check(judged_solve):
    """The converged open-loop solution with R = 3 (solved with the residual form's weights)
    passes the first-order Nash check: ``jax.grad`` of each player's own total cost through
    ``RaceGame.rollout`` and ``costs``, with respect to its own inputs, is below 1e-4 of the
    zero input's."""
    judged, x0, res = judged_solve
    assert bool(res.converged)
    zero = np.asarray(nash_residual(judged, x0, jnp.zeros_like(res.us)))
    assert np.all(np.asarray(nash_residual(judged, x0, res.us)) <= 1e-4 * zero)


@pytest.mark.slow
def test_a_converged_solve_with_responsibility_weights_is_certified(judged_solve):
    """And the certificate (stationary, positive curvature in each player's own inputs, no
    better best response) says: a local Nash equilibrium."""
    judged, x0, res = judged_solve
    assert certify(judged, x0, res, "open_loop").verdict == LOCAL_NASH


@pytest.mark.slow
def test_with_responsibility_the_leader_holds_its_line_and_the_trailing_car_avoids(judged_solve):
    """The paper's Fig. 2: with the trailing car's collision weight 3 times the leader's, the
    leader swerves less than with the symmetric cost and the trailing car more (measured:
    2.42 -> 1.79 m and 4.44 -> 5.14 m)."""
    judged, x0, res = judged_solve
    game, _ = paper_game()
    plain_res = ilq.solve(game, x0, mode="open_loop", max_iterations=100)
    assert bool(plain_res.converged)
    xs, plain = np.asarray(res.xs), np.asarray(plain_res.xs)
    assert np.abs(xs[:, 0, 2]).max() < np.abs(plain[:, 0, 2]).max() - 0.3
    assert xs[:, 1, 2].max() > plain[:, 1, 2].max() + 0.3


def test_a_local_game_orders_the_scale_with_its_cars():
    """A local game takes the field's scale in its own car order: its players' stage costs are
    the field game's at the same joint state."""
    game = RaceGame.create(trefoil(), [VehicleParams()] * 4)
    x0 = _state([100.0, 104.0, 96.0, 130.0], n=[0.0, 1.5, -1.5, 0.0])
    judged = game.with_responsibility(x0, 3.0)
    local = rival_game.local_game(judged, x0, 2, 2)
    params, order = local.problem.params, local.order
    u = jnp.array([0.4, -0.3])
    field = jnp.asarray(x0)
    x_local = field[order[:3]].reshape(-1)
    for p in range(3):
        cost = local.problem.stage_cost(params, 0, p, x_local, u)
        assert float(cost) == pytest.approx(float(judged.stage_cost(int(order[p]), field, u)), rel=1e-12)


def test_the_option_is_checked_and_sets_the_replans_game():
    """``responsibility`` is a finite number >= 1 (default :data:`DEFAULT_RESPONSIBILITY`, 2),
    refused otherwise when the agent is made; a re-plan's game carries the scale of the state
    it starts from, and 1 none."""
    for bad in ("0.5", "0", "-2", "nan", "inf"):
        with pytest.raises(ValueError, match="responsibility must be a finite number >= 1"):
            make_agent(f"ilqgame-fb:responsibility={bad}")
    with pytest.raises(ValueError, match="expected a number"):
        make_agent("ilqr:responsibility=much")
    assert make_agent("ilqgame-ol").responsibility == DEFAULT_RESPONSIBILITY == 2.0
    assert make_agent("ilqr:responsibility=1.5").responsibility == 1.5
    env = racing_env.parallel_env(track="trefoil", num_agents=2)
    observations, _ = env.reset(seed=0)
    x = env.state()
    for spec, expected in (("ilqgame-fb", 2.0), ("ilqgame-fb:responsibility=4", 4.0),
                           ("ilqgame-fb:responsibility=1", None)):
        agent = make_agent(spec)
        agent.reset(0, 0, env)
        scale = agent._game_now(observations["car_0"], x, {}).collision_scale
        if expected is None:
            assert scale is None
        else:
            np.testing.assert_array_equal(scale, env.game.with_responsibility(x, expected).collision_scale)
