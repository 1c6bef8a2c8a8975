"""Tests of racing_env.dynamics and RaceGame.step against the paper's equations (NumPy oracle)."""


import jax
import jax.numpy as jnp
import numpy as np
import pytest

from racing_env import dynamics as dyn
from racing_env import track as tr
from racing_env.game import RaceGame
from racing_env.vehicle import VehicleParams


# --- an independent NumPy implementation of the paper's model ---------------------------
def np_kappa(track: tr.Track, s: np.ndarray) -> np.ndarray:
    """Piecewise-linear curvature of the track's grid, by np.interp (wraps closed tracks)."""
    s = np.asarray(s, dtype=float)
    m = track.num_points
    if track.closed:
        grid = track.ds * np.arange(m + 1)
        values = np.append(track.kappa, track.kappa[0])
        return np.interp(np.mod(s, track.length), grid, values)
    return np.interp(np.clip(s, 0.0, track.length), track.ds * np.arange(m), track.kappa)


def np_paper_derivative(x: np.ndarray, u: np.ndarray, track: tr.Track) -> np.ndarray:
    """The paper's eq. (dynamics), written out for cars ``x (K, 6)``, ``u (K, 2)``."""
    s, v, n, chi, ax, ay = x.T
    kappa = np_kappa(track, s)
    s_dot = v * np.cos(chi) / (1.0 - n * kappa)
    return np.stack(
        [
            s_dot,
            ax,
            v * np.sin(chi),
            ay / v - kappa * v * np.cos(chi) / (1.0 - n * kappa),
            u[:, 0],
            u[:, 1],
        ],
        axis=1,
    )


def np_rk4(x: np.ndarray, u: np.ndarray, dt: float, track: tr.Track) -> np.ndarray:
    """Classical RK4 step of the NumPy equations with the input held over dt."""
    f = lambda z: np_paper_derivative(z, u, track)  # noqa: E731
    k1 = f(x)
    k2 = f(x + 0.5 * dt * k1)
    k3 = f(x + 0.5 * dt * k2)
    k4 = f(x + dt * k3)
    return x + dt / 6.0 * (k1 + 2.0 * k2 + 2.0 * k3 + k4)


def random_states(rng: np.random.Generator, count: int, track: tr.Track, s_range=None):
    """Random car states with V well above V_EPS and |n kappa| < 0.5, and random jerks."""
    lo, hi = s_range if s_range is not None else (0.0, track.length)
    x = np.stack(
        [
            rng.uniform(lo, hi, count),
            rng.uniform(3.0 * dyn.V_EPS, 35.0, count),
            rng.uniform(-5.0, 5.0, count),
            rng.uniform(-0.6, 0.6, count),
            rng.uniform(-10.0, 8.0, count),
            rng.uniform(-12.0, 12.0, count),
        ],
        axis=1,
    )
    u = rng.uniform(-30.0, 30.0, (count, 2))
    return x, u


@pytest.fixture(scope="module")
def trefoil() -> tr.Track:
    track = tr.trefoil()
    assert np.abs(track.kappa).max() > 0.005  # genuinely curved, left and right turns
    assert track.kappa.min() < 0 < track.kappa.max()
    return track


@pytest.fixture(scope="module")
def linear_curvature_track() -> tr.Track:
    """Open 600 m track whose curvature is linear in s (-0.002 .. 0.01 1/m).

    Piecewise-linear interpolation of a linear function is that function, so kappa(s) has
    no kinks at the grid points and finite differences across them are valid, while
    dkappa/ds != 0 still exercises the curvature derivative.
    """
    length, m = 600.0, 601
    s = np.linspace(0.0, length, m)
    kappa = 0.004 + 2e-5 * (s - 300.0)
    heading = np.concatenate([[0.0], np.cumsum(0.5 * (kappa[1:] + kappa[:-1]) * np.diff(s))])
    x = np.concatenate([[0.0], np.cumsum(np.cos(heading[:-1]) * np.diff(s))])
    y = np.concatenate([[0.0], np.cumsum(np.sin(heading[:-1]) * np.diff(s))])
    width = np.full(m, 6.0)
    return tr.Track(s=s, kappa=kappa, width_left=width, width_right=width, x=x, y=y,
                    heading=heading, length=length, closed=False, name="clothoid")


