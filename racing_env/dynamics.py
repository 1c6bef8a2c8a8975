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

A car with aerodynamic drag (``VehicleParams.c_drag > 0``) has ``dV/dt = ax - D`` instead, with
the drag deceleration ``D = c_drag (1 - r) V |V|`` and ``r`` the share of it another car's wake
takes away (:func:`slipstream_reduction`; ``r = 0`` without a slipstream): ``ax`` is then the
acceleration the tyres deliver, which the car must hold at ``D`` to keep its speed. The drag
couples the cars (car i's ``dV/dt`` depends on the states of the cars ahead of it), so the joint
step of cars with drag (:func:`joint_step` with an :class:`Aero`) integrates the joint state as
one system; without drag it is the per-car step mapped over the cars, as in the paper.

Two guards keep the model finite where the equations are singular: ``ay / V`` uses
``max(V, V_EPS)``, and ``1 - n kappa`` is kept above ``MIN_FRENET_SCALE`` (only reached when
a car is beyond the centre of curvature). What stops a slow car from spinning is not here
but the turn limit ``|ay| <= V**2 / min_turn_radius`` (``VehicleParams.ay_turn_max``), which
the environment enforces and the game's costs penalise.
"""

from __future__ import annotations

import dataclasses
from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp

STATE_DIM = 6
INPUT_DIM = 2
S, V, N_LAT, CHI, AX, AY = range(STATE_DIM)
V_EPS = 1.0  # [m/s] speed below which ay/V is evaluated at V_EPS
MIN_FRENET_SCALE = 0.05

CurvatureFn = Callable[[jax.Array], jax.Array]
WrapFn = Callable[[jax.Array], jax.Array]


@dataclasses.dataclass(frozen=True)
class Slipstream:
    """The wake of a car: how much of a following car's drag it takes away (a static constant
    of a game; docs/model.md, "Drag and the slipstream").

    For car i behind car j (``ds = s_j - s_i`` wrapped, the gap between them
    ``g = ds - l``, ``dn = n_j - n_i``, ``l`` and ``w`` the mean length and width of the two):

        r_ij = reduction * sigmoid(g / (onset l)) * exp(-g / (wake_length l)) * exp(-(dn / (wake_width w))^2)

    and car i's drag is ``(1 - r_i)`` times its drag in still air, ``r_i = 1 - prod_j (1 - r_ij)``
    (each car ahead shelters it from the air the others let through). The sigmoid switches
    the wake on behind the car ahead (a car alongside or ahead gets none), the exponentials let
    it fade with the gap and the lateral offset; all of it smooth, so the planners' game has
    its gradients.

    Attributes:
        reduction: the amplitude of the reduction (the share of the drag removed just behind,
            before the onset and the fading), in ``[0, 1)``.
        wake_length: the gap over which the wake fades by ``1/e`` [mean car lengths].
        onset: the width of the sigmoid that switches the wake on at ``g = 0`` [mean car lengths].
        wake_width: the lateral offset at which the wake has fallen by ``1/e`` [mean car widths].
    """

    reduction: float = 0.51
    wake_length: float = 3.2
    onset: float = 0.125
    wake_width: float = 0.5

    def __post_init__(self) -> None:
        if not (0.0 <= self.reduction < 1.0):
            raise ValueError(f"Slipstream.reduction must be in [0, 1), got {self.reduction!r}")
        for name in ("wake_length", "onset", "wake_width"):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and value > 0 and value < float("inf")):
                raise ValueError(f"Slipstream.{name} must be a finite number > 0, got {value!r}")


#: The slipstream of the races (fitted to measured drag reductions; docs/model.md).
SLIPSTREAM = Slipstream()


class Aero(NamedTuple):
    """What the joint step of cars with drag needs besides the state (built by
    :meth:`racing_env.RaceGame.step` from the cars' parameters).

    Attributes:
        c_drag: ``(N,)`` drag per unit mass [1/m] (0: no drag).
        length: ``(N,)`` footprint lengths [m] (the wake's length scale).
        width: ``(N,)`` footprint widths [m] (the wake's lateral scale).
        wake: ``(N,)`` 1 for a car whose wake counts, 0 for one out of the race.
        wrap_ds: the track's signed arc-length difference (:meth:`racing_env.track.Track.wrap_ds`).
        slipstream: the wake model, or None: drag alone.
    """

    c_drag: jax.Array
    length: jax.Array
    width: jax.Array
    wake: jax.Array
    wrap_ds: WrapFn
    slipstream: Slipstream | None


def slipstream_reduction(x: jax.Array, aero: Aero) -> jax.Array:
    """The share ``r_i`` of every car's still-air drag that the wakes of the cars ahead take
    away, ``(N,)`` in ``[0, reduction]`` (:class:`Slipstream`; zeros without one).

    Computed in logarithms, so a car far ahead or far behind gives an exact 0 in float32 as
    in float64 (no overflowing exponential times a vanishing sigmoid).
    """
    slip = aero.slipstream
    n_cars = x.shape[0]
    if slip is None:
        return jnp.zeros(n_cars, dtype=x.dtype)
    ds = aero.wrap_ds(x[None, :, S] - x[:, None, S])  # [i, j] = s_j - s_i: > 0 with j ahead of i
    dn = x[None, :, N_LAT] - x[:, None, N_LAT]
    length = 0.5 * (aero.length[:, None] + aero.length[None, :])
    width = 0.5 * (aero.width[:, None] + aero.width[None, :])
    gap = ds - length
    log_r = (jax.nn.log_sigmoid(gap / (slip.onset * length)) - gap / (slip.wake_length * length)
             - (dn / (slip.wake_width * width)) ** 2)
    others = 1.0 - jnp.eye(n_cars, dtype=x.dtype)
    r_ij = slip.reduction * jnp.exp(log_r) * others * aero.wake[None, :]
    return (1.0 - jnp.prod(1.0 - r_ij, axis=1)).astype(x.dtype)


def drag_deceleration(x: jax.Array, aero: Aero) -> jax.Array:
    """Every car's deceleration by drag ``c_drag (1 - r) V |V|`` [m/s^2], ``(N,)``."""
    v = x[:, V]
    return aero.c_drag * (1.0 - slipstream_reduction(x, aero)) * v * jnp.abs(v)


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


def joint_derivative(x: jax.Array, u: jax.Array, kappa_at: CurvatureFn, aero: Aero) -> jax.Array:
    """Continuous-time derivative of the joint state of cars with drag, ``(N, 6)``: every
    car's :func:`car_derivative` with its drag deceleration (:func:`drag_deceleration`, which
    couples the cars through the slipstream) taken off ``dV/dt``."""
    dx = jax.vmap(lambda xi, ui: car_derivative(xi, ui, kappa_at))(x, u)
    return dx.at[:, V].add(-drag_deceleration(x, aero).astype(dx.dtype))


def joint_step(x: jax.Array, u: jax.Array, dt: float, kappa_at: CurvatureFn, aero: Aero | None = None) -> jax.Array:
    """Advance all cars by ``dt``: ``x (N, 6)``, ``u (N, 2)`` -> ``(N, 6)``.

    Without ``aero`` (no car has drag) the cars do not interact through the dynamics, and the
    joint RK4 step is the per-car step mapped over cars. With ``aero`` it is one RK4 step of
    :func:`joint_derivative` on the joint state (the slipstream couples the cars within the
    step). The result has ``x``'s dtype (a float32 state stays float32 when the track's tables
    are float64), so a ``lax.scan`` of steps carries one type.
    """
    if aero is None:
        return jax.vmap(lambda xi, ui: rk4_step(xi, ui, dt, kappa_at))(x, u).astype(jnp.result_type(x))
    k1 = joint_derivative(x, u, kappa_at, aero)
    k2 = joint_derivative(x + 0.5 * dt * k1, u, kappa_at, aero)
    k3 = joint_derivative(x + 0.5 * dt * k2, u, kappa_at, aero)
    k4 = joint_derivative(x + dt * k3, u, kappa_at, aero)
    return (x + dt / 6.0 * (k1 + 2.0 * k2 + 2.0 * k3 + k4)).astype(jnp.result_type(x))
