"""The racing-line driver's rules of the road: adaptive cruise behind a car on its line, passing
only where the line beside it is clear, and never moving across into a car alongside.

These are the parts a real racing-line controller has besides its tracking law
(:class:`planners.scripted.RacelineDriver`): the tracking law says where the line is and how
fast to drive it; the functions here say how far the car may follow it given the other cars.
Every function is pure JAX on fixed shapes (the joint state ``x (N, 6)``, per-car arrays
``(N,)``), so the driver's law stays jittable and vmappable over races.

The driver's picture of traffic (:func:`traffic`) is the joint state seen from its own car
``i``: the wrapped arc-length gap ``ds_k = s_k - s_i`` to every car (positive: ahead), the
bumper-to-bumper gap along its path, and the half sums of the two cars' lengths and widths.
A car is *on the driver's path* when its centre lies within ``w_ik + LATERAL_CLEARANCE`` of
where the driver will be when it gets there (:func:`path_offsets`: the lateral error to the
path's target decays as the tracking law's critically damped response). Three rules:

* **Adaptive cruise** (:func:`following_acceleration`): behind every car on its path within
  the look-ahead, the driver asks for at most the smaller of a constant-time-gap law
  (``standstill + time_gap V``, the leader's acceleration fed forward) and the constant
  deceleration that matches the leader's speed at the standstill gap (the closing speed's
  distance over the jerk-limited ramp into braking allowed for). The caller clips it to the
  car's own gg room: the driver brakes within its limits.
* **Passing** (:func:`pass_target`): when the nearest car on its line is slower than the
  line's speed there and within ``PASS_LOOKAHEAD`` seconds at the driver's speed (its
  bumper gap beyond the standstill gap), the driver moves to the side with more room beside
  that car, if the track is wide enough there and no other car is in that lane from alongside
  to the look-ahead; otherwise it stays on its line and follows. Further back it keeps to its
  line: where the car ahead is when the driver reaches it is not where it is now.
* **Alongside** (:func:`alongside`): the lateral target never comes nearer than
  ``w_ik + ALONGSIDE_CLEARANCE`` to a car beside it (overlapping in arc length, up to a margin
  ahead and the standstill gap behind): the car that moves across answers for the contact.
  The driver's path at such a car is that target, so a car it is properly beside is not on
  its path, and one it already overlaps is (it brakes as well as moving away).

Where no other car is near, every rule leaves the tracking law's numbers untouched (a
select or a minimum with infinity), so alone the driver laps exactly as without the rules.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from racing_env.dynamics import AX, N_LAT, S, V
from racing_env.track import Track

RACELINE_TIME_GAP = 0.5  # [s] time gap kept to a car ahead on the path
RACELINE_STANDSTILL = 3.0  # [m] bumper-to-bumper gap kept behind a car ahead at any speed
FOLLOW_GAP_GAIN = 0.5  # [1/s^2] ax += gain * (gap - desired gap)
FOLLOW_SPEED_GAIN = 1.0  # [1/s] ax += gain * (v_ahead - V); with the gap gain a damping ratio of ~0.9
FOLLOW_LAG = 0.4  # [s] the jerk-limited ramp into braking: the gap closed before braking bites
TRAFFIC_LOOKAHEAD = 3.0  # [s] cars up to this many seconds ahead at the driver's speed count
TRAFFIC_REACH = 10.0  # [m] plus this, so that a car stopped ahead counts at a standstill
LATERAL_CLEARANCE = 0.5  # [m] between the footprints: nearer the path than this is on it
ALONGSIDE_CLEARANCE = 0.75  # [m] between the footprints of cars side by side (more than LATERAL_CLEARANCE)
PASS_CLEARANCE = 1.0  # [m] between the footprints when passing (more than LATERAL_CLEARANCE)
PASS_SPEED_MARGIN = 1.0  # [m/s] a car is passed when it is this much slower than the line there
PASS_COMMITMENT = 2.0  # side score per metre the driver already is on that side of the car passed
PASS_LOOKAHEAD = 1.5  # [s] a pass begins when the car to pass is within this many seconds at the driver's speed
ALONGSIDE_AHEAD = 1.0  # [m] a car whose tail is less than this ahead of the nose is alongside
PATH_FREQUENCY = 2.0  # [1/s] sqrt of the tracking law's lateral stiffness (RACELINE_LATERAL_STIFFNESS)
_FAR = 1e9  # [m] an arc-length gap no car has: "none"


class Traffic(NamedTuple):
    """The other cars as car ``i`` sees them, ``(N,)`` each (its own entry is not ``present``).

    Attributes:
        ds: wrapped arc-length gap ``s_k - s_i`` [m], positive ahead.
        gap: bumper-to-bumper gap along the path [m], ``ds (1 - n_mid kappa_mid) - l_ik``.
        n, v, ax: the cars' lateral offsets [m], speeds [m/s], longitudinal accelerations [m/s^2].
        half_length: ``l_ik = (l_i + l_k) / 2`` [m]; half_width: ``w_ik = (w_i + w_k) / 2`` [m].
        present: racing, finite and not the driver itself.
        scale: the track's ``scale`` k (1 at full size, 0.1 on a 1:10 model): the rules'
            distances are k times the constants above, their speeds ``sqrt(k)`` times.
    """

    ds: jax.Array
    gap: jax.Array
    n: jax.Array
    v: jax.Array
    ax: jax.Array
    half_length: jax.Array
    half_width: jax.Array
    present: jax.Array
    scale: float = 1.0


def traffic(x: jax.Array, index: int, track: Track, lengths: jax.Array, widths: jax.Array,
            racing: jax.Array | None = None) -> Traffic:
    """The other cars of the joint state ``x (N, 6)`` seen from car ``index``; ``lengths``,
    ``widths`` the cars' footprints ``(N,)`` [m]; ``racing (N,)`` bool (None: all race): a
    car out of the race is frozen by the env and nobody collides with it."""
    num = x.shape[0]
    s, n = x[:, S], x[:, N_LAT]
    ds = track.wrap_ds(s - s[index])
    n_mid = 0.5 * (n + n[index])
    scale = 1.0 - n_mid * track.kappa_at(s[index] + 0.5 * ds)
    half_length = 0.5 * (lengths[index] + lengths)
    half_width = 0.5 * (widths[index] + widths)
    finite = jnp.all(jnp.isfinite(x), axis=1)
    present = finite & (jnp.arange(num) != index)
    if racing is not None:
        present = present & jnp.asarray(racing, dtype=bool)
    # cars not present get harmless finite numbers, so no NaN reaches a select's other branch
    clean = jnp.where(finite[:, None], x, 0.0)
    ds = jnp.where(present, ds, _FAR)
    gap = jnp.where(present, ds * scale - half_length, _FAR)
    return Traffic(ds=ds, gap=gap, n=clean[:, N_LAT], v=clean[:, V], ax=clean[:, AX], half_length=half_length,
                   half_width=half_width, present=present, scale=float(track.scale))


def reach(speed: jax.Array, standstill: float, length: jax.Array, scale: float = 1.0) -> jax.Array:
    """How far ahead [m] the driver looks for cars at ``speed`` [m/s]: ``TRAFFIC_LOOKAHEAD``
    seconds, plus its length, the standstill gap and ``TRAFFIC_REACH`` (times the track's
    ``scale``)."""
    return TRAFFIC_LOOKAHEAD * speed + length + standstill + TRAFFIC_REACH * scale


def path_offsets(cars: Traffic, own_n: jax.Array, own_target: jax.Array, target_at_cars: jax.Array,
                 speed: jax.Array) -> jax.Array:
    """How far [m] each car's centre is, laterally, from where the driver will be at that
    car's arc length: the target there plus the driver's present error ``own_n - own_target``
    decayed as the critically damped tracking law decays it over the time to get there
    (``(1 + w t) exp(-w t)``, ``t = ds / max(V, 1 m/s)``). ``(N,)``, absolute values."""
    t = jnp.maximum(cars.ds, 0.0) / jnp.maximum(speed, 1.0)
    wt = PATH_FREQUENCY * jnp.minimum(t, 60.0)
    decay = (1.0 + wt) * jnp.exp(-wt)
    return jnp.abs(cars.n - (target_at_cars + (own_n - own_target) * decay))


def on_path(cars: Traffic, offsets: jax.Array, look: jax.Array) -> jax.Array:
    """``(N,)`` bool: the cars ahead within ``look`` [m] whose centres are within
    ``w_ik + LATERAL_CLEARANCE`` of the driver's path (``offsets`` of :func:`path_offsets`)."""
    return cars.present & (cars.ds > 0.0) & (cars.ds < look) & (offsets < cars.half_width + LATERAL_CLEARANCE * cars.scale)


