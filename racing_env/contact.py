"""Contact between cars: a swept footprint test and an impulse that makes cars collide.

Two cars collide when their footprints (rectangles of ``length x width`` at ``(s, n)`` with
heading ``chi`` relative to the centreline) meet at any time inside a step, not only at its
end: :func:`sweep` moves every pair's relative position linearly over the step (the headings
held at the step's end) and finds, per pair, the first fraction ``toi`` of the step at which
the separating-axis test fails. A closing speed of ``length / dt`` or more (47 m/s for the
paper's car at ``dt = 0.1`` s) therefore cannot carry one car through another between two
samples.

Each pair that meets is resolved as two rigid bodies without rotation (point masses with a
footprint) in the centreline's local Cartesian frame at the pair (tangent ``t``, normal to
the left ``n``; a car's velocity there is ``V (cos chi, sin chi)``):

* the **contact normal** is the separating axis the footprints were last to close on (the
  axis of least penetration at ``toi``), pointing from the first car to the second;
* an **impulse** ``J = -(1 + e) v_n / (1/m_i + 1/m_j)`` along it when the cars approach
  (``v_n < 0``, ``e`` the restitution), and a **friction** impulse along the tangent that
  opposes the sliding, at most ``mu J`` and never reversing it (Coulomb);
* each car of a pair goes back to ``toi`` and drives the rest of the step with its new
  velocity, whose length and direction are its new ``V`` and ``chi``; the accelerations
  ``ax, ay`` are kept (what the driver asks for);
* footprints still overlapping at the end are pushed apart along their axis of least
  penetration by the overlap plus :attr:`ContactModel.gap`, shared in inverse proportion to
  the masses.

Several contacts of one car in a step are summed (one Jacobi pass over the pairs); each
pair's impulse acts equally and oppositely on its two cars, so the momentum of every pair,
and of the field, is conserved. With ``e <= 1`` and friction that only opposes sliding no
contact adds kinetic energy. The cars do not spin: the footprint keeps its heading ``chi``,
which follows the velocity.

Everything is pure JAX on the joint states ``x (N, 6)`` before and after a step; a pair is
resolved only when both its cars race (``racing (N,)`` bool). Rules and figures: docs/rules.md.
"""

from __future__ import annotations

import dataclasses
import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from racing_env.dynamics import CHI, MIN_FRENET_SCALE, N_LAT, S, V
from racing_env.physics import footprint_overlap
from racing_env.track import Track
from racing_env.vehicle import VehicleParams

CONTACT_MODES = ("physics", "ghost")
"""``physics``: cars collide (this module); ``ghost``: they drive through each other, and
contact is only detected (footprints overlapping at the end of a step)."""

_TINY = 1e-12


@functools.partial(jax.tree_util.register_dataclass, data_fields=["restitution", "friction", "gap"],
                   meta_fields=["physics"])
@dataclasses.dataclass(frozen=True)
class ContactModel:
    """How cars that meet interact (part of :class:`racing_env.race.RaceParams`).

    Attributes:
        physics: whether cars collide (a Python bool: static, so a compiled step holds one
            mode; ``False`` is the ``ghost`` mode).
        restitution: ``e`` in ``[0, 1]``, the share of the closing speed along the contact
            normal that the cars separate with (0: they stay together, 1: elastic).
        friction: ``mu >= 0``, the Coulomb coefficient of the tangential impulse.
        gap: [m] the distance left between two footprints pushed apart.
    """

    physics: bool
    restitution: jax.Array
    friction: jax.Array
    gap: jax.Array

    @classmethod
    def create(cls, mode: str = "physics", restitution: float = 0.3, friction: float = 0.5,
               gap: float = 0.02) -> "ContactModel":
        """The model of ``mode`` (one of :data:`CONTACT_MODES`), checked."""
        check_contact(mode, restitution, friction)
        return cls(mode == "physics", np.float64(restitution), np.float64(friction), np.float64(gap))


def check_contact(mode: str, restitution: float, friction: float) -> None:
    """Refuse an unknown contact mode, a restitution outside ``[0, 1]`` and a negative or
    non-finite friction coefficient."""
    if mode not in CONTACT_MODES:
        raise ValueError(f"contact must be one of {CONTACT_MODES}, got {mode!r}")
    if not (isinstance(restitution, (int, float, np.number)) and not isinstance(restitution, bool)
            and 0.0 <= float(restitution) <= 1.0):
        raise ValueError(f"restitution must be a number in [0, 1], got {restitution!r}")
    if not (isinstance(friction, (int, float, np.number)) and not isinstance(friction, bool)
            and np.isfinite(friction) and float(friction) >= 0.0):
        raise ValueError(f"contact_friction must be a finite number >= 0, got {friction!r}")


