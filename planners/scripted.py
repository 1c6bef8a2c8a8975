"""Scripted baseline drivers: a lane-keeping controller, a constant-speed cruiser and a
racing-line driver (:class:`RacelineDriver`: the circuit's racing line at the speed profile of
its lap-time limit, with the rules in traffic of :mod:`planners.traffic`).

They read the joint state (full information, like the planners) and return normalised
jerk actions in ``[-1, 1]^2``. These are the control laws alone, callables
``driver(observation, joint_state) -> action``: :mod:`planners.agents.scripted` makes them
agents, and :mod:`planners.prediction` drives predicted opponents with them. The lateral law makes the lateral offset behave like a
critically damped second-order system around a target offset; the longitudinal law tracks a
target speed capped by the tightest curve in a preview window.

:func:`jax_policy` (and :func:`lane_keeping_policy`, :func:`constant_speed_policy`) gives the
same laws as pure JAX functions of the joint state, to be jitted into a compiled env step and
vmapped over the races of a batch (:mod:`planners.agents.batched`).
"""

from __future__ import annotations

from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from planners import traffic
from planners.methods import CONSTANT_SPEED, LANE_KEEPING
from planners.traffic import RACELINE_STANDSTILL, RACELINE_TIME_GAP
from racing_env.dynamics import MIN_FRENET_SCALE
from racing_env.precision import default_float
from racing_env.track import Track
from racing_env.vehicle import VehicleParams

LATERAL_STIFFNESS = 1.0  # [1/s^2] n'' = k_p (n_target - n) - k_d n'
LATERAL_DAMPING = 2.0  # [1/s] critical damping for k_p = 1
ACCEL_GAIN = 5.0  # [1/s] jerk = gain * (a_desired - a)
SPEED_GAIN = 1.5  # [1/s] ax_desired = gain * (v_target - V)
GRIP_MARGIN = 0.75  # fraction of rho(V) used for cornering
PREVIEW_TIME = 3.0  # [s] look-ahead for the curve speed limit
PREVIEW_POINTS = 16  # curvature samples over the look-ahead
_PREVIEW_INDEX = np.arange(PREVIEW_POINTS, dtype=np.float64)


def _preview_offsets(reach: float) -> np.ndarray:
    """``np.linspace(0, reach, PREVIEW_POINTS)`` [m] with the same arithmetic (index times
    step, the end point set exactly), without its per-call overhead."""
    offsets = _PREVIEW_INDEX * (reach / (PREVIEW_POINTS - 1))
    offsets[-1] = reach
    return offsets


def _curvature_grid(track: Track) -> tuple[np.ndarray, np.ndarray]:
    """Arc lengths and curvatures for ``np.interp``; on a closed track, wrapped, sorted and
    padded by one point each side, once per controller, where ``np.interp(..., period=length)``
    would prepare them again on every call."""
    s, kappa = np.asarray(track.s, dtype=np.float64), np.asarray(track.kappa, dtype=np.float64)
    if not track.closed:
        return s, kappa
    period = track.length
    s = s % period
    order = np.argsort(s)
    s, kappa = s[order], kappa[order]
    return np.concatenate((s[-1:] - period, s, s[:1] + period)), np.concatenate((kappa[-1:], kappa, kappa[:1]))


def check_targets(target_speed: float | None = None, target_n: float = 0.0) -> None:
    """Refuse a cruise speed that is not finite and positive (``None``: the car's v_max) and
    a lateral offset that is not finite (a NaN target would make every action NaN)."""
    if target_speed is not None and not 0 < float(target_speed) < np.inf:
        raise ValueError(f"target_speed must be a finite speed > 0 m/s, got {target_speed!r}")
    if not np.isfinite(float(target_n)):
        raise ValueError(f"target_n must be a finite lateral offset [m], got {target_n!r}")


