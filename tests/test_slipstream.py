"""Drag and the slipstream (racing_env.dynamics): the cars without drag are what they were,
bit for bit; a car with drag decelerates by ``c_drag (1 - r) V^2``, with the wake share ``r``
of the formula; its top speed is where the drive equals the drag; the coupled step's JAX
derivatives agree with finite differences; and the planners' linearisation carries the
coupling (the follower's rows depend on the leader's state in the wake, not out of it)."""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from planners import race_problem
from planners.ilqr import ego_problem
from racing_env import physics
from racing_env.car_classes import AV21_MASS, AV21_POWER, get_car
from racing_env.costs import CostWeights
from racing_env.dynamics import AX, SLIPSTREAM, STATE_DIM, V, Slipstream, joint_derivative
from racing_env.game import RaceGame
from racing_env.track import straight

jax.config.update("jax_enable_x64", True)

EPS = float(np.finfo(np.float64).eps)


def _game(gap: float, offset: float = 0.0, speed: float = 70.0, slipstream=SLIPSTREAM):
    """Two AV-21s on a straight, car 1 ``gap`` metres (centre to centre) behind car 0 and
    ``offset`` metres to its left, both at ``speed`` with ``ax = 2`` m/s^2."""
    car = get_car("av21")
    game = RaceGame.create(straight(3000.0), [car, car], CostWeights(), slipstream=slipstream)
    x = np.array([[1000.0, speed, 0.0, 0.0, 2.0, 0.0], [1000.0 - gap, speed, offset, 0.0, 2.0, 0.0]])
    return game, x


def _reduction(gap: float, offset: float, car, slip: Slipstream) -> float:
    """The wake's share of the follower's drag by the formula of docs/model.md, in plain floats."""
    g = gap - float(car.length)
    eps, fade = slip.onset * float(car.length), slip.wake_length * float(car.length)
    sigmoid = 1.0 / (1.0 + math.exp(-g / eps))
    return slip.reduction * sigmoid * math.exp(-g / fade) * math.exp(-(offset / (slip.wake_width * float(car.width))) ** 2)


@pytest.mark.parametrize("gap, offset", [(6.0, 0.0), (12.0, 0.5), (25.0, -1.2)])
def test_a_car_in_the_slipstream_has_the_formulas_drag(gap, offset):
    """dV/dt = ax - c_drag (1 - r) V^2 with r from the formula for both cars: the follower's
    a share of its drag, the leader's (the sigmoid's tail at a negative gap) below 1e-7; so the
    follower accelerates more than the same car alone at the same speed, by r c_drag V^2."""
    game, x = _game(gap, offset)
    car = get_car("av21")
    c, v = float(car.c_drag), 70.0
    dx = np.asarray(joint_derivative(jnp.asarray(x), jnp.zeros((2, 2)), game.track.kappa_at, game.aero()))
    r, r_leader = _reduction(gap, offset, car, SLIPSTREAM), _reduction(-gap, -offset, car, SLIPSTREAM)
    assert r > 0.03 and r_leader < 1e-7
    # the values are ~1 m/s^2: float64 rounding of the formula's few operations is ~1e-15
    assert dx[0, V] == pytest.approx(2.0 - c * (1.0 - r_leader) * v * v, rel=0, abs=1e-13)
    assert dx[1, V] == pytest.approx(2.0 - c * (1.0 - r) * v * v, rel=0, abs=1e-13)
    alone = 2.0 - c * v * v
    assert dx[1, V] - alone == pytest.approx(r * c * v * v, rel=1e-12)


