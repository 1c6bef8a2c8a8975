"""The physical limit of a circuit: racing lines and the quasi-steady-state lap time.

A :class:`RacingLine` is a path on a track given by its lateral offset ``n(s)`` [m] on the
track's arc-length grid, with the geometry the Frenet point mass (:mod:`racing_env.dynamics`)
needs to follow it: the heading relative to the centre line ``chi(s)``, the path's own arc
length ``sigma(s)`` and curvature ``kappa_line(s)``. With ``a = 1 - n kappa``:

    chi = atan2(n', a)        dsigma/ds = sqrt(a^2 + n'^2)        kappa_line = (kappa + chi') / (dsigma/ds)

(``'`` is ``d/ds``; for the centre line ``n = 0`` these are ``0``, ``1`` and ``kappa``).
:func:`line_from_offset` builds one from ``n(s)``; :func:`centerline` is the centre line;
:func:`racing_line` reads the racing line of a shipped circuit (or any file of rows
``x_m, y_m``), takes its own arc length and curvature from a periodic smoothing spline of its
points, and places it on the track's Frenet frame (``n(s)``, ``chi(s)``).

:func:`speed_profile` is the quasi-steady-state (QSS) speed profile of a car along a line,
the fastest the point mass can drive it within its limits (:class:`VehicleParams`: the
same ``ax_max(V)`` and ``rho(V)``, formula or table, as the environment and the planners):

* lateral: ``|kappa_line| V^2 <= rho(V)`` and ``V <= v_max``;
* drive: ``dV/dt <= min(ax_max(V), sqrt(rho(V)^2 - ay^2) - c_drag V^2)`` (forward pass);
* braking: ``-dV/dt <= sqrt(rho(V)^2 - ay^2) + c_drag V^2`` (backward pass; the environment
  brakes the tyres at most at ``rho``).

A car with drag (``c_drag > 0``, :mod:`racing_env.dynamics`) accelerates at what its tyres
deliver, at most ``drive_max(V) = ax_max(V) + c_drag V^2`` and within the gg room, less the
drag, and the drag helps it brake (as in TUMFTM's ``calc_vel_profile``, where the machines'
limit and the tyres' are reduced by the drag forwards and increased by it backwards). The
profile is a lone car's, in still air: no slipstream. Without drag the terms are zero and the
profile is the paper car's.

The turn limit ``|ay| <= V^2 / min_turn_radius`` is not part of the profile: it binds below
about 8 m/s only, and a line tighter than the turning radius (Shanghai's hairpin, whose centre
line turns at 4.8 m for a few metres) cannot be followed at any speed, so the profile there is
the gg limit alone.

Each pass integrates ``w = V^2`` in the line's arc length (``dw/dsigma = 2 ax``) with
classical Runge-Kutta steps between grid points and clips ``w`` to the lateral limit; at the
lateral limit, where the gg room's square root is not smooth, a step is also kept within the
mean of its ends' limits (so no step's mean acceleration leaves the gg circle). The profile
is the smaller of the two. On a closed track the passes start at the slowest
corner and run two laps, so the profile is periodic (a flying lap); on an open track the car
starts at ``v_start`` (default 0) at ``s = 0``. The time of a segment is ``2 dsigma /
(V_k + V_{k+1})`` (exact under constant acceleration). :func:`lap_time_limit` is the
profile's lap time. Everything here is NumPy on arrays of the track's grid.
"""

from __future__ import annotations

import bisect
import dataclasses
import functools
import math
import os
from pathlib import Path

import numpy as np

from racing_env.dynamics import MIN_FRENET_SCALE
from racing_env.track import Track, circuit_name, circuit_names, raceline_path, read_csv_rows
from racing_env.vehicle import VehicleParams

#: Positional noise [m] assumed by the racing line's smoothing spline (``from_centerline``).
RACELINE_SMOOTHING = 0.1
#: How far [m] a racing-line point may lie beyond a boundary of the fitted track before the
#: file is refused: the track's centre line is a smoothing spline of the measured one
#: (``DEFAULT_SMOOTHING`` = 0.3 m), so its boundaries move by a few centimetres to decimetres.
RACELINE_TOLERANCE = 0.3
#: Where a racing line comes nearer the centre line's centre of curvature than this
#: ``1 - n kappa``, it is blended back to the centre line over BLEND_DISTANCE [m] either side.
FRENET_LIMIT = 0.3
BLEND_DISTANCE = 30.0
#: The lines :func:`lap_time_limit` takes by name.
LINES = ("raceline", "centerline")