class LaneKeeping:
    """Follows a lateral offset ``target_n`` [m] at ``target_speed`` [m/s] (default: v_max).

    Args:
        track: the track raced on.
        index: the car this controller drives (row of the joint state).
        vehicle: that car's parameters (limits and jerk scaling).
        target_speed: cruise speed; ``None`` tracks the car's v_max.
        target_n: lateral offset to hold [m], positive to the left.
    """

    name = LANE_KEEPING

    def __init__(
        self,
        track: Track,
        index: int,
        vehicle: VehicleParams = VehicleParams(),
        target_speed: float | None = None,
        target_n: float = 0.0,
    ) -> None:
        check_targets(target_speed, target_n)
        self.track, self.index, self.vehicle = track, int(index), vehicle
        self.target_speed = float(vehicle.v_max if target_speed is None else target_speed)
        self.target_n = float(target_n)
        self._jerk_max = np.array([float(vehicle.jx_max), float(vehicle.jy_max)])
        self._c_drag = float(vehicle.c_drag)
        self._kappa_s, self._kappa_values = _curvature_grid(track)

    def _kappa(self, s: np.ndarray) -> np.ndarray:
        if self.track.closed:
            # The double wrap is np.interp's own periodic normalisation of the wrapped s.
            period = self.track.length
            return np.interp(np.mod(s, period) % period, self._kappa_s, self._kappa_values)
        return np.interp(s, self._kappa_s, self._kappa_values)

    def __call__(self, observation: np.ndarray | None, joint_state: np.ndarray) -> np.ndarray:
        # Scalar work in scalars: np.linspace and np.clip on a few numbers cost more than the
        # arithmetic; every value equals the array form (tests/test_agents.py checks it).
        s, v, n, chi, ax, ay = np.asarray(joint_state, dtype=float)[self.index]
        v_pos = max(v, 0.0)
        reach = max(v_pos, 5.0) * PREVIEW_TIME
        kappa_ahead = self._kappa(s + _preview_offsets(reach))  # kappa_ahead[0] is at s itself
        kappa_max = float(np.max(np.abs(kappa_ahead)))
        rho = float(self.vehicle.rho(v_pos))
        v_curve = np.sqrt(GRIP_MARGIN * rho / max(kappa_max, 1e-6))
        v_target = min(self.target_speed, v_curve)
        ax_des = min(max(SPEED_GAIN * (v_target - v), -GRIP_MARGIN * rho), float(self.vehicle.ax_max(v_pos)))
        ax_des += self._c_drag * v_pos * v_pos  # the drive that holds the speed against still-air drag
        n_rate = v * np.sin(chi)
        ay_des = kappa_ahead[0] * v**2 + LATERAL_STIFFNESS * (self.target_n - n) - LATERAL_DAMPING * n_rate
        jx, jy = ACCEL_GAIN * (ax_des - ax) / self._jerk_max[0], ACCEL_GAIN * (ay_des - ay) / self._jerk_max[1]
        return np.array([min(max(jx, -1.0), 1.0), min(max(jy, -1.0), 1.0)], dtype=np.float32)


class ConstantSpeed(LaneKeeping):
    """Cruises on the centre line at a constant ``target_speed`` (slowing only for curves)."""

    name = CONSTANT_SPEED

    def __init__(self, track: Track, index: int, vehicle: VehicleParams = VehicleParams(), target_speed: float = 15.0):
        super().__init__(track, index, vehicle, target_speed=target_speed, target_n=0.0)


# --------------------------------------------------------------------------------------
# The same laws in JAX, for batched races (racing_env.vector) and compiled env steps.
# --------------------------------------------------------------------------------------

BRAKE_ACTION = (-0.5, 0.0)
"""The normalised action a scripted driver's JAX law returns where its law is not finite:
the constant braking action of :meth:`planners.agents.BaseAgent._safe_action` for a car
whose own state is not finite (the only way the law gives a non-finite action)."""