def test_the_wake_fits_the_measured_reductions():
    """The default wake takes 43% of the drag half a car length behind (the rear car of
    Cerutti et al. 2021 at d = L/2) and 20% three lengths behind (their two-car mean at
    d/L = 3), each to the rounding of its stated figure; it is at most 0.44 and falls under 1%
    12.6 lengths behind or one width aside."""
    car = get_car("av21")
    length = float(car.length)
    assert _reduction(1.5 * length, 0.0, car, SLIPSTREAM) == pytest.approx(0.43, abs=0.005)
    assert _reduction(4.0 * length, 0.0, car, SLIPSTREAM) == pytest.approx(0.20, abs=0.005)
    gaps = np.linspace(0.0, 20.0, 2001) * length
    peak = max(_reduction(g, 0.0, car, SLIPSTREAM) for g in gaps)
    assert 0.43 < peak < 0.44
    assert _reduction(13.6 * length, 0.0, car, SLIPSTREAM) < 0.01
    assert _reduction(1.5 * length, float(car.width), car, SLIPSTREAM) < 0.01


def test_no_wake_without_a_slipstream_or_from_far_ahead():
    """A game without a slipstream leaves every car its whole drag, and so does the wake of a
    car 2 km ahead (its tail, ~1e-58 of the drag, is below float64's rounding of it)."""
    car = get_car("av21")
    c, v = float(car.c_drag), 70.0
    for gap, slip in ((6.0, None), (2000.0, SLIPSTREAM)):
        game, x = _game(gap, slipstream=slip)
        dx = np.asarray(joint_derivative(jnp.asarray(x), jnp.zeros((2, 2)), game.track.kappa_at, game.aero()))
        np.testing.assert_array_equal(dx[:, V], np.full(2, 2.0 - c * v * v))


def test_a_car_with_drag_settles_where_its_drive_equals_the_drag():
    """Flat out in still air the AV-21 reaches its top speed, where the engine's power
    P / (m V) equals the drag c_drag V^2 (the class's v_max, 87.57 m/s); the env's physics
    (physics.drive, full throttle) approaches it from below and stays under it. Coasting
    (ax = 0) it loses c_drag V^2."""
    car = get_car("av21")
    top = float(car.v_max)
    assert float(car.drive_max(top)) == pytest.approx(AV21_POWER / AV21_MASS / top, rel=1e-12)
    assert float(car.drive_max(top)) == pytest.approx(float(car.c_drag) * top * top, rel=1e-12)
    game = RaceGame.create(straight(100000.0), [car], CostWeights())
    x0 = jnp.array([[0.0, 80.0, 0.0, 0.0, 0.0, 0.0]])
    step = jax.jit(lambda x: physics.drive(game, x, jnp.array([[1.0, 0.0]])))

    def run(x, _):
        x = step(x)
        return x, x[0, V]

    _, speeds = jax.lax.scan(run, x0, None, length=1200)
    speeds = np.asarray(speeds)
    assert np.all(np.diff(speeds) >= 0) and np.all(speeds <= top)
    # the net acceleration near the top is about -2 V slope (V - top) with the table's slope in
    # V^2 of about -1e-3: a time constant of ~6 s, so 120 s leave far less than 1e-6 m/s
    assert speeds[-1] == pytest.approx(top, abs=1e-6)
    coast = np.asarray(joint_derivative(jnp.array([[0.0, 80.0, 0.0, 0.0, 0.0, 0.0]]), jnp.zeros((1, 2)),
                                        game.track.kappa_at, game.aero()))
    assert coast[0, V] == pytest.approx(-float(car.c_drag) * 80.0**2, rel=1e-14)