@dataclasses.dataclass(frozen=True, eq=False)
class RacingLine:
    """A path on a track as the lateral offset ``n(s)``, on the track's grid ``(M,)``.

    Attributes:
        track: the track.
        n: ``(M,)`` lateral offset [m] (left positive) at ``track.s``.
        chi: ``(M,)`` heading of the line relative to the centre line [rad].
        sigma: ``(M,)`` arc length along the line at ``track.s`` [m], ``sigma[0] = 0``.
        kappa: ``(M,)`` curvature of the line [1/m], positive for left turns.
        length: the line's length [m]: once round a closed track, ``sigma[-1]`` on an open one.
        name: ``"raceline"``, ``"centerline"`` or a description.
    """

    track: Track
    n: np.ndarray
    chi: np.ndarray
    sigma: np.ndarray
    kappa: np.ndarray
    length: float
    name: str = "line"


def _periodic_gradient(values: np.ndarray, ds: float, closed: bool) -> np.ndarray:
    if closed:
        return (np.roll(values, -1) - np.roll(values, 1)) / (2.0 * ds)
    return np.gradient(values, ds)


def line_from_offset(
    track: Track, n: np.ndarray, dn: np.ndarray | None = None, ddn: np.ndarray | None = None,
    name: str = "line",
) -> RacingLine:
    """The :class:`RacingLine` of lateral offsets ``n (M,)`` [m] on the track's grid.

    ``dn = n'`` and ``ddn = n''`` (per metre of ``s``, ``(M,)``) are taken from finite
    differences of ``n`` unless given (a spline gives them exactly). ``kappa'`` of the centre
    line is a central difference on the grid.

    Raises:
        ValueError: for arrays not of the grid's shape or not finite, or a line beyond a
            centre of curvature (``1 - n kappa <= 0``).
    """
    m, ds = track.num_points, track.ds
    n = np.asarray(n, dtype=np.float64)
    dn = _periodic_gradient(n, ds, track.closed) if dn is None else np.asarray(dn, dtype=np.float64)
    ddn = _periodic_gradient(dn, ds, track.closed) if ddn is None else np.asarray(ddn, dtype=np.float64)
    for label, a in (("n", n), ("dn", dn), ("ddn", ddn)):
        if a.shape != (m,):
            raise ValueError(f"line_from_offset: {label} must have the track grid's shape ({m},), got {a.shape}")
        if not np.all(np.isfinite(a)):
            raise ValueError(f"line_from_offset: {label} must be finite")
    kappa = np.asarray(track.kappa)
    dkappa = _periodic_gradient(kappa, ds, track.closed)
    a = 1.0 - n * kappa
    if np.any(a <= 0):
        k = int(np.argmin(a))
        raise ValueError(f"line_from_offset: the line at s = {track.s[k]:.1f} m lies beyond the centre of "
                         f"curvature (n = {n[k]:.2f} m, kappa = {kappa[k]:.4f} 1/m)")
    da = -(dn * kappa + n * dkappa)
    stretch = np.sqrt(a**2 + dn**2)
    chi = np.arctan2(dn, a)
    dchi = (ddn * a - dn * da) / stretch**2
    line_kappa = (kappa + dchi) / stretch
    # Arc length by the trapezoid rule on the grid (closed: the last segment closes the loop).
    seg = 0.5 * (stretch + np.roll(stretch, -1)) * ds
    if not track.closed:
        seg = seg[:-1]
    sigma = np.concatenate([[0.0], np.cumsum(seg)])
    length = float(sigma[-1])
    return RacingLine(track=track, n=n, chi=chi, sigma=sigma[:m], kappa=line_kappa, length=length, name=name)


def centerline(track: Track) -> RacingLine:
    """The centre line ``n = 0`` as a :class:`RacingLine` (its curvature is the track's)."""
    zeros = np.zeros(track.num_points)
    return line_from_offset(track, zeros, zeros, zeros, name="centerline")


def _read_xy(path: Path) -> np.ndarray:
    rows = [row for _, row in read_csv_rows(path, ("x_m", "y_m"), extra_columns=True)]
    if len(rows) < 10:
        raise ValueError(f"{path}: a racing line needs at least 10 points, got {len(rows)}")
    return np.asarray(rows, dtype=np.float64)