def jax_curvature(controller: LaneKeeping) -> Callable[[jnp.ndarray], jnp.ndarray]:
    """``kappa(s)`` [1/m] of a controller's prepared curvature grid, in JAX, as ``np.interp``
    computes it: the same segment (the last grid point at or below ``s``), the same slope
    ``(f[j+1] - f[j]) / (x[j+1] - x[j])`` and ``slope * (s - x[j]) + f[j]``, ``f[j]`` at a
    grid point, the end values beyond the ends (open tracks). On a closed track ``s`` is
    wrapped twice as :meth:`LaneKeeping._kappa` wraps it. ``s``: any shape [m], finite.

    XLA:CPU fuses the multiply-add into one rounding (FMA) where NumPy rounds twice, so a
    value may differ from ``np.interp``'s by one ulp."""
    xp = np.asarray(controller._kappa_s, dtype=np.float64)
    fp = np.asarray(controller._kappa_values, dtype=np.float64)
    slopes = (fp[1:] - fp[:-1]) / (xp[1:] - xp[:-1])
    closed, period = bool(controller.track.closed), float(controller.track.length)
    last = xp.shape[0] - 1

    def kappa(s):
        s = jnp.asarray(s, dtype=default_float())
        x_grid, f_grid, slope = jnp.asarray(xp), jnp.asarray(fp), jnp.asarray(slopes)
        if closed:
            s = jnp.mod(jnp.mod(s, period), period)
        j = jnp.clip(jnp.searchsorted(x_grid, s, side="right") - 1, 0, last - 1)
        inside = jnp.where(s == x_grid[j], f_grid[j], slope[j] * (s - x_grid[j]) + f_grid[j])
        return jnp.where(s < xp[0], fp[0], jnp.where(s >= xp[last], fp[last], inside))

    return kappa


def jax_policy(controller: LaneKeeping) -> Callable[[jnp.ndarray], jnp.ndarray]:
    """The law of a :class:`LaneKeeping` (or :class:`ConstantSpeed`) controller as a pure JAX
    function ``policy(x (N, 6)) -> action (2,)``: normalised jerks in ``[-1, 1]``, in JAX's widest
    float (float64; float32 where the user turned ``jax_enable_x64`` off).

    The same IEEE operations in the same order as ``controller(observation, x)`` (the
    curvature preview by :func:`jax_curvature`), except that XLA fuses multiply-adds into
    one rounding and has its own ``sin`` (each within an ulp), and that the output stays
    float64 where the NumPy law rounds it to float32. On the law's magnitudes (``kappa V^2``
    and accelerations up to ~100 m/s^2, scaled by ``ACCEL_GAIN / jerk_max`` = 5 / 30 by default)
    those ulps are ~1e-14 in the normalised action. A non-finite law (a car whose own state is not finite) gives
    :data:`BRAKE_ACTION`, so the function never returns NaN. Jit it, ``vmap`` it over races.
    """
    if hasattr(controller, "jax_law"):  # a driver with its own JAX law (RacelineDriver)
        return controller.jax_law()
    index = controller.index
    kappa = jax_curvature(controller)
    vehicle = controller.vehicle
    target_speed, target_n = float(controller.target_speed), float(controller.target_n)
    jx_max, jy_max = (float(j) for j in controller._jerk_max)

    def policy(x):
        # JAX's widest float when traced: float64 with jax_enable_x64 on, float32 with it off
        dtype = default_float()
        preview_index = jnp.asarray(_PREVIEW_INDEX, dtype)
        brake = jnp.asarray(BRAKE_ACTION, dtype=dtype)
        s, v, n, chi, ax, ay = (jnp.asarray(x, dtype=dtype)[index, k] for k in range(6))
        v_pos = jnp.maximum(v, 0.0)
        reach = jnp.maximum(v_pos, 5.0) * PREVIEW_TIME
        offsets = (preview_index * (reach / (PREVIEW_POINTS - 1))).at[-1].set(reach)
        kappa_ahead = kappa(s + offsets)
        kappa_max = jnp.max(jnp.abs(kappa_ahead))
        rho = vehicle.rho(v_pos)
        v_curve = jnp.sqrt(GRIP_MARGIN * rho / jnp.maximum(kappa_max, 1e-6))
        v_target = jnp.minimum(target_speed, v_curve)
        ax_des = jnp.minimum(jnp.maximum(SPEED_GAIN * (v_target - v), -GRIP_MARGIN * rho), vehicle.ax_max(v_pos))
        ax_des = ax_des + vehicle.c_drag * v_pos * v_pos
        n_rate = v * jnp.sin(chi)
        ay_des = kappa_ahead[0] * v**2 + LATERAL_STIFFNESS * (target_n - n) - LATERAL_DAMPING * n_rate
        jx, jy = ACCEL_GAIN * (ax_des - ax) / jx_max, ACCEL_GAIN * (ay_des - ay) / jy_max
        action = jnp.clip(jnp.stack([jx, jy]), -1.0, 1.0)
        return jnp.where(jnp.all(jnp.isfinite(action)), action, brake)

    return policy


