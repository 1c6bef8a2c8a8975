"""Frenet-frame point-mass dynamics of the race cars (the paper's vehicle model).

State of one car ``x = [s, V, n, chi, ax, ay]``: arc length along the centreline [m]
(cumulative: it keeps growing over laps), speed [m/s], lateral offset [m] (positive to the
left), heading relative to the centreline [rad], longitudinal and lateral acceleration
[m/s^2]. Input ``u = [jx, jy]``: jerks [m/s^3].

    ds/dt   = V cos(chi) / (1 - n kappa(s))
    dV/dt   = ax
    dn/dt   = V sin(chi)
    dchi/dt = ay / V - kappa(s) V cos(chi) / (1 - n kappa(s))
    dax/dt  = jx
    day/dt  = jy

Two guards keep the model finite where the equations are singular: ``ay / V`` uses
``max(V, V_EPS)``, and ``1 - n kappa`` is kept above ``MIN_FRENET_SCALE`` (only reached when
a car is beyond the centre of curvature). What stops a slow car from spinning is not here
but the turn limit ``|ay| <= V**2 / min_turn_radius`` (``VehicleParams.ay_turn_max``), which
the environment enforces and the game's costs penalise.
"""

from __future__ import annotations

from typing import Callable

import jax
import jax.numpy as jnp

STATE_DIM = 6
INPUT_DIM = 2
S, V, N_LAT, CHI, AX, AY = range(STATE_DIM)
V_EPS = 1.0  # [m/s] speed below which ay/V is evaluated at V_EPS
MIN_FRENET_SCALE = 0.05

CurvatureFn = Callable[[jax.Array], jax.Array]


def car_derivative(x: jax.Array, u: jax.Array, kappa_at: CurvatureFn) -> jax.Array:
    """Continuous-time state derivative of one car, shape ``(6,)``."""
    s, v, n, chi, ax, ay = x
    kappa = kappa_at(s)
    s_dot = v * jnp.cos(chi) / jnp.maximum(1.0 - n * kappa, MIN_FRENET_SCALE)
    return jnp.stack(
        [
            s_dot,
            ax,
            v * jnp.sin(chi),
            ay / jnp.maximum(v, V_EPS) - kappa * s_dot,
            u[0],
            u[1],
        ]
    )


def rk4_step(x: jax.Array, u: jax.Array, dt: float, kappa_at: CurvatureFn) -> jax.Array:
    """One classical Runge-Kutta step of one car with the input held over ``dt`` [s]."""
    k1 = car_derivative(x, u, kappa_at)
    k2 = car_derivative(x + 0.5 * dt * k1, u, kappa_at)
    k3 = car_derivative(x + 0.5 * dt * k2, u, kappa_at)
    k4 = car_derivative(x + dt * k3, u, kappa_at)
    return x + dt / 6.0 * (k1 + 2.0 * k2 + 2.0 * k3 + k4)


def joint_step(x: jax.Array, u: jax.Array, dt: float, kappa_at: CurvatureFn) -> jax.Array:
    """Advance all cars by ``dt``: ``x (N, 6)``, ``u (N, 2)`` -> ``(N, 6)``.

    The cars do not interact through the dynamics, so the joint RK4 step is the per-car
    step mapped over cars. The result has ``x``'s dtype (a float32 state stays float32 when
    the track's tables are float64), so a ``lax.scan`` of steps carries one type.
    """
    return jax.vmap(lambda xi, ui: rk4_step(xi, ui, dt, kappa_at))(x, u).astype(jnp.result_type(x))