def _project_along(track: Track, xy: np.ndarray, expected: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Frenet ``(s, n)`` of a path's points ``xy (P, 2)`` in driving order, each point looked
    up near where the path should be (so a figure-eight's crossing cannot send a point to
    the other leg): near ``expected (P,)`` [m] where given, else near the previous point plus
    the step between them. ``s`` is unwrapped: it grows along the path."""
    s_exact, n_exact = track.from_cartesian(xy[:, 0], xy[:, 1])
    m, ds, length = track.num_points, track.ds, track.length
    if expected is not None:  # vectorised: the exact inverse where it lands near the expected s
        offset = s_exact - expected
        if track.closed:
            offset = (offset + 0.5 * length) % length - 0.5 * length
        agree = np.abs(offset) <= 20.0
        s_out = np.where(agree, expected + offset, np.nan)
        n_out = np.where(agree, n_exact, np.nan)
        todo = np.flatnonzero(~agree)
        guesses = expected
    else:
        s_out, n_out = np.full(len(xy), np.nan), np.full(len(xy), np.nan)
        todo = np.arange(len(xy))
        guesses = None
    grid = np.stack([np.asarray(track.x), np.asarray(track.y)], axis=-1)
    window = np.arange(-60, 61)
    steps = np.concatenate([[0.0], np.hypot(*np.diff(xy, axis=0).T)])
    s_prev = float(s_exact[0])
    for i in todo:
        p = xy[i]
        if guesses is not None:
            guess = float(guesses[i])
        else:
            guess = s_prev + steps[i] if i else s_prev
        idx = int(round(guess / ds)) + window
        idx_wrapped = idx % m if track.closed else np.clip(idx, 0, m - 1)
        k = idx[int(np.argmin(np.sum((grid[idx_wrapped] - p) ** 2, axis=1)))]
        near = k * ds
        # The exact inverse where it agrees with the local search (it is continuous there).
        offset = float(s_exact[i]) - near
        if track.closed:
            offset = (offset + 0.5 * length) % length - 0.5 * length
        if abs(offset) <= 3.0 * ds:
            s_out[i], n_out[i] = near + offset, n_exact[i]
        else:  # the nearest grid point of the window, offset along its normal
            kk = k % m if track.closed else int(np.clip(k, 0, m - 1))
            heading = float(track.heading[kk])
            d = p - grid[kk]
            s_out[i] = k * ds + d[0] * math.cos(heading) + d[1] * math.sin(heading)
            n_out[i] = -d[0] * math.sin(heading) + d[1] * math.cos(heading)
        s_prev = float(s_out[i])
    return s_out, n_out


def racing_line(
    track: Track, path: str | os.PathLike | None = None, smoothing: float = RACELINE_SMOOTHING,
    tolerance: float = RACELINE_TOLERANCE, margin: float = 0.0,
) -> RacingLine:
    """A racing line (rows ``x_m, y_m``) on a closed track, as a :class:`RacingLine`.

    ``path`` defaults to the shipped racing line of the circuit the track is named after
    (``track.name``, as :func:`racing_env.track.circuit` names them). The points are fitted
    by a periodic cubic smoothing spline (positional noise ``smoothing`` [m], as
    :func:`racing_env.track.from_centerline` fits centre lines), which gives the line's own
    arc length and curvature; its points are then placed on the track's Frenet frame in
    driving order (a figure-eight's crossing cannot send them to the other leg) and
    everything is resampled onto the track's grid. Where the line passes beyond the centre
    line's centre of curvature (``1 - n kappa < FRENET_LIMIT``; only Norisring's hairpin, whose
    inner boundary does too) the track's Frenet frame has no place for it, and the line is
    blended back to the centre line there, smoothly over ``BLEND_DISTANCE`` either side.
    ``margin`` [m] > 0 first moves points closer than that to a boundary back to ``margin``
    inside it (a driver that needs room to track the line; the fit smooths the corners).

    Raises:
        ValueError: for an open track; a track with no shipped racing line and no ``path``;
            points farther than ``tolerance`` [m] beyond a boundary (naming the distance and
            where); a line that does not go once round the track in its direction, or that
            comes nearer the centre line's centre of curvature than the Frenet frame allows.
    """
    if not track.closed:
        raise ValueError(f"racing_line: {track.name!r} is an open track; racing lines are for closed circuits")
    if path is None and track.scale != 1.0:  # a circuit's model: its full-size line, scaled
        return _scaled_raceline(track, margin)
    if path is None:
        if circuit_name(track.name) is None:
            raise ValueError(f"no racing line is shipped for track {track.name!r}: pass path= (rows x_m,y_m) "
                             f"or use the centre line; the shipped circuits are {circuit_names()}")
        path = raceline_path(track.name)
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"racing line file not found: {path}")
    xy = _read_xy(path)
    if np.hypot(*(xy[-1] - xy[0])) < 1e-9:
        xy = xy[:-1]
    s, n = _project_along(track, xy)
    advance = s[-1] - s[0] + np.hypot(*(xy[0] - xy[-1]))
    if not 0.9 * track.length < advance < 1.1 * track.length:
        raise ValueError(f"{path}: the line advances {advance:.0f} m along the {track.length:.0f} m track "
                         f"{track.name!r}; a racing line goes once round it in the driving direction")
    if np.any(np.diff(s) <= 0):
        k = int(np.argmax(np.diff(s) <= 0))
        raise ValueError(f"{path}: points {k} and {k + 1} do not advance along track {track.name!r}")
    width_left = np.interp(s, track.s, track.width_left, period=track.length)
    width_right = np.interp(s, track.s, track.width_right, period=track.length)
    beyond = np.maximum(n - width_left, -n - width_right)
    worst = int(np.argmax(beyond))
    if beyond[worst] > tolerance:
        raise ValueError(
            f"{path}: the racing line does not fit track {track.name!r}: point {worst} "
            f"(x = {xy[worst, 0]:.1f} m, y = {xy[worst, 1]:.1f} m, s = {s[worst] % track.length:.1f} m) lies "
            f"{beyond[worst]:.2f} m beyond the {'left' if n[worst] > 0 else 'right'} boundary "
            f"(at most {tolerance:g} m allowed)")
    # The line's own geometry from a smoothing spline of its points (well conditioned where
    # the centre line's Frenet frame is not, in hairpins wider than their radius), then
    # its grid points' places on the track, and everything resampled onto the track's grid.
    from racing_env.track import from_centerline

    if not (np.isfinite(margin) and margin >= 0):
        raise ValueError(f"racing_line: margin must be a distance >= 0 m, got {margin!r}")
    if margin > 0:
        pulled = np.clip(n, -(width_right - margin), width_left - margin)
        if np.any(pulled != n):
            n = pulled
            x_new, y_new, _ = track.to_cartesian(s, n)
            xy = np.stack([x_new, y_new], axis=-1)
    # Where the line passes beyond the centre line's centre of curvature (Norisring's hairpin,
    # whose inner boundary does too) the Frenet frame of the track has no place for it: there
    # the line is blended back to the centre line, smoothly over BLEND_DISTANCE either side.
    # (checked on the track's grid, whose curvature peaks the line's points may straddle)
    spacing = float(np.mean(np.hypot(*np.diff(xy, axis=0).T)))
    grid_s = np.asarray(track.s)
    n_grid = np.interp(grid_s, s % track.length, n, period=track.length)
    bad_grid = (1.0 - n_grid * np.asarray(track.kappa) < FRENET_LIMIT).astype(float)
    bad_s = grid_s[bad_grid > 0]
    gap = np.abs((s[:, None] % track.length) - bad_s[None, :]) if bad_s.size else np.zeros((len(s), 0))
    gap = np.minimum(gap, track.length - gap)
    degenerate = np.any(gap <= spacing, axis=1) if bad_s.size else np.zeros(len(s), dtype=bool)
    if np.any(degenerate):
        half = max(1, int(round(BLEND_DISTANCE / spacing)))
        idx = np.flatnonzero(degenerate)
        weight = np.zeros(len(xy))
        for k in idx:  # 1 within +-half points of a degenerate one, then a linear ramp
            for j in range(-2 * half, 2 * half + 1):
                w = 1.0 if abs(j) <= half else 1.0 - (abs(j) - half) / half
                weight[(k + j) % len(xy)] = max(weight[(k + j) % len(xy)], w)
        n = n * (1.0 - weight)
        x_new, y_new, _ = track.to_cartesian(s, n)
        xy = np.stack([x_new, y_new], axis=-1)
    ones = np.ones(len(xy))
    own = from_centerline(xy[:, 0], xy[:, 1], ones, ones, closed=True, ds=0.5 * track.ds,
                          smoothing=smoothing, name=track.name)
    # The fit's points lie between the file's, whose places are known: look them up there.
    spans = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(np.vstack([xy, xy[:1]]), axis=0).T))])
    expected = np.interp(np.asarray(own.s) / own.length * spans[-1], spans, np.append(s, s[0] + track.length))
    own_s, own_n = _project_along(track, np.stack([own.x, own.y], axis=-1), expected)
    if np.any(np.diff(own_s) <= 0):
        k = int(np.argmax(np.diff(own_s) <= 0))
        raise ValueError(f"{path}: the line turns back along track {track.name!r} near s = "
                         f"{own_s[k] % track.length:.1f} m")
    # own_s grows from own_s[0] by about one lap; close it with the first point one lap on.
    own_s = np.append(own_s, own_s[0] + track.length)
    sigma_own = np.append(np.asarray(own.s), own.length)
    grid = np.asarray(track.s)
    grid_u = own_s[0] + (grid - own_s[0]) % track.length  # the grid in own_s's range
    sigma = np.interp(grid_u, own_s, sigma_own)
    n = np.interp(grid_u, own_s, np.append(own_n, own_n[0]))
    kappa = np.interp(grid_u, own_s, np.append(own.kappa, own.kappa[0]))
    heading = np.interp(grid_u, own_s, np.append(own.heading, own.heading[0] + 2 * np.pi * round(
        (own.heading[-1] - own.heading[0]) / (2 * np.pi))))
    chi = (heading - np.asarray(track.heading) + np.pi) % (2 * np.pi) - np.pi
    first = int(np.argmin(grid))  # sigma from s = 0
    sigma = (sigma - sigma[first]) % own.length
    a = 1.0 - n * np.asarray(track.kappa)
    if np.any(a <= MIN_FRENET_SCALE):
        k = int(np.argmin(a))
        raise ValueError(f"{path}: the line at s = {grid[k]:.1f} m lies too near the centre line's centre of "
                         f"curvature for the Frenet frame (n = {n[k]:.2f} m, 1 - n kappa = {a[k]:.3f})")
    return RacingLine(track=track, n=n, chi=chi, sigma=sigma, kappa=kappa, length=float(own.length),
                      name="raceline" if margin == 0 else f"raceline, {margin:g} m inside")


@functools.lru_cache(maxsize=64)
def _shipped_raceline(track: Track, margin: float) -> RacingLine:
    if track.scale != 1.0:
        return _scaled_raceline(track, margin)
    return racing_line(track, margin=margin)


def _scaled_raceline(track: Track, margin: float) -> RacingLine:
    """The shipped racing line of a circuit's scaled model (:func:`racing_env.track.scaled`):
    the full-size circuit's line ``margin / scale`` inside its boundaries, every length times
    the scale, on the model's grid (the same points)."""
    from racing_env.track import circuit

    if circuit_name(track.name) is None:
        raise ValueError(f"no racing line is shipped for track {track.name!r} (at scale {track.scale:g}): use the "
                         f"centre line; the shipped circuits are {circuit_names()}")
    full = circuit(track.name)
    if full.num_points != track.num_points or not np.isclose(full.length * track.scale, track.length):
        raise ValueError(f"track {track.name!r} at scale {track.scale:g} is not the shipped circuit's model "
                         "(build it with racing_env.track.circuit(name, scale) or scaled(circuit(name), scale))")
    line = _shipped_raceline(full, margin / track.scale)
    k = track.scale
    return RacingLine(track=track, n=line.n * k, chi=line.chi, sigma=line.sigma * k, kappa=line.kappa / k,
                      length=line.length * k, name=line.name)


def get_line(track: Track, line: str | RacingLine = "raceline", margin: float = 0.0) -> RacingLine:
    """``line`` on ``track``: a :class:`RacingLine` as it is, ``"centerline"``, or
    ``"raceline"`` (the shipped racing line of the circuit, ``margin`` [m] inside the
    boundaries: see :func:`racing_line`; cached per track and margin).

    Raises:
        ValueError: for another name (listing :data:`LINES`) or a track with no racing line.
    """
    if isinstance(line, RacingLine):
        if line.track is not track:
            raise ValueError("get_line: the RacingLine was built on another track")
        return line
    if line == "centerline":
        return centerline(track)
    if line == "raceline":
        return _shipped_raceline(track, float(margin))
    raise ValueError(f"unknown line {line!r}: expected one of {list(LINES)} or a RacingLine")


def has_raceline(track: Track) -> bool:
    """Whether a racing line is shipped for ``track`` (a closed track named after a circuit)."""
    return track.closed and circuit_name(track.name) is not None


@dataclasses.dataclass(frozen=True, eq=False)
class SpeedProfile:
    """The quasi-steady-state speed profile of a car along a :class:`RacingLine`.

    Attributes:
        line: the line.
        v: ``(M,)`` speed [m/s] at the grid points.
        ax: ``(M,)`` longitudinal acceleration [m/s^2] (``dw/dsigma / 2``, central differences).
        ay: ``(M,)`` lateral acceleration ``kappa_line v^2`` [m/s^2].
        t: ``(M,)`` time [s] at the grid points from ``t[0] = 0``.
        lap_time: time [s] once round a closed track (to the end of an open one).
    """

    line: RacingLine
    v: np.ndarray
    ax: np.ndarray
    ay: np.ndarray
    t: np.ndarray
    lap_time: float


def check_vehicle(vehicle: VehicleParams) -> None:
    """Refuse a vehicle whose limits are not positive numbers, or a stacked one (a lap-time
    limit is one car's)."""
    for name in ("v_max", "ax_max_0", "rho_0", "min_turn_radius"):
        value = np.asarray(getattr(vehicle, name), dtype=float)
        if value.shape != () or not (np.isfinite(value) and value > 0):
            raise ValueError(f"the lap-time limit needs one car with {name} > 0, got {name}={getattr(vehicle, name)!r}")
    rho_aero = np.asarray(vehicle.rho_aero, dtype=float)
    if rho_aero.shape != () or not (np.isfinite(rho_aero) and rho_aero >= 0):
        raise ValueError(f"the lap-time limit needs one car with rho_aero >= 0, got {vehicle.rho_aero!r}")
    if vehicle.table is not None and np.ndim(vehicle.table.speeds) != 1:
        raise ValueError(f"the lap-time limit needs one car, got a stacked limit table of shape "
                         f"{np.shape(vehicle.table.speeds)}")


@dataclasses.dataclass(frozen=True)
class _Curve:
    """One car's limits as functions of ``w = V^2`` on plain floats: the piecewise-linear
    functions of :class:`racing_env.vehicle.LimitTable` (the formula as its two-point table),
    for the profile's scalar loops."""

    knots: tuple[float, ...]    # (K,) w at the table's speeds [m^2/s^2]
    ax: tuple[float, ...]       # (K,) drive limit [m/s^2]
    rho: tuple[float, ...]      # (K,) gg radius [m/s^2]

    @staticmethod
    def of(vehicle: VehicleParams) -> "_Curve":
        table = vehicle.as_table().table
        speeds = np.asarray(table.speeds, dtype=float)
        return _Curve(tuple((speeds**2).tolist()), tuple(np.asarray(table.ax_max, dtype=float).tolist()),
                      tuple(np.asarray(table.rho, dtype=float).tolist()))

    def segment(self, w: float) -> int:
        return min(max(bisect.bisect_right(self.knots, w) - 1, 0), len(self.knots) - 2)

    def at(self, values: tuple[float, ...], w: float) -> float:
        k = self.segment(w)
        w0, w1 = self.knots[k], self.knots[k + 1]
        return values[k] + (values[k + 1] - values[k]) / (w1 - w0) * (w - w0)

    def lateral_limit(self, kappa: np.ndarray) -> np.ndarray:
        """The largest ``w`` with ``|kappa| w <= rho(w)`` at each curvature ``(M,)``: the first
        zero of ``|kappa| w - rho(w)`` (negative at ``w = 0``), ``inf`` where it has none."""
        knots, rho = np.asarray(self.knots), np.asarray(self.rho)
        k = np.abs(np.asarray(kappa, dtype=float))[:, None]
        g = k * knots[None, :] - rho[None, :]          # (M, K); g[:, 0] = -rho(0) < 0
        over = g >= 0
        first = np.argmax(over, axis=1)               # first knot at or past the limit (0: none)
        inside = over.any(axis=1) & (first > 0)
        j = np.maximum(first, 1)
        rows = np.arange(len(k))
        g0, g1 = g[rows, j - 1], g[rows, j]
        w_in = knots[j - 1] + (-g0) * (knots[j] - knots[j - 1]) / np.where(inside, g1 - g0, 1.0)
        # beyond the last knot: g continues with the slope |kappa| - (rho's last slope)
        slope = k[:, 0] - (rho[-1] - rho[-2]) / (knots[-1] - knots[-2])
        with np.errstate(divide="ignore", invalid="ignore"):
            w_out = np.where(slope > 0, knots[-1] - g[:, -1] / np.where(slope > 0, slope, 1.0), np.inf)
        return np.where(inside, w_in, w_out)


def speed_profile(line: RacingLine, vehicle: VehicleParams = VehicleParams(),
                  v_start: float | None = None) -> SpeedProfile:
    """The QSS speed profile of ``vehicle`` along ``line`` (see the module docstring).

    Args:
        line: the path.
        vehicle: one car's limits (scalars).
        v_start: speed [m/s] at ``s = 0``: on a closed track ``None`` (default) is the flying
            lap (a periodic profile); a number starts the lap at that speed (a standing or
            rolling start) and ends it flying. Open tracks start at ``v_start`` or 0.

    Raises:
        ValueError: for a vehicle whose limits are not positive or a negative ``v_start``.
    """
    check_vehicle(vehicle)  # (min_turn_radius is not used: see the module docstring)
    if v_start is not None and not (np.isfinite(v_start) and v_start >= 0):
        raise ValueError(f"v_start must be a speed >= 0 m/s or None, got {v_start!r}")
    track = line.track
    closed = track.closed
    v_max = float(vehicle.v_max)
    curve = _Curve.of(vehicle)
    kappa = np.abs(line.kappa)
    w_cap = v_max**2
    w_lat = np.minimum(curve.lateral_limit(kappa), w_cap)
    m = track.num_points
    seg = np.diff(line.sigma) if not closed else np.diff(np.append(line.sigma, line.length))
    ax_values, rho_values = curve.ax, curve.rho

    c_drag = float(vehicle.c_drag)

    def drive(w: float, k: float) -> float:
        v2 = max(w, 0.0)
        rho = curve.at(rho_values, v2)
        room = rho * rho - (k * v2) ** 2
        return 2.0 * min(curve.at(ax_values, v2), (math.sqrt(room) if room > 0 else 0.0) - c_drag * v2)

    def brake(w: float, k: float) -> float:
        v2 = max(w, 0.0)
        rho = curve.at(rho_values, v2)
        room = rho * rho - (k * v2) ** 2
        return 2.0 * ((math.sqrt(room) if room > 0 else 0.0) + c_drag * v2)

    def rk4(f, w: float, k0: float, k1: float, h: float) -> float:
        km = 0.5 * (k0 + k1)
        d1 = f(w, k0)
        d2 = f(w + 0.5 * h * d1, km)
        d3 = f(w + 0.5 * h * d2, km)
        d4 = f(w + h * d3, k1)
        return w + h / 6.0 * (d1 + 2.0 * d2 + 2.0 * d3 + d4)

    def step(f, w: float, k0: float, k1: float, h: float, cap: float) -> float:
        """One RK4 step, capped at ``cap``; where the step's mean slope exceeds the mean of its
        ends' limits (the square root of the gg room is not smooth where it reaches zero, at
        the lateral limit), the largest ``x`` with ``x <= w + h (f(w) + f(x)) / 2`` instead."""
        x = min(rk4(f, w, k0, k1, h), cap)
        f0 = f(w, k0)
        if x <= w + 0.5 * h * (f0 + f(x, k1)) + 1e-12 * abs(x):
            return x
        lo, hi = w, x  # x - w - h (f0 + f(x)) / 2 is increasing in x where f decreases
        for _ in range(60):
            mid = 0.5 * (lo + hi)
            if mid <= w + 0.5 * h * (f0 + f(mid, k1)):
                lo = mid
            else:
                hi = mid
        return lo

    kap = kappa.tolist()
    lat = w_lat.tolist()
    hs = seg.tolist()

    def forward(start: int, w0: float, count: int) -> list[float]:
        out = [0.0] * m
        w, i = w0, start
        out[i] = w
        for _ in range(count):
            j = (i + 1) % m
            w = step(drive, w, kap[i], kap[j], hs[i], lat[j])
            out[j] = w
            i = j
        return out

    def backward(start: int, w0: float, count: int) -> list[float]:
        out = [0.0] * m
        w, j = w0, start
        out[j] = w
        for _ in range(count):
            i = (j - 1) % m
            w = step(brake, w, kap[j], kap[i], hs[i], lat[i])
            out[i] = w
            j = i
        return out

    if closed:
        slowest = int(np.argmin(w_lat))
        if v_start is None:
            fwd = forward(slowest, lat[slowest], 2 * m)
        else:
            fwd = forward(0, min(float(v_start) ** 2, lat[0]), m - 1)
        bwd = backward(slowest, lat[slowest], 2 * m)
    else:
        w0 = 0.0 if v_start is None else min(float(v_start) ** 2, lat[0])
        fwd = forward(0, w0, m - 1)
        bwd = backward(m - 1, lat[m - 1], m - 1)
    w = np.minimum(np.asarray(fwd), np.asarray(bwd))
    if not closed or v_start is not None:
        w[0] = fwd[0]
    v = np.sqrt(np.maximum(w, 0.0))
    nxt = np.roll(v, -1) if closed else v[1:]
    pairs = v + nxt if closed else v[:-1] + nxt
    with np.errstate(divide="ignore"):
        dt = np.where(pairs > 0, 2.0 * seg / np.maximum(pairs, 1e-300), np.inf)
    if closed and v_start is not None:  # the lap ends back at s = 0 on the flying profile
        w_end = min(step(drive, float(w[-1]), kap[-1], kap[0], hs[-1], lat[0]), bwd[0])
        dt[-1] = 2.0 * seg[-1] / (v[-1] + math.sqrt(max(w_end, 0.0)))
    t = np.concatenate([[0.0], np.cumsum(dt)])
    lap_time = float(t[-1])
    sigma = np.append(line.sigma, line.length) if closed else line.sigma
    ww = np.append(w, w[0]) if closed else w
    slope = np.diff(ww) / np.diff(sigma)  # dw/dsigma per segment
    before = np.roll(slope, 1) if closed else np.concatenate([[slope[0]], slope])
    after = slope if closed else np.concatenate([slope, [slope[-1]]])
    ax = 0.25 * (before + after)
    return SpeedProfile(line=line, v=v, ax=ax, ay=line.kappa * w, t=t[:m], lap_time=lap_time)


def lap_time_limit(track: Track | str, vehicle: VehicleParams = VehicleParams(),
                   line: str | RacingLine = "raceline", v_start: float | None = None) -> float:
    """The quasi-steady-state lap time [s] of ``vehicle`` on ``line`` of ``track``: the
    fastest lap the point mass can drive on that line within its limits (a flying lap on a
    closed track; see :func:`speed_profile`).

    Args:
        track: a :class:`Track` or a name :func:`racing_env.track.get_track` resolves.
        vehicle: one car's limits.
        line: ``"raceline"`` (the shipped racing line of the circuit), ``"centerline"`` or a
            :class:`RacingLine` of the track.
        v_start: ``None`` for a flying lap, or the speed [m/s] at the start line.

    Raises:
        ValueError: for an unknown line, a track without a shipped racing line with
            ``line="raceline"``, or a vehicle whose limits are not positive.
    """
    from racing_env.track import get_track

    track = get_track(track)
    return speed_profile(get_line(track, line), vehicle, v_start=v_start).lap_time


def reference_lap_time(track: Track, vehicle: VehicleParams = VehicleParams()) -> tuple[float, str] | None:
    """The lap-time limit a result is compared with, and its line: on the racing line where
    one is shipped (a real circuit), else on the centre line; ``None`` on an open track."""
    if not track.closed:
        return None
    line = "raceline" if has_raceline(track) else "centerline"
    return lap_time_limit(track, vehicle, line=line), line


@functools.lru_cache(maxsize=256)
def _cached_reference(track: Track, vehicle_key: tuple) -> tuple[float, str] | None:
    return reference_lap_time(track, VehicleParams.from_key(vehicle_key))


def race_limit(track: Track, vehicle: VehicleParams, laps: int, race_distance: float | None = None
               ) -> tuple[float, str] | None:
    """The lap-time limit of a race of ``laps`` whole laps on a closed track, ``laps`` times the
    flying lap of :func:`reference_lap_time` (the racing line where one is shipped, else the
    centre line), and its line; ``None`` for an open track or a race to a ``race_distance``.
    Cached per track and car. A race from the grid's rolling start (about 15 m/s) is a few
    tenths of a second slower than flying laps at the limit (0.7 s at Monza)."""
    if race_distance is not None or not track.closed:
        return None
    reference = _cached_reference(track, vehicle.key())
    if reference is None:
        return None
    lap, line = reference
    return laps * lap, line