def following_acceleration(cars: Traffic, ahead: jax.Array, speed: jax.Array, time_gap: float,
                           standstill: float) -> jax.Array:
    """The largest longitudinal acceleration [m/s^2] the adaptive cruise allows behind the cars
    ``ahead (N,)`` bool (``+inf`` when there are none): for each, the smaller of

    * the time-gap law ``ax_k + k_v (v_k - V) + k_g (gap - standstill - time_gap V)``, and
    * while it closes in (``c = V - v_k > 0``), the constant deceleration
      ``min(ax_k, 0) - c^2 / (2 room)`` that brings the closing speed to zero within the
      ``room`` left of the gap above the standstill gap once the jerk-limited ramp
      (``FOLLOW_LAG`` seconds of closing) is taken off it (a leader that brakes is matched).

    ``speed`` is the driver's speed ``V >= 0`` [m/s]."""
    closing = jnp.maximum(speed - cars.v, 0.0)
    desired = standstill + time_gap * speed
    cruise = cars.ax + FOLLOW_SPEED_GAIN * (cars.v - speed) + FOLLOW_GAP_GAIN * (cars.gap - desired)
    room = jnp.maximum(cars.gap - standstill - FOLLOW_LAG * closing, 0.05 * cars.scale)
    brake = jnp.where(closing > 0.0, jnp.minimum(cars.ax, 0.0) - closing**2 / (2.0 * room), jnp.inf)
    return jnp.min(jnp.where(ahead, jnp.minimum(cruise, brake), jnp.inf))