def test_car_derivative_matches_paper_equations(trefoil):
    """car_derivative equals the paper's ODE (NumPy) at 50 random states on a curved track."""
    rng = np.random.default_rng(0)
    x, u = random_states(rng, 50, trefoil)
    kappa = np_kappa(trefoil, x[:, 0])
    assert np.abs(x[:, 2] * kappa).max() < 0.5 and np.abs(kappa).max() > 1e-3
    expected = np_paper_derivative(x, u, trefoil)
    derivative = jax.vmap(dyn.car_derivative, in_axes=(0, 0, None))
    got = np.asarray(derivative(jnp.asarray(x), jnp.asarray(u), trefoil.kappa_at))
    # Same formula evaluated in a different order: a few ulps of |f| <= ~40.
    np.testing.assert_allclose(got, expected, rtol=1e-12, atol=1e-12)


def test_joint_rk4_step_matches_independent_rk4(trefoil):
    """joint_step (RK4, all cars at once) equals an independent NumPy RK4 of the paper's ODE."""
    rng = np.random.default_rng(1)
    x, u = random_states(rng, 50, trefoil)
    dt = 0.1
    got = np.asarray(dyn.joint_step(jnp.asarray(x), jnp.asarray(u), dt, trefoil.kappa_at))
    expected = np_rk4(x, u, dt, trefoil)
    # Same method and stages; only rounding differs (|x| <= ~1.5e3, eps ~ 2e-16).
    np.testing.assert_allclose(got, expected, rtol=1e-12, atol=1e-12)
    # The step actually moves every car (guards against comparing x with x).
    assert np.all(np.abs(got - x)[:, 0] > 0.1)


def test_rk4_is_fourth_order(trefoil):
    """Halving dt shrinks the one-step RK4 error ~32x (local error O(dt^5)): it is RK4, not Euler."""
    rng = np.random.default_rng(2)
    x, u = random_states(rng, 10, trefoil, s_range=(100.0, 300.0))
    step = jax.jit(dyn.joint_step, static_argnums=(2, 3))

    def error(dt):
        fine = x
        for _ in range(64):  # reference: 64 substeps of dt/64 (error 64^-4 times smaller)
            fine = np_rk4(fine, u, dt / 64, trefoil)
        return np.abs(np.asarray(step(jnp.asarray(x), jnp.asarray(u), dt, trefoil.kappa_at)) - fine).max()

    e1, e2 = error(0.2), error(0.1)
    # Local error ratio 2^(p+1): 32 for RK4 (observed ~34), 16 for a third-order method, 4 for Euler.
    assert e1 / e2 > 24.0, (e1, e2)


def test_speed_guard_gives_finite_derivatives_at_standstill(trefoil):
    """At V = 0 (and for n kappa >= 1) the guarded ODE and its Jacobian stay finite."""
    x0 = jnp.array([50.0, 0.0, 1.0, 0.2, -3.0, 4.0])
    u0 = jnp.array([5.0, -5.0])
    f = dyn.car_derivative(x0, u0, trefoil.kappa_at)
    assert np.all(np.isfinite(np.asarray(f)))
    kappa = float(trefoil.kappa_at(50.0))
    # A car at rest cannot turn: ay / V is evaluated at V_EPS; the path terms vanish with V.
    expected = [0.0, -3.0, 0.0, 4.0 / dyn.V_EPS, 5.0, -5.0]
    np.testing.assert_allclose(np.asarray(f), expected, rtol=1e-15, atol=1e-15)
    assert kappa != 0.0
    jac = jax.jacfwd(dyn.car_derivative, argnums=(0, 1))(x0, u0, trefoil.kappa_at)
    assert all(np.all(np.isfinite(np.asarray(j))) for j in jac)
    # Beyond the centre of curvature (1 - n kappa <= 0) the Frenet scale is clamped.
    s_far = float(trefoil.s[int(np.argmax(trefoil.kappa))])
    n_far = 1.5 / float(trefoil.kappa_at(s_far))
    f_far = dyn.car_derivative(jnp.array([s_far, 10.0, n_far, 0.0, 0.0, 0.0]), u0, trefoil.kappa_at)
    assert np.all(np.isfinite(np.asarray(f_far)))