class Sweep(NamedTuple):
    """Every pair's meeting inside a step; ``(N, N)`` fields, row i and column j the pair
    (i, j), quantities of the pair seen from car i.

    Attributes:
        touch: the footprints meet inside the step (symmetric, false on the diagonal and for
            pairs with a car not racing).
        toi: the first fraction of the step at which they meet, in ``[0, 1]`` (1 where they
            do not).
        normal: ``(N, N, 2)`` the unit contact normal from i to j in the local ``(t, n)``
            frame.
        axis: which separating axis the normal is: 0/1 car i's length/width axis, 2/3 car
            j's (int32).
        closing: the speed [m/s] at which the two approach along the normal, ``>= 0``.
        kappa: the centreline's curvature [1/m] at the pair, the local frame's.
    """

    touch: jax.Array
    toi: jax.Array
    normal: jax.Array
    axis: jax.Array
    closing: jax.Array
    kappa: jax.Array


def _pair_kappa(x: jax.Array, track: Track) -> jax.Array:
    """The centreline's curvature ``(N, N)`` [1/m] at every pair's mean arc length."""
    ds = track.wrap_ds(x[None, :, S] - x[:, None, S])
    return track.kappa_at(x[:, None, S] + 0.5 * ds)


def _pair_frame(x: jax.Array, track: Track, kappa: jax.Array) -> tuple[jax.Array, jax.Array]:
    """Car j's position relative to car i in the local frame at the pair, ``(N, N)`` each:
    ``dx`` along the centreline (scaled by ``1 - n kappa`` at the pair's mean, ``kappa``
    from :func:`_pair_kappa`) and ``dy``."""
    ds = track.wrap_ds(x[None, :, S] - x[:, None, S])
    n_mean = 0.5 * (x[None, :, N_LAT] + x[:, None, N_LAT])
    return ds * (1.0 - n_mean * kappa), x[None, :, N_LAT] - x[:, None, N_LAT]


def _axes_and_reach(chi: jax.Array, vehicles: VehicleParams) -> tuple[jax.Array, jax.Array]:
    """The four separating axes of every pair as unit vectors ``(N, N, 4, 2)`` in the local
    frame (car i's length and width axes, then car j's) and the sum of the two footprints'
    half extents along each, ``(N, N, 4)``. Trigonometry per car only: the footprints' own
    axes are ``(cos chi, sin chi)`` and ``(-sin chi, cos chi)``."""
    num = chi.shape[0]
    cos, sin = jnp.cos(chi), jnp.sin(chi)
    along = jnp.stack([cos, sin], axis=-1)  # (N, 2): each car's length axis
    across = jnp.stack([-sin, cos], axis=-1)  # its width axis
    own = jnp.stack([along, across], axis=1)  # (N, 2, 2)
    axes = jnp.concatenate([jnp.broadcast_to(own[:, None], (num, num, 2, 2)),
                            jnp.broadcast_to(own[None, :], (num, num, 2, 2))], axis=2)  # (N, N, 4, 2)
    half_l = 0.5 * jnp.broadcast_to(jnp.asarray(vehicles.length), (num,))
    half_w = 0.5 * jnp.broadcast_to(jnp.asarray(vehicles.width), (num,))

    def extent(car_along, car_across, half_length, half_width):  # a footprint's half extent along each axis
        return (half_length * jnp.abs(jnp.sum(axes * car_along, axis=-1))
                + half_width * jnp.abs(jnp.sum(axes * car_across, axis=-1)))

    reach = (extent(along[:, None, None], across[:, None, None], half_l[:, None, None], half_w[:, None, None])
             + extent(along[None, :, None], across[None, :, None], half_l[None, :, None], half_w[None, :, None]))
    return axes, reach


def _velocity(x: jax.Array) -> jax.Array:
    """Every car's velocity ``(N, 2)`` [m/s] in the local ``(t, n)`` frame."""
    return x[:, V, None] * jnp.stack([jnp.cos(x[:, CHI]), jnp.sin(x[:, CHI])], axis=-1)