def lane_keeping_policy(track: Track, index: int, vehicle: VehicleParams = VehicleParams(),
                        target_speed: float | None = None,
                        target_n: float = 0.0) -> Callable[[jnp.ndarray], jnp.ndarray]:
    """:func:`jax_policy` of ``LaneKeeping(track, index, vehicle, target_speed, target_n)``."""
    return jax_policy(LaneKeeping(track, index, vehicle, target_speed=target_speed, target_n=target_n))


def constant_speed_policy(track: Track, index: int, vehicle: VehicleParams = VehicleParams(),
                          target_speed: float = 15.0) -> Callable[[jnp.ndarray], jnp.ndarray]:
    """:func:`jax_policy` of ``ConstantSpeed(track, index, vehicle, target_speed)``."""
    return jax_policy(ConstantSpeed(track, index, vehicle, target_speed=target_speed))


# --------------------------------------------------------------------------------------
# The racing-line driver.
# --------------------------------------------------------------------------------------

RACELINE_LATERAL_STIFFNESS = 4.0  # [1/s^2] e'' = -k_p e - k_d e' on the lateral error e = n - n_ref
RACELINE_LATERAL_DAMPING = 4.0  # [1/s] critical damping for k_p = 4
RACELINE_SPEED_GAIN = 2.0  # [1/s] ax_desired = ax_ref + gain * (v_ref - V)
RACELINE_ACCEL_GAIN = 6.0  # [1/s] jerk = gain * (a_desired - a), clipped to the jerk limits
RACELINE_PREVIEW = 1.0 / RACELINE_ACCEL_GAIN  # [s] the line's curvature is read this far ahead: the acceleration lag
RACELINE_SPEED_PREVIEW = 0.4  # [s] speeds and accelerations are read this far ahead: the jerk-limited ramp into braking
RACELINE_MARGIN = 1.25  # [m] the line is kept this far inside the boundaries (half a car's width)
RACELINE_OVERSPEED = 2.0  # [m/s] this much faster than the profile, braking takes the grip before turning
RACELINE_ERROR_CAP = 2.0  # [m] the lateral error the stiffness acts on is capped here (the start, a pass)
#: [s] times ahead at the driver's speed at which a path off the line (held off it, or thrown) is read for its corners
RACELINE_PATH_PREVIEW = tuple(np.linspace(0.0, 4.0, 9))
RACELINE_PATH_BRAKING = 0.7  # share of the grip the driver counts on to brake for a corner of such a path
RACELINE_OFF_LINE = 1.0  # [m] farther than this from its target the car drives its own path, not the line


def check_raceline_options(pace: float = 1.0, margin: float = RACELINE_MARGIN, line: str = "raceline",
                           yielding: bool = True, time_gap: float = RACELINE_TIME_GAP,
                           standstill: float = RACELINE_STANDSTILL) -> None:
    """Refuse a pace outside ``(0, 1]``, a negative or non-finite margin [m], an unknown line,
    a ``yielding`` that is not a bool, a time gap [s] that is not finite and >= 0 and a
    standstill gap [m] that is not finite and > 0."""
    if not 0.0 < float(pace) <= 1.0:
        raise ValueError(f"pace must be in (0, 1] (a fraction of the limit's speed), got {pace!r}")
    if not (np.isfinite(float(margin)) and float(margin) >= 0.0):
        raise ValueError(f"margin must be a finite distance >= 0 m, got {margin!r}")
    if line not in ("raceline", "centerline"):
        raise ValueError(f"line must be 'raceline' or 'centerline', got {line!r}")
    if not isinstance(yielding, (bool, np.bool_)):
        raise ValueError(f"yield must be true (the rules: keep a gap, pass where clear) or false (drive the line "
                         f"whoever is on it), got {yielding!r}")
    if not (np.isfinite(float(time_gap)) and float(time_gap) >= 0.0):
        raise ValueError(f"time_gap must be a finite time >= 0 s (the gap kept to a car ahead), got {time_gap!r}")
    if not (np.isfinite(float(standstill)) and float(standstill) > 0.0):
        raise ValueError(f"standstill must be a finite distance > 0 m (the gap kept behind a car ahead at rest), "
                         f"got {standstill!r}")