def test_step_jacobian_matches_finite_differences(linear_curvature_track):
    """jax.jacfwd(game.step) w.r.t. x and u equals central finite differences of game.step."""
    vehicles = [VehicleParams(), VehicleParams(v_max=20.0), VehicleParams(length=5.0)]
    game = RaceGame.create(linear_curvature_track, vehicles, dt=0.1, horizon=5)
    step = jax.jit(lambda x, u: game.step(x, u))
    jac = jax.jit(jax.jacfwd(lambda x, u: game.step(x, u), argnums=(0, 1)))
    rng = np.random.default_rng(3)
    # s in [150, 450]: all RK4 stages stay well inside the open track (no clamp at the ends).
    h = 1e-6
    for _ in range(6):
        x, u = random_states(rng, 3, linear_curvature_track, s_range=(150.0, 450.0))
        jx, ju = (np.asarray(j) for j in jac(jnp.asarray(x), jnp.asarray(u)))
        for arg, analytic in ((x, jx), (u, ju)):
            fd = np.zeros_like(analytic)
            for idx in np.ndindex(arg.shape):
                plus, minus = arg.copy(), arg.copy()
                plus[idx] += h
                minus[idx] -= h
                if arg is x:
                    fp, fm = step(jnp.asarray(plus), jnp.asarray(u)), step(jnp.asarray(minus), jnp.asarray(u))
                else:
                    fp, fm = step(jnp.asarray(x), jnp.asarray(plus)), step(jnp.asarray(x), jnp.asarray(minus))
                fd[(...,) + idx] = (np.asarray(fp) - np.asarray(fm)) / (2 * h)
            # Central FD: truncation h^2 |f'''| / 6 ~ 1e-11, rounding eps |f| / h with
            # |f| <= ~500 (the s entries) ~ 1e-7. Entries are O(1e-3 .. 1).
            np.testing.assert_allclose(analytic, fd, rtol=1e-6, atol=5e-7)
    # The cars are independent: d x_i^+ / d x_j = 0 exactly for i != j.
    assert np.all(jx[0, :, 1] == 0.0) and np.all(ju[0, :, 2] == 0.0)


def test_curvature_enters_through_the_track(linear_curvature_track):
    """On a straight the step has no curvature terms; on the curved track chi changes by -kappa ds."""
    straight = tr.straight(length=600.0)
    x = np.array([[300.0, 20.0, 0.0, 0.0, 0.0, 0.0]])
    u = np.zeros((1, 2))
    on_straight = np.asarray(dyn.joint_step(jnp.asarray(x), jnp.asarray(u), 0.1, straight.kappa_at))
    np.testing.assert_allclose(on_straight, [[302.0, 20.0, 0.0, 0.0, 0.0, 0.0]], rtol=0, atol=1e-12)
    curved = np.asarray(dyn.joint_step(jnp.asarray(x), jnp.asarray(u), 0.1, linear_curvature_track.kappa_at))
    # chi' = -kappa s' to first order: about -0.004 * 2 m = -0.008 rad; the car drifts right of a left turn.
    assert curved[0, 3] == pytest.approx(-0.008, rel=0.05)
    assert curved[0, 2] < 0.0


def test_vehicle_params_are_validated():
    """VehicleParams refuses non-positive or non-finite limits with a message naming the field."""
    for bad in (dict(v_max=0.0), dict(v_max=-1.0), dict(length=float("nan")), dict(rho_aero=-0.1),
                dict(min_turn_radius=0.0)):
        with pytest.raises(ValueError, match=f"VehicleParams.{next(iter(bad))}"):
            VehicleParams(**bad)
        # concrete JAX values are checked like NumPy ones (only tracers are not)
        with pytest.raises(ValueError, match=f"VehicleParams.{next(iter(bad))}"):
            VehicleParams(**{k: jnp.asarray(v) for k, v in bad.items()})


def test_a_car_at_the_turn_limit_drives_a_circle_of_min_turn_radius():
    """With ay = ay_turn_max(V) at constant V on a straight, the car drives a circle of
    radius min_turn_radius (heading rate ay / V = V / R): after t it is at
    (s, n) = (R sin(V t / R), R (1 - cos(V t / R))). RK4 at dt = 0.01 s: the error of
    about a quarter turn is ~ steps (V dt / R)^5 R ~ 2e-8 m, far below the 1e-6 tolerance."""
    radius, v = 4.0, 3.0
    veh = VehicleParams(min_turn_radius=radius)
    x = jnp.array([[0.0, v, 0.0, 0.0, 0.0, float(veh.ay_turn_max(v))]])
    flat = lambda s: jnp.zeros_like(s)
    dt = 0.01
    steps = int(round(0.5 * np.pi * radius / v / dt))
    step = jax.jit(lambda x: dyn.joint_step(x, jnp.zeros((1, 2)), dt, flat))
    for _ in range(steps):
        x = step(x)
    t_end = steps * dt  # about a quarter turn
    angle = v * t_end / radius
    np.testing.assert_allclose(np.asarray(x[0, :4]), [radius * np.sin(angle), v, radius * (1 - np.cos(angle)), angle],
                               atol=1e-6)