def pairs_racing(racing: jax.Array) -> jax.Array:
    """``(N, N)`` bool: both cars of the pair race (false on the diagonal)."""
    return racing[:, None] & racing[None, :] & ~jnp.eye(racing.shape[0], dtype=bool)


def _project(dx: jax.Array, dy: jax.Array, axes: jax.Array) -> jax.Array:
    """The pairs' relative positions along each of their axes, ``(N, N, 4)``."""
    return dx[..., None] * axes[..., 0] + dy[..., None] * axes[..., 1]


def _pick(values: jax.Array, axis: jax.Array) -> jax.Array:
    """``values[i, j, axis[i, j]]`` of ``(N, N, 4, ...)`` values."""
    index = axis.reshape(axis.shape + (1,) * (values.ndim - 2))
    return jnp.take_along_axis(values, index, axis=2)[:, :, 0]


def sweep(x0: jax.Array, x1: jax.Array, racing: jax.Array, vehicles: VehicleParams, track: Track) -> Sweep:
    """Where the footprints of every pair first meet while the cars move from ``x0`` to
    ``x1`` (joint states ``(N, 6)``), the pair's relative position moving linearly and the
    headings held at ``x1``'s (the local frame's curvature too). Pure JAX."""
    kappa = _pair_kappa(x1, track)
    dx0, dy0 = _pair_frame(x0, track, kappa)
    dx1, dy1 = _pair_frame(x1, track, kappa)
    axes, reach = _axes_and_reach(x1[:, CHI], vehicles)
    p0 = _project(dx0, dy0, axes)
    p1 = _project(dx1, dy1, axes)
    slope = p1 - p0
    still = jnp.abs(slope) < _TINY
    safe = jnp.where(still, 1.0, slope)
    t_a, t_b = (-reach - p0) / safe, (reach - p0) / safe
    inside = jnp.abs(p0) <= reach
    lo = jnp.where(still, jnp.where(inside, -jnp.inf, jnp.inf), jnp.minimum(t_a, t_b))
    hi = jnp.where(still, jnp.where(inside, jnp.inf, -jnp.inf), jnp.maximum(t_a, t_b))
    enter = jnp.maximum(jnp.max(lo, axis=-1), 0.0)
    leave = jnp.minimum(jnp.min(hi, axis=-1), 1.0)
    touch = (enter <= leave) & pairs_racing(racing)
    toi = jnp.where(touch, enter, 1.0)
    p_toi = p0 + toi[..., None] * slope
    axis = jnp.argmin(reach - jnp.abs(p_toi), axis=-1).astype(jnp.int32)
    side = jnp.where(_pick(p_toi, axis) < 0.0, -1.0, 1.0)
    normal = side[..., None] * _pick(axes, axis)
    velocity = _velocity(x1)
    approach = jnp.sum((velocity[None, :, :] - velocity[:, None, :]) * normal, axis=-1)
    closing = jnp.where(touch, jnp.maximum(-approach, 0.0), 0.0)
    return Sweep(touch, toi, normal, axis, closing, kappa)


def _upper(num: int) -> jax.Array:
    return jnp.triu(jnp.ones((num, num), dtype=bool), 1)


def _to_frenet(x: jax.Array, shift: jax.Array, track: Track) -> jax.Array:
    """``x`` with its cars moved by ``shift (N, 2)`` [m] in the local ``(t, n)`` frame."""
    scale = jnp.maximum(1.0 - x[:, N_LAT] * track.kappa_at(x[:, S]), MIN_FRENET_SCALE)
    return x.at[:, S].add(shift[:, 0] / scale).at[:, N_LAT].add(shift[:, 1])


def _pair_sum(pair_vectors: jax.Array) -> jax.Array:
    """Per car, the sum of the upper triangle's ``(N, N, 2)`` pair vectors acting on it:
    ``+v`` on the second car of a pair, ``-v`` on the first (equal and opposite)."""
    return jnp.sum(pair_vectors, axis=0) - jnp.sum(pair_vectors, axis=1)


def _inverse_masses(vehicles: VehicleParams, num: int) -> jax.Array:
    return 1.0 / jnp.broadcast_to(jnp.asarray(vehicles.mass), (num,))