class PassTarget(NamedTuple):
    """The passing decision: ``passing`` (bool), the lateral offset [m] to pass at, ``n``,
    and which car is passed, ``leader`` (an index; meaningless without ``passing``)."""

    passing: jax.Array
    n: jax.Array
    leader: jax.Array


def pass_target(cars: Traffic, on_line: jax.Array, line_speed_at_cars: jax.Array, own_s: jax.Array,
                own_n: jax.Array, look: jax.Array, track: Track, margin: float, standstill: float,
                speed: jax.Array) -> PassTarget:
    """Whether and where to pass the nearest car on the driver's line (``on_line (N,)`` bool).

    It is passed when it is slower than the line's speed at its place
    (``line_speed_at_cars (N,)`` [m/s]) by ``PASS_SPEED_MARGIN`` and its bumper gap is within
    ``standstill + PASS_LOOKAHEAD * speed`` (the driver's ``speed`` [m/s]), on the side (left or right
    of it, ``w_ik + PASS_CLEARANCE`` from its centre) that keeps the driver's centre ``margin``
    [m] inside the boundaries at the driver, at the car and a car's length beyond, and in
    whose lane no other car is, from ``standstill`` [m] behind the driver's tail to ``look``
    ahead. Of two such sides: the one with more room beside the car, each counted with
    ``PASS_COMMITMENT`` times the driver's own offset towards it (so a pass once begun keeps
    its side)."""
    leader = jnp.argmin(jnp.where(on_line, cars.ds, jnp.inf))
    has_leader = jnp.any(on_line)
    slower = cars.v[leader] < line_speed_at_cars[leader] - PASS_SPEED_MARGIN * np.sqrt(cars.scale)
    near = cars.gap[leader] < standstill + PASS_LOOKAHEAD * np.sqrt(cars.scale) * speed
    n_leader, s_leader = cars.n[leader], own_s + cars.ds[leader]
    clearance = cars.half_width[leader] + PASS_CLEARANCE * cars.scale
    samples = jnp.stack([own_s, s_leader, s_leader + 2.0 * cars.half_length[leader]])
    left_edge = jnp.min(track.width_left_at(samples)) - margin
    right_edge = jnp.min(track.width_right_at(samples)) - margin
    others = cars.present & (jnp.arange(cars.ds.shape[0]) != leader)
    lane = others & (cars.ds > -(cars.half_length + standstill)) & (cars.ds < look)

    def side(sign):
        n_pass = n_leader + sign * clearance
        inside = sign * n_pass <= jnp.where(sign > 0, left_edge, right_edge)
        clear = ~jnp.any(lane & (jnp.abs(cars.n - n_pass) < cars.half_width + PASS_CLEARANCE * cars.scale))
        room = jnp.where(sign > 0, track.width_left_at(s_leader) - n_leader, track.width_right_at(s_leader) + n_leader)
        return n_pass, inside & clear, room + PASS_COMMITMENT * sign * (own_n - n_leader)

    n_left, left_ok, left_score = side(1.0)
    n_right, right_ok, right_score = side(-1.0)
    go_left = left_ok & (~right_ok | (left_score >= right_score))
    passing = has_leader & slower & near & (left_ok | right_ok)
    return PassTarget(passing=passing, n=jnp.where(go_left, n_left, n_right), leader=leader)


class Alongside(NamedTuple):
    """The cars beside the driver (``beside (N,)`` bool) and the lateral offsets ``lower``,
    ``upper`` [m] its target keeps to so as not to move across into them (``-inf``, ``+inf``
    where none is on that side)."""

    beside: jax.Array
    lower: jax.Array
    upper: jax.Array


def alongside(cars: Traffic, own_n: jax.Array, standstill: float) -> Alongside:
    """The cars beside the driver: overlapping it in arc length, up to ``ALONGSIDE_AHEAD``
    ahead of its nose and ``standstill`` [m] behind its tail, except those nose to tail in
    its lane (which the adaptive cruise keeps a gap to). Its lateral target keeps
    ``w_ik + ALONGSIDE_CLEARANCE`` from each of their centres, on the side each is on."""
    dn = cars.n - own_n
    in_lane = (jnp.abs(dn) < cars.half_width) & (jnp.abs(cars.ds) >= cars.half_length)
    beside = cars.present & (cars.ds > -(cars.half_length + standstill)) & \
        (cars.ds < cars.half_length + ALONGSIDE_AHEAD * cars.scale) & ~in_lane
    keep = cars.half_width + ALONGSIDE_CLEARANCE * cars.scale
    upper = jnp.min(jnp.where(beside & (dn >= 0.0), cars.n - keep, jnp.inf))
    lower = jnp.max(jnp.where(beside & (dn < 0.0), cars.n + keep, -jnp.inf))
    return Alongside(beside=beside, lower=lower, upper=upper)
