"""What the environment enforces and detects beyond the smooth game model.

The planners' game only *penalises* leaving the gg diagram, exceeding the drive limit or driving
backwards; the environment makes them impossible, and it detects footprint overlaps
(collisions) and cars beyond the track boundary. All functions are pure JAX on the joint
state ``x (N, 6)``.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from racing_env.dynamics import AX, AY, CHI, N_LAT, S, V
from racing_env.track import Track
from racing_env.vehicle import VehicleParams


def enforce_limits(x: jax.Array, vehicles: VehicleParams) -> jax.Array:
    """Project every car's accelerations onto its feasible set and keep ``V >= 0``.

    The acceleration vector is scaled radially onto the gg circle ``|a| <= rho(V)`` (the
    paper's combined-acceleration limit), then ``ax`` is capped at the drive limit
    ``drive_max(V)`` (``ax_max(V)`` for a car without drag), and
    ``ay`` is clipped so the cap cannot push ``|a|`` past ``rho`` (only possible above v_max,
    where ``ax_max < 0``), and finally to the turn limit ``V**2 / min_turn_radius``. A car
    cannot reverse: ``V`` stops at zero, and a stopped car keeps no braking and (by the turn
    limit) no lateral acceleration.
    """
    v = jnp.maximum(x[:, V], 0.0)
    ax, ay = x[:, AX], x[:, AY]
    rho = vehicles.rho(v)
    norm = jnp.sqrt(ax**2 + ay**2)
    scale = jnp.where(norm > rho, rho / jnp.maximum(norm, 1e-12), 1.0)
    ax, ay = ax * scale, ay * scale
    ax = jnp.clip(ax, -rho, vehicles.drive_max(v))
    ay_room = jnp.sqrt(jnp.maximum(rho**2 - ax**2, 0.0))
    ay_room = jnp.minimum(ay_room, vehicles.ay_turn_max(v))
    ay = jnp.clip(ay, -ay_room, ay_room)
    ax = jnp.where(v <= 0.0, jnp.maximum(ax, 0.0), ax)
    dtype = jnp.result_type(x)  # the limits are float64 constants; the state keeps its dtype
    return x.at[:, V].set(v.astype(dtype)).at[:, AX].set(ax.astype(dtype)).at[:, AY].set(ay.astype(dtype))


def saturate_jerk(x: jax.Array, u: jax.Array, vehicles: VehicleParams, dt: float) -> jax.Array:
    """Limit the jerks so the accelerations end the step inside their speed-dependent caps.

    Projecting ``ax`` only at the end of a step would let it ramp past ``ax_max`` inside
    the step, and a car driven flat out would settle above its v_max. With the jerk capped
    at ``(drive_max(V) - ax) / dt`` (``ax_max(V)`` without drag) the speed approaches v_max
    from below (for ``2 ax_max_0 dt < v_max``, true for any sensible car; a car with drag in a
    slipstream can exceed it). Likewise the lateral jerk keeps
    ``|ay|`` within the turn limit ``V**2 / min_turn_radius`` at the step's start speed, so
    a slow car cannot spin inside the step before ``enforce_limits`` clips ``ay``.

    A stopped car (``V <= 0``) gets no negative longitudinal jerk (inside the step it would
    make ``V < 0``: the car creeping backwards) and, by the turn limit, no lateral jerk.
    """
    v, ax, ay = x[:, V], x[:, AX], x[:, AY]
    jx = jnp.minimum(u[:, 0], (vehicles.drive_max(v) - ax) / dt)
    jx = jnp.where(v <= 0.0, jnp.maximum(jx, 0.0), jx)
    ay_cap = vehicles.ay_turn_max(jnp.maximum(v, 0.0))
    jy = jnp.clip(u[:, 1], (-ay_cap - ay) / dt, (ay_cap - ay) / dt)
    return jnp.stack([jx, jy], axis=-1)


def drive(game, x: jax.Array, actions: jax.Array) -> jax.Array:
    """One step of the environment's car physics: ``x (N, 6)`` -> the next joint state.

    ``actions (N, 2)`` are normalised jerks, clipped to ``[-1, 1]`` and scaled by each
    car's jerk limits; the jerks are saturated (:func:`saturate_jerk`), the game's RK4 step
    is taken and the limits are enforced (:func:`enforce_limits`). ``game`` is a
    :class:`racing_env.RaceGame` (dynamics, vehicles, ``dt``). The environment's step is
    this plus the race's bookkeeping (rules, incidents, observations). The next state has
    ``x``'s dtype.
    """
    u = jnp.clip(actions, -1.0, 1.0) * game.vehicles.jerk_max
    u = saturate_jerk(x, u, game.vehicles, game.dt)
    return enforce_limits(game.step(x, u), game.vehicles).astype(jnp.result_type(x))


def footprint_overlap(x: jax.Array, vehicles: VehicleParams, track: Track) -> jax.Array:
    """Which pairs of car footprints overlap, ``(N, N)`` bool, symmetric, false diagonal.

    Each footprint is a rectangle (length x width) at ``(s, n)`` with heading ``chi``
    relative to the centreline, compared in the local frame of the centreline at the
    pair's mean arc length (longitudinal gaps scaled by ``1 - n kappa``). The test is the
    separating-axis theorem on the four edge normals of the two rectangles.
    """
    ds = track.wrap_ds(x[None, :, S] - x[:, None, S])
    n_mean = 0.5 * (x[None, :, N_LAT] + x[:, None, N_LAT])
    kappa = track.kappa_at(x[:, None, S] + 0.5 * ds)
    dx = ds * (1.0 - n_mean * kappa)
    dy = x[None, :, N_LAT] - x[:, None, N_LAT]
    chi_i = jnp.broadcast_to(x[:, None, CHI], dx.shape)
    chi_j = jnp.broadcast_to(x[None, :, CHI], dx.shape)
    axes = jnp.stack([chi_i, chi_i + jnp.pi / 2, chi_j, chi_j + jnp.pi / 2], axis=-1)
    half_l, half_w = 0.5 * vehicles.length, 0.5 * vehicles.width

    def radius(half_length, half_width, heading):
        rel = heading[..., None] - axes
        return half_length * jnp.abs(jnp.cos(rel)) + half_width * jnp.abs(jnp.sin(rel))

    reach = radius(half_l[:, None, None], half_w[:, None, None], chi_i) + radius(
        half_l[None, :, None], half_w[None, :, None], chi_j
    )
    separation = jnp.abs(dx[..., None] * jnp.cos(axes) + dy[..., None] * jnp.sin(axes))
    overlap = jnp.all(separation <= reach, axis=-1)
    return overlap & ~jnp.eye(x.shape[0], dtype=bool)


def off_track(x: jax.Array, track: Track) -> jax.Array:
    """Cars whose centre is beyond the left or right boundary, ``(N,)`` bool."""
    s, n = x[:, S], x[:, N_LAT]
    return (n > track.width_left_at(s)) | (-n > track.width_right_at(s))