def test_the_coupled_steps_derivatives_agree_with_central_differences():
    """jax.jacfwd of the joint RK4 step with the slipstream against central differences at
    h = 1e-4 (in every state and input): the truncation error h^2 |f'''| / 6, with f''' at
    most ~c V^2 r / onset^3 dt ~ 1 here, is ~1e-9, the rounding eps |x| / h ~ 2e-9; 1e-6 bounds
    both with room."""
    game, x = _game(8.0, 0.4)
    u = jnp.array([[3.0, -2.0], [5.0, 1.0]])
    f = jax.jit(lambda xx, uu: game.step(xx.reshape(2, STATE_DIM), uu).reshape(-1))
    A, B = jax.jacfwd(f, argnums=(0, 1))(jnp.asarray(x).reshape(-1), u)
    h = 1e-4
    xf, uf = np.asarray(x).reshape(-1), np.asarray(u)
    for k in range(xf.size):
        e = np.zeros_like(xf)
        e[k] = h
        fd = (np.asarray(f(jnp.asarray(xf + e), u)) - np.asarray(f(jnp.asarray(xf - e), u))) / (2 * h)
        np.testing.assert_allclose(np.asarray(A)[:, k], fd, rtol=0, atol=1e-6)
    for i in range(2):
        for j in range(2):
            e = np.zeros_like(uf)
            e[i, j] = h
            fd = (np.asarray(f(jnp.asarray(xf), jnp.asarray(uf + e)))
                  - np.asarray(f(jnp.asarray(xf), jnp.asarray(uf - e)))) / (2 * h)
            np.testing.assert_allclose(np.asarray(B)[:, i, j], fd, rtol=0, atol=1e-6)
    # the follower's speed depends on the leader's position and offset (the wake)
    assert abs(float(A[STATE_DIM + V, 0])) > 1e-4 and abs(float(A[STATE_DIM + V, 2])) > 1e-4


def test_the_games_linearisation_carries_the_coupling_in_the_wake_only():
    """race_dynamics_jacobians of a game with drag: the block of the follower's rows and the
    leader's columns is non-zero in the wake (its speed row ~1e-3 per metre) and nothing 2 km
    behind (the wake's tail e^(-2000 / 15) ~ 1e-58); the leader's rows hardly depend on the
    follower (the sigmoid's tail: < 1e-9); and it is the Jacobian of the game's own step."""
    for gap, coupled in ((8.0, True), (2000.0, False)):
        game, x = _game(gap, 0.3)
        u = jnp.zeros((2, 2))
        A, B = jax.jit(race_problem.race_dynamics_jacobians)(game, 0, jnp.asarray(x).reshape(-1), u)
        A = np.asarray(A)
        follower_on_leader = A[STATE_DIM:, :STATE_DIM]
        if coupled:
            assert abs(follower_on_leader[V, 0]) > 1e-4
            assert np.max(np.abs(A[:STATE_DIM, STATE_DIM:])) < 1e-9
        else:
            assert np.max(np.abs(follower_on_leader)) < 1e-50
            np.testing.assert_array_equal(A[:STATE_DIM, STATE_DIM:], 0.0)
        ref = jax.jit(jax.jacfwd(lambda xx: game.step(xx.reshape(2, STATE_DIM), u).reshape(-1)))(
            jnp.asarray(x).reshape(-1))
        np.testing.assert_allclose(A, np.asarray(ref), rtol=0, atol=1e-15)


def test_the_ego_problem_feels_the_wake_of_the_predicted_car():
    """iLQR's single-car problem with drag steps the ego with the predicted cars: in the wake
    of the car ahead its speed falls by less than alone, by the formula's r c V^2 dt to first
    order."""
    car = get_car("av21")
    game, x = _game(8.0)
    problem = ego_problem(game, jnp.asarray(x), ego=1)
    x_ego = jnp.asarray(x[1])
    u = jnp.zeros((1, 2))
    behind = float(problem.dynamics(problem.params, 0, x_ego, u)[V])
    alone_game, alone_x = _game(2000.0)
    alone = float(ego_problem(alone_game, jnp.asarray(alone_x), ego=1).dynamics(
        ego_problem(alone_game, jnp.asarray(alone_x), ego=1).params, 0, jnp.asarray(alone_x[1]), u)[V])
    gain = _reduction(8.0, 0.0, car, SLIPSTREAM) * float(car.c_drag) * 70.0**2 * game.dt
    assert behind - alone == pytest.approx(gain, rel=0.02)
    assert float(problem.dynamics(problem.params, 0, x_ego, u)[AX]) == 2.0