class _LineTables(NamedTuple):
    """The line on the track's grid ``(M,)``: offset ``n`` [m], heading ``chi`` [rad],
    curvature ``kappa`` [1/m], speed ``v`` [m/s] and acceleration ``ax`` [m/s^2] (pace applied)."""

    n: jax.Array
    chi: jax.Array
    kappa: jax.Array
    v: jax.Array
    ax: jax.Array


class RacelineDriver:
    """Follows a racing line at the speed profile of its lap-time limit, scaled by ``pace``, and
    (``yielding``, the default) keeps to the rules of :mod:`planners.traffic` in traffic.

    The line is the circuit's shipped racing line (``line="raceline"``; the centre line on
    tracks that ship none: the built-in ones), its points kept ``margin`` [m] inside the
    boundaries before its fit (:func:`racing_env.limits.racing_line`); the speeds and accelerations are the car's own quasi-steady-state profile on
    it (:func:`racing_env.limits.speed_profile`), times ``pace`` (accelerations times
    ``pace**2``). The law, in JAX (:meth:`jax_law`):

    * lateral: ``ay = kappa_line(s') V^2 - k_p (n - n_target) - k_d V (sin chi - sin chi_ref(s))``,
      the line's curvature read ``RACELINE_PREVIEW`` ahead (``s' = s + V * preview``); the
      target is the line ``n_ref(s)`` unless the rules say otherwise;
    * longitudinal: ``ax = ax_ref(s') + k_v (v_ref(s') - V)``, at most what the adaptive
      cruise allows, within ``ax_max(V)`` and the gg room the lateral demand leaves (the
      lateral acceleration comes first);
    * jerks ``gain * (a_desired - a)``, normalised by the car's jerk limits and clipped to
      ``[-1, 1]``: the controller never asks for more jerk than the car has.

    The rules (:mod:`planners.traffic`): behind a car on its path it keeps ``standstill`` [m]
    plus ``time_gap`` [s] of its speed, braking within its own limits; it passes a slower car
    on its line only on a side with room where no other car is; it never moves across into a
    car alongside. With no car near they change nothing: alone it drives exactly the line.
    ``yielding=False`` is the driver without them, which drives its line whoever is on it
    (robustness tests of the planners: a rival that does not avoid them).

    Args:
        track: the track raced on.
        index: the car this controller drives (row of the joint state).
        vehicle: that car's parameters.
        pace: fraction of the limit's speed, in ``(0, 1]``.
        margin: how far inside the boundaries the line (and a pass) is kept [m], at the circuit's full
            size (on a model at scale k, k times it: racing_env.track.scaled).
        line: ``"raceline"`` or ``"centerline"``.
        yielding: keep to the rules (True) or drive the line whoever is on it (False).
        time_gap: the time gap [s] kept to a car ahead on its path, >= 0.
        standstill: the bumper-to-bumper gap [m] kept behind a car ahead, > 0, at the circuit's full
            size (on a model, scale times it, as ``margin``).
        fleet: every car's parameters, stacked ``(N,)`` fields (the footprints of the others);
            None: every car is the size of this one.
    """

    name = "raceline"

    def __init__(self, track: Track, index: int, vehicle: VehicleParams = VehicleParams(), pace: float = 1.0,
                 margin: float = RACELINE_MARGIN, line: str = "raceline", yielding: bool = True,
                 time_gap: float = RACELINE_TIME_GAP, standstill: float = RACELINE_STANDSTILL,
                 fleet: VehicleParams | None = None) -> None:
        from racing_env import limits

        check_raceline_options(pace, margin, line, yielding, time_gap, standstill)
        self.track, self.index, self.vehicle = track, int(index), vehicle
        # the margin is at the circuit's full size: a model at scale k keeps k times it
        self.pace, self.margin = float(pace), float(margin) * track.scale
        self.yielding, self.time_gap = bool(yielding), float(time_gap)
        self.standstill = float(standstill) * track.scale  # at full size too
        self.fleet = fleet
        use_raceline = line == "raceline" and limits.has_raceline(track)
        self.line_name = "raceline" if use_raceline else "centerline"
        racing_line = limits.get_line(track, self.line_name, margin=self.margin) if use_raceline else \
            limits.centerline(track)
        # open tracks: no start constraint (the profile is the lateral and braking limits ahead)
        profile = limits.speed_profile(racing_line, vehicle, v_start=None if track.closed else float(vehicle.v_max))
        self.profile = profile
        width_left, width_right = np.asarray(track.width_left), np.asarray(track.width_right)
        # the fitted line may still touch the margin by the fit's few centimetres
        self._n_ref = np.clip(racing_line.n, -(width_right - self.margin), width_left - self.margin)
        self._chi_ref = np.asarray(racing_line.chi)
        self._kappa = np.asarray(racing_line.kappa)
        self._v_ref = self.pace * profile.v
        self._ax_ref = self.pace**2 * profile.ax
        self._jerk_max = np.array([float(vehicle.jx_max), float(vehicle.jy_max)])
        self._law = None

    def _footprints(self, num_cars: int, dtype) -> tuple[jax.Array, jax.Array]:
        """Every car's length and width ``(N,)`` [m]: the fleet's, or this car's for all."""
        source = self.vehicle if self.fleet is None else self.fleet
        return tuple(jnp.broadcast_to(jnp.asarray(getattr(source, k), dtype), (num_cars,)) for k in ("length", "width"))

    def _rules(self, x: jax.Array, racing: jax.Array | None, tables: _LineTables, s: jax.Array, n: jax.Array,
               speed: jax.Array, n_ref: jax.Array) -> tuple[jax.Array, jax.Array, jax.Array]:
        """The lateral target [m], whether traffic moved it off the line (a pass or a car
        alongside), and the largest longitudinal acceleration [m/s^2] the rules of
        :mod:`planners.traffic` allow at the joint state ``x (N, 6)``: the line ``n_ref``,
        False and ``+inf`` exactly when no car is near."""
        track, margin, standstill = self.track, self.margin, self.standstill
        lengths, widths = self._footprints(x.shape[0], x.dtype)
        cars = traffic.traffic(x, self.index, track, lengths, widths, racing)
        look = traffic.reach(speed, standstill, lengths[self.index], track.scale)
        s_cars = s + cars.ds
        line_at_cars = track._interp(tables.n, s_cars)
        on_line = traffic.on_path(cars, traffic.path_offsets(cars, n, n_ref, line_at_cars, speed), look)
        decision = traffic.pass_target(cars, on_line, track._interp(tables.v, s_cars), s, n, look, track, margin,
                                       standstill, speed)
        side = traffic.alongside(cars, n, standstill)
        wanted = jnp.where(decision.passing, decision.n, n_ref)
        held = jnp.minimum(jnp.maximum(wanted, side.lower), side.upper)
        on_track = jnp.clip(held, -(track.width_right_at(s) - margin), track.width_left_at(s) - margin)
        adjusted = decision.passing | jnp.any(side.beside)
        n_target = jnp.where(adjusted, on_track, n_ref)
        # the path: the target held beside the cars alongside, the pass or the line elsewhere
        target_at_cars = jnp.where(side.beside, n_target, jnp.where(decision.passing, decision.n, line_at_cars))
        ahead = traffic.on_path(cars, traffic.path_offsets(cars, n, n_target, target_at_cars, speed), look)
        return n_target, adjusted, traffic.following_acceleration(cars, ahead, speed, self.time_gap, standstill)

    def _path_speed(self, s: jax.Array, speed: jax.Array, offset: jax.Array, time_scale: float) -> jax.Array:
        """The highest speed [m/s] from which the car can still take the corners of the path at
        the constant ``offset`` [m] from the centre line, read at :data:`RACELINE_PATH_PREVIEW`
        seconds ahead at ``speed``: at each point ``d`` ahead, ``sqrt(v_c^2 + 2 b d)`` with the
        corner speed ``v_c = sqrt(rho / |kappa_path|)`` (the grip at it, with downforce, found in
        two passes) and ``b`` the share :data:`RACELINE_PATH_BRAKING` of that grip."""
        track, vehicle = self.track, self.vehicle
        ahead = speed * jnp.asarray(RACELINE_PATH_PREVIEW, speed.dtype) * time_scale
        kappa = track.kappa_at(s + ahead).astype(speed.dtype)
        path = jnp.abs(kappa) / jnp.maximum(1.0 - offset * kappa, MIN_FRENET_SCALE)
        path = jnp.maximum(path, 1e-9)
        corner = jnp.sqrt(vehicle.rho(speed) / path)
        corner = jnp.sqrt(vehicle.rho(jnp.minimum(corner, speed)) / path)
        braking = RACELINE_PATH_BRAKING * vehicle.rho(corner)
        return jnp.min(jnp.sqrt(corner**2 + 2.0 * braking * ahead))

    def jax_law(self) -> Callable[..., jnp.ndarray]:
        """The law as a pure JAX function ``policy(x (N, 6), racing=None) -> action (2,)``:
        normalised jerks in ``[-1, 1]``, float64 (float32 with ``jax_enable_x64`` off);
        :data:`BRAKE_ACTION` where the car's own state is not finite. ``racing (N,)`` bool
        marks the cars still racing (None: all; the env freezes a car out of the race, and
        nobody collides with it). Jit it, ``vmap`` it over races."""
        track, index, vehicle = self.track, self.index, self.vehicle
        arrays = _LineTables(n=self._n_ref, chi=self._chi_ref, kappa=self._kappa, v=self._v_ref, ax=self._ax_ref)
        jx_max, jy_max = (float(j) for j in self._jerk_max)
        # on a model at scale k the law's times scale as sqrt(k) (Froude: equal accelerations,
        # lengths k times, speeds sqrt(k) times): its gains [1/s] divided by it, its stiffness
        # [1/s^2] by k, its previews [s] times it; exactly 1 at full size
        time_scale = float(np.sqrt(track.scale))

        def policy(x, racing=None):
            # JAX's widest float when traced: float64 with jax_enable_x64 on, float32 with it off
            dtype = default_float()
            tables = _LineTables(*(jnp.asarray(v, dtype) for v in arrays))
            brake = jnp.asarray(BRAKE_ACTION, dtype=dtype)
            x = jnp.asarray(x, dtype=dtype)
            s, v, n, chi, ax, ay = (x[index, k] for k in range(6))
            v_pos = jnp.maximum(v, 0.0)
            ahead = s + v_pos * RACELINE_PREVIEW * time_scale
            ahead_v = s + v_pos * RACELINE_SPEED_PREVIEW * time_scale
            n_ref = track._interp(tables.n, s)
            chi_ref = track._interp(tables.chi, s)
            n_target, kappa_ahead = n_ref, track._interp(tables.kappa, ahead)
            if self.yielding:
                n_target, adjusted, ax_cap = self._rules(x, racing, tables, s, n, v_pos, n_ref)
                # a target traffic holds is an offset from the centre line, not from the line:
                # damp the speed across the track and feed the centre line's curvature
                # forward, or the car drifts on with the line's own lateral motion into a car
                # it is held beside
                chi_ref = jnp.where(adjusted, jnp.zeros_like(chi_ref), chi_ref)
                kappa_ahead = jnp.where(adjusted, track.kappa_at(ahead).astype(dtype), kappa_ahead)
            cap = RACELINE_ERROR_CAP * track.scale
            lateral_error = jnp.clip(n - n_target, -cap, cap)
            error_rate = v * (jnp.sin(chi) - jnp.sin(chi_ref))
            ay_des = (kappa_ahead * v**2 - RACELINE_LATERAL_STIFFNESS / time_scale**2 * lateral_error
                      - RACELINE_LATERAL_DAMPING / time_scale * error_rate)
            rho = vehicle.rho(v_pos)
            ax_des = (track._interp(tables.ax, ahead_v)
                      + RACELINE_SPEED_GAIN / time_scale * (track._interp(tables.v, ahead_v) - v))
            if self.yielding:
                ax_des = jnp.minimum(ax_des, ax_cap)
            # off its line (held off it by traffic, or thrown off it by a pass or a contact) the
            # car drives a path at about a constant offset from the centre line, whose curvature
            # kappa / (1 - n kappa) the line's speeds may be too fast for: it brakes to what the
            # corners ahead allow, at its own offset and at its target's
            off_line = jnp.abs(n - n_target) > RACELINE_OFF_LINE * track.scale
            if self.yielding:
                off_line = off_line | adjusted
            path_speed = jnp.where(off_line, jnp.minimum(self._path_speed(s, v_pos, n, time_scale),
                                                         self._path_speed(s, v_pos, n_target, time_scale)), jnp.inf)
            ax_des = jnp.minimum(ax_des, RACELINE_SPEED_GAIN / time_scale * (path_speed - v))
            # faster than the profile where it is: the braking it asks for keeps a share of the
            # grip (growing with the excess), or a car at the lateral limit could not slow down
            excess = jnp.maximum(v - track._interp(tables.v, s), v - path_speed)
            share = jnp.clip(excess / (RACELINE_OVERSPEED * np.sqrt(track.scale)), 0.0, 1.0)
            reserve = jnp.minimum(jnp.maximum(-ax_des, 0.0), share * rho)
            lateral = jnp.where(reserve > 0, jnp.sqrt(jnp.maximum((rho - reserve) * (rho + reserve), 0.0)), rho)
            ay_des = jnp.clip(ay_des, -lateral, lateral)
            # (rho - |ay|)(rho + |ay|), not rho^2 - ay^2: at the gg limit the factor is exactly 0,
            # where the difference of squares leaves a rounding error (with or without a fused
            # multiply-add) whose square root is ~1e-7 m/s^2
            room = jnp.sqrt(jnp.maximum((rho - jnp.abs(ay_des)) * (rho + jnp.abs(ay_des)), 0.0))
            # the tyres' share: the net acceleration plus the still-air drag it overcomes
            ax_des = jnp.clip(ax_des + vehicle.c_drag * v_pos * v_pos, -room, jnp.minimum(room, vehicle.drive_max(v_pos)))
            jx = RACELINE_ACCEL_GAIN / time_scale * (ax_des - ax) / jx_max
            jy = RACELINE_ACCEL_GAIN / time_scale * (ay_des - ay) / jy_max
            action = jnp.clip(jnp.stack([jx, jy]), -1.0, 1.0)
            return jnp.where(jnp.all(jnp.isfinite(action)), action, brake)

        policy.takes_racing = True  # the vectorised env hands it the race's racing flags
        return policy

    def __call__(self, observation: np.ndarray | None, joint_state: np.ndarray,
                 racing: np.ndarray | None = None) -> np.ndarray:
        """The action ``(2,)`` float32 at ``joint_state (N, 6)``, the cars still racing ``racing
        (N,)`` bool (None: all); the observation is not read."""
        if self._law is None:
            self._law = jax.jit(self.jax_law())
        racing = np.ones(np.shape(joint_state)[0], dtype=bool) if racing is None else np.asarray(racing, dtype=bool)
        return np.asarray(self._law(np.asarray(joint_state, dtype=np.float64), racing), dtype=np.float32)