def collide(x0: jax.Array, x1: jax.Array, hit: Sweep, vehicles: VehicleParams, model: ContactModel,
            track: Track, dt: float) -> jax.Array:
    """The joint state after the step from ``x0`` to ``x1`` whose meetings are ``hit``
    (:func:`sweep`): the impulses exchanged, the cars of each pair moved from their meeting
    with their new velocities, then pushed apart (:func:`separate`). Cars without contact
    keep ``x1`` bit for bit. ``(N, 6)`` in ``x1``'s dtype."""
    num = x1.shape[0]
    dtype = jnp.result_type(x1)
    inv = _inverse_masses(vehicles, num)
    pair_inv = inv[:, None] + inv[None, :]
    velocity = _velocity(x1)
    relative = velocity[None, :, :] - velocity[:, None, :]
    normal = hit.normal
    tangent = jnp.stack([-normal[..., 1], normal[..., 0]], axis=-1)
    v_n = jnp.sum(relative * normal, axis=-1)
    v_t = jnp.sum(relative * tangent, axis=-1)
    active = hit.touch & _upper(num)
    j_n = jnp.where(active & (v_n < 0.0), -(1.0 + model.restitution) * v_n / pair_inv, 0.0)
    j_t = -jnp.sign(v_t) * jnp.minimum(model.friction * j_n, jnp.abs(v_t) / pair_inv)
    impulse = j_n[..., None] * normal + j_t[..., None] * tangent
    new_velocity = velocity + inv[:, None] * _pair_sum(jnp.where(active[..., None], impulse, 0.0))

    hit_any = hit.touch.any(axis=1)
    toi = jnp.min(jnp.where(hit.touch, hit.toi, 1.0), axis=1)
    rest = (1.0 - toi) * dt
    speed = jnp.sqrt(jnp.sum(new_velocity**2, axis=-1))
    heading = jnp.arctan2(new_velocity[:, 1], new_velocity[:, 0])
    met = x0 + toi[:, None] * (x1 - x0)
    moved = _to_frenet(met.at[:, V].set(speed).at[:, CHI].set(heading), rest[:, None] * new_velocity, track)
    resolved = x1.at[:, S].set(moved[:, S]).at[:, N_LAT].set(moved[:, N_LAT]).at[:, V].set(speed).at[:, CHI].set(
        heading)
    x = jnp.where(hit_any[:, None], resolved.astype(dtype), x1)
    return separate(x, hit.touch, hit.kappa, vehicles, model, track)


def separate(x: jax.Array, pairs: jax.Array, kappa: jax.Array, vehicles: VehicleParams, model: ContactModel,
             track: Track) -> jax.Array:
    """Push apart the footprints of the ``pairs (N, N)`` that overlap in ``x``, along each
    pair's axis of least penetration, by the overlap plus ``model.gap``, each car's share
    in inverse proportion to its mass; ``kappa (N, N)``: the local frames' curvature (the
    sweep's: the cars moved a step at most). Cars of no such pair keep ``x`` bit for bit."""
    num = x.shape[0]
    dx, dy = _pair_frame(x, track, kappa)
    axes, reach = _axes_and_reach(x[:, CHI], vehicles)
    p = _project(dx, dy, axes)
    depth = reach - jnp.abs(p)
    overlapping = jnp.all(depth >= 0.0, axis=-1) & pairs & _upper(num)
    axis = jnp.argmin(depth, axis=-1)
    side = jnp.where(_pick(p, axis) < 0.0, -1.0, 1.0)
    push = (jnp.min(depth, axis=-1) + model.gap) * side
    direction = _pick(axes, axis)
    inv = _inverse_masses(vehicles, num)
    share = inv[:, None] / (inv[:, None] + inv[None, :])  # car i's share of pair (i, j)
    # the pair's push as a vector acting on the second car; each car moves by its share
    on_second = jnp.where(overlapping[..., None], push[..., None] * direction, 0.0)
    shift = jnp.sum(on_second * share.T[..., None], axis=0) - jnp.sum(on_second * share[..., None], axis=1)
    moved = _to_frenet(x, shift, track).astype(jnp.result_type(x))
    involved = (overlapping | overlapping.T).any(axis=1)
    return jnp.where(involved[:, None], moved, x)


def overlapping(x: jax.Array, racing: jax.Array, vehicles: VehicleParams, track: Track) -> jax.Array:
    """``(N, N)`` bool: the footprints of two racing cars overlap at ``x`` (the ghost mode's
    contact)."""
    return footprint_overlap(x, vehicles, track) & pairs_racing(racing)
